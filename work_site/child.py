"""The work site's child processes (the camera renderer, vision): their threads, their
priority, their stop."""

from __future__ import annotations

import multiprocessing as mp
import os
from multiprocessing.connection import Connection
from pathlib import Path

TERMINATE_WAIT_S = 5.0
"""How long a terminated child is waited for before the parent goes on."""

BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
"""The environment variables that set numpy's BLAS threads, read when numpy is imported: a
child doing one core's work is started with them at 1."""

CHILD_NICENESS = 10
"""How much less CPU priority the camera renderer and vision take than the control loop: on a
loaded machine the loop, its stops and the operator's heartbeats come first, and a frame or a
recognition waits (a starved loop hears the dead-man's heartbeats late and stops the robot)."""
AUTOGROUP = Path("/proc/self/autogroup")


def yield_to_control() -> None:
    """Lower this child process's CPU priority by :data:`CHILD_NICENESS` (called first thing
    in the child), and take it out of the work site's share of the machine.

    Linux shares the CPU between sessions first (autogroups) and by niceness only within one:
    a niced child in the work site's session still spends the session's share, and on a loaded
    machine the loop's threads (the one that reads the heartbeats among them) then wait for
    other sessions' turns. A session of its own, niced as a whole, spends only what the
    others leave. The parent stops the child through its pipe, as before; a terminal's Ctrl-C
    reaches the parent alone."""
    os.nice(CHILD_NICENESS)
    if AUTOGROUP.exists():
        os.setsid()
        try:
            AUTOGROUP.write_text(f"{CHILD_NICENESS}\n")
        except OSError:  # a kernel that does not let a session lower its own priority
            pass


def stop_child(proc: mp.process.BaseProcess, conn: Connection, ask: bool, grace_s: float) -> None:
    """Stop ``proc``: when ``ask``, send it ``None`` down ``conn`` (its sign to exit) and wait
    ``grace_s`` for it; a child still alive then is terminated. ``conn`` is closed."""
    if ask:
        try:
            conn.send(None)
        except (BrokenPipeError, OSError):
            pass  # the child is gone already
        proc.join(timeout=grace_s)
    if proc.is_alive():
        proc.terminate()
        proc.join(timeout=TERMINATE_WAIT_S)
    conn.close()
