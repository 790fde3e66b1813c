"""The work site's robot control (§III-A, §VI-B).

- :mod:`.kinematics`: closed-form inverse kinematics of the Puma-type arm (every solution, the
  nearest one) and its Jacobian;
- :mod:`.trajectory`: spatially-linear Cartesian moves with trapezoidal timing;
- :mod:`.controller`: the 100 Hz task controller over the 1 kHz joint servos, with guarded moves,
  position-based impedance (admittance) for contact moves and the hard force limit;
- :mod:`.sensing`: the wrist force sensor, read as the external force on the hand with the held
  block's weight removed;
- :mod:`.executor`: the execution monitor: a motion program checked whole before any motion,
  then executed command by command with a report for each step, contacts verified by force.
"""
