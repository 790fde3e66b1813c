"""Why an operator's task did not succeed, in kinds a person and a benchmark can count."""

from __future__ import annotations

FAILURES = (
    "not_recognised",
    "no_grasp",
    "infeasible",
    "program_refused",
    "execution_failed",
    "goal_missed",
)
"""Why a run did not succeed, as its result's ``failure.kind`` says."""


class RunError(RuntimeError):
    """A run that cannot go on: ``kind`` is one of :data:`FAILURES`, the message says why."""

    def __init__(self, kind: str, message: str) -> None:
        if kind not in FAILURES:
            raise ValueError(f"unknown failure kind {kind!r}")
        super().__init__(message)
        self.kind = kind
