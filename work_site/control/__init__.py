"""The work site's robot control (§III-A, §VI-B).

Today: closed-form kinematics (:mod:`work_site.control.kinematics`). To come: trajectories,
guarded moves, impedance control and the execution monitor (issue 5).
"""
