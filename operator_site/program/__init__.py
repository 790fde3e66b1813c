"""The program generator (§VI): from the operator's simulated task to a robot motion program.

Today: :func:`pick_and_place`, the straight program (grasp, lift, carry, lower, release) with
no path deformation and no contact states; the deformation of §VI-A comes with issue 6.
"""

from operator_site.program.pick_place import choose_grasp_yaw, pick_and_place

__all__ = ["choose_grasp_yaw", "pick_and_place"]
