"""The check before sending: every segment between program targets swept against the
model, and the program refused with a reason if anything would collide or a required contact
would be lost.

A segment is the robot's spatially-linear move between two targets: the workpiece's centre of
mass on a straight line, its rotation about a fixed axis (:func:`poses.interpolate`; the work
site moves the TCP, which differs from this only while turning, by at most the turn times the
TCP's offset from the centre, a few tenths of a millimetre for our turns).

The sweep's bound: with distance d to everything that is in contact at neither end of the
segment, no point of the workpiece can reach it before the next sample if the sample is less
than d − floor further on (conservative advancement, exact: every point moves at most
|Δc| + θ·r_max per unit of the segment). Objects in contact at an end are touched by design,
so for them the samples are at most ``contact_sample_m`` of point travel apart and each must be
more than the barrier floor away: a dent deeper than the floor and shorter than
``contact_sample_m`` along the segment could be missed.

An object kept in contact at both ends of a move may be cut into by up to ``contact_cut_m``
(fcl's penetration depth): the robot makes such a move under impedance control, pressed onto
the surface by the target bias anyway, so a straight move that pivots round an outside corner
(Fig. 13) cuts the corner by a fraction of a millimetre and meets a little more force, stiffness
× depth (1 N for 1 mm at the work site's 1000 N/m), well inside its force limit. Anything
deeper, or any cut into an object not in contact at both ends, is a collision.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from models.geometry import ConvexPart
from models.scene import Scene
from operator_site.program.contact_step import ContactStepper
from operator_site.program.poses import interpolate, log_batch
from operator_site.simulator import SimParams
from operator_site.simulator.world import SimWorld
from protocol import MotionProgram

CONTACT_SAMPLE_M = 0.5e-3
"""Largest point travel between samples against objects in contact at a segment's end (m)."""
KEEP_CONTACT_M = 0.005
"""A contact kept at both ends of a segment must stay within this along it (m): the target
bias d of §VI-B, by which the impedance controller presses the workpiece onto the surface."""
CONTACT_CUT_M = 1e-3
"""A move may cut this deep into an object kept in contact at both of its ends (m)."""
MAX_SAMPLES_PER_SEGMENT = 20_000
"""A segment needing more samples than this is refused (it grazes something all along)."""
CARRYING = ("guarded_grasp", "move", "guarded_move", "contact_move")


@dataclass(frozen=True)
class SegmentCheck:
    """How one segment fared: ``ok``, a ``reason`` when not, the smallest distance to anything
    not in contact at its ends (m), and the number of sampled poses."""

    ok: bool
    reason: str
    clearance_m: float
    samples: int


@dataclass(frozen=True)
class CheckResult:
    """The program's verdict: ``ok``, and when not, the failing ``segment`` (index of the
    command it ends at) and the ``reason``; ``clearance_m`` is the smallest free clearance."""

    ok: bool
    reason: str
    segment: int | None
    clearance_m: float
    samples: int


def _pose_key(X: np.ndarray) -> bytes:
    """The exact bits of a pose, as a dictionary key."""
    return np.ascontiguousarray(X, dtype=np.float64).tobytes()


class Sweeper:
    """Sweeps workpiece segments against one scene's fixed obstacles."""

    def __init__(
        self,
        scene: Scene,
        workpiece: str,
        params: SimParams | None = None,
        attached_O: tuple[ConvexPart, ...] = (),
        X_WO: dict[str, np.ndarray] | None = None,
        keep_contact_m: float = KEEP_CONTACT_M,
        contact_sample_m: float = CONTACT_SAMPLE_M,
        contact_cut_m: float = CONTACT_CUT_M,
    ) -> None:
        self.params = params or SimParams()
        world = SimWorld(
            scene, workpiece, {o.name: o.X_WO for o in scene.objects} | (X_WO or {}), attached_O
        )
        self.c_O = scene.object(workpiece).model.com_O.astype(np.float64)
        self.keep_contact_m = keep_contact_m
        self.contact_sample_m = contact_sample_m
        self.contact_cut_m = contact_cut_m
        # Reach: far enough that an object out of reach leaves room for a long sample step.
        self.stepper = ContactStepper(world, self.c_O, self.params, 0.02)
        self._swept: dict[tuple[bytes, bytes, frozenset[str], frozenset[str]], SegmentCheck] = {}
        """Segments swept so far: the program generator tries a move while fitting targets, again
        round corners, and the final check sweeps it once more: many sweeps repeat an earlier
        one. A sweep depends on nothing else (the world is fixed)."""

    def segment(
        self,
        X0: np.ndarray,
        X1: np.ndarray,
        touching: frozenset[str],
        kept: frozenset[str],
    ) -> SegmentCheck:
        """Sweep the move ``X0`` → ``X1``: objects in ``touching`` (in contact at an end) are
        sampled densely; objects in ``kept`` must stay within ``keep_contact_m`` and may be cut
        into by up to ``contact_cut_m``."""
        key = (_pose_key(X0), _pose_key(X1), frozenset(touching), frozenset(kept))
        if key not in self._swept:
            self._swept[key] = self._sweep(X0, X1, key[2], key[3])
        return self._swept[key]

    def _sweep(
        self, X0: np.ndarray, X1: np.ndarray, touching: frozenset[str], kept: frozenset[str]
    ) -> SegmentCheck:
        st = self.stepper
        c0 = X0[:3, :3] @ self.c_O + X0[:3, 3]
        c1 = X1[:3, :3] @ self.c_O + X1[:3, 3]
        turn = float(np.linalg.norm(log_batch((X1[:3, :3] @ X0[:3, :3].T)[None])[0]))
        travel = float(np.linalg.norm(c1 - c0)) + turn * st.r_max_m  # point travel over t ∈ [0, 1]
        t, samples, clearance = 0.0, 0, math.inf
        while True:
            X = interpolate(X0, X1, np.array([t]), self.c_O)[0]
            probe = st.probe(X)
            samples += 1
            free = st.reach_m
            for name, pair in probe.nearest.items():
                if pair.distance_m <= st.floor_m:
                    if name in kept and st.penetration(X, name)[0] <= self.contact_cut_m:
                        continue
                    where = f"{t:.3f} of the way"
                    return SegmentCheck(False, f"collides with {name} {where}", clearance, samples)
                if name not in touching:
                    free = min(free, pair.distance_m)
            clearance = min(clearance, free)
            for name in kept:
                if probe.distance_m(name) > self.keep_contact_m:
                    return SegmentCheck(
                        False,
                        f"loses the required contact with {name} {t:.3f} of the way",
                        clearance,
                        samples,
                    )
            if t >= 1.0 or travel <= 0.0:
                return SegmentCheck(True, "", clearance, samples)
            if samples > MAX_SAMPLES_PER_SEGMENT:
                return SegmentCheck(False, "needs too many samples", clearance, samples)
            step_m = free - st.floor_m
            if any(name in touching for name in probe.nearest):
                step_m = min(step_m, self.contact_sample_m)
            t = min(1.0, t + max(step_m, 0.5 * st.floor_m) / travel)

    def program(self, program: MotionProgram) -> CheckResult:
        """Sweep every segment on which the workpiece is carried (grasp to release)."""
        clearance, samples = math.inf, 0
        commands = program.commands
        if not commands or commands[0].kind != "guarded_grasp":
            return CheckResult(False, "the program must start with a guarded grasp", 0, 0.0, 0)
        for k in range(1, len(commands)):
            prev, cmd = commands[k - 1], commands[k]
            if cmd.kind not in CARRYING[1:]:
                break  # released: the workpiece stays where it is
            at_prev = frozenset(c.object for c in prev.contacts)
            at_cmd = frozenset(c.object for c in cmd.contacts)
            result = self.segment(
                np.asarray(prev.X_WP), np.asarray(cmd.X_WP), at_prev | at_cmd, at_prev & at_cmd
            )
            clearance, samples = min(clearance, result.clearance_m), samples + result.samples
            if not result.ok:
                reason = f"command {k} ({cmd.kind}) {result.reason}"
                return CheckResult(False, reason, k, clearance, samples)
        return CheckResult(True, "", None, clearance, samples)


def check_program(
    scene: Scene,
    workpiece: str,
    program: MotionProgram,
    attached_O: tuple[ConvexPart, ...] = (),
    params: SimParams | None = None,
    X_WO: dict[str, np.ndarray] | None = None,
) -> CheckResult:
    """Sweep ``program`` for ``workpiece`` in ``scene``; refuse it with a reason if a carried
    segment would collide or lose a contact held at both of its ends."""
    return Sweeper(scene, workpiece, params, attached_O, X_WO=X_WO).program(program)
