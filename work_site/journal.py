"""The program journal's writer: lines appended and flushed by a thread of its own, so that the
control loop never waits for the disk."""

from __future__ import annotations

import json
import logging
import queue
import threading
from pathlib import Path

log = logging.getLogger("work-site")

WRITE_BATCH = 256
"""Lines written at most before each flush."""


def journal_line(program_id: str, payload: bytes) -> str:
    """One journal line: a program id and one of its encoded reports."""
    return json.dumps({"program_id": program_id, "report": payload.hex()}) + "\n"


class JournalWriter:
    """Appends :func:`journal_line`s to ``path`` on its own thread; :meth:`append` never
    blocks. :meth:`close` writes what is queued and closes the file."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._file = path.open("a")
        self._queue: queue.SimpleQueue[str | None] = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._run, name="journal", daemon=True)
        self._thread.start()

    def append(self, program_id: str, payload: bytes) -> None:
        self._queue.put(journal_line(program_id, payload))

    def _run(self) -> None:
        closing = False
        while not closing:
            lines = [self._queue.get()]
            for _ in range(WRITE_BATCH - 1):  # whatever else is queued, in one flush
                try:
                    lines.append(self._queue.get_nowait())
                except queue.Empty:
                    break
            if None in lines:
                closing = True
                lines = [line for line in lines if line is not None]
            try:
                self._file.writelines(lines)
                self._file.flush()
            except OSError:
                log.exception("could not write the program journal %s", self.path)

    def close(self) -> None:
        if self._thread.is_alive():
            self._queue.put(None)
            self._thread.join()
        self._file.close()
