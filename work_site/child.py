"""Stopping the work site's child processes (the camera renderer, vision)."""

from __future__ import annotations

import multiprocessing as mp
from multiprocessing.connection import Connection

TERMINATE_WAIT_S = 5.0
"""How long a terminated child is waited for before the parent goes on."""


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
