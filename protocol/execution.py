"""How the work site executes a program, as far as an operator site must predict it: the rules
both sites share (the operator site checks a program's feasibility against them before sending,
the work site executes by them). SI units; frames in names."""

from __future__ import annotations

from collections.abc import Container, Sequence

import numpy as np

from protocol.messages import target_bias

WORKSPACE_MIN_W = np.array([0.10, -0.45, 0.02])
"""Lowest corner of the box every TCP target must lie in (m). z: the fingertips hang 15 mm
below the TCP, so 0.02 m keeps them 5 mm above the table."""
WORKSPACE_MAX_W = np.array([0.75, 0.45, 0.50])
"""Highest corner of that box (m)."""
TARGET_BIAS_M = 0.005
"""d of §VI-B: how far past each contact a contact move aims (the paper's ≈ 5 mm)."""
TARGET_BIAS_MAX_M = 2 * TARGET_BIAS_M
"""Bound on |Δp|: nearly parallel normals would otherwise ask for a long bias."""
CONTACT_VERIFY_N = 1.0
"""A contact is verified when the force along its normal reaches this (N); the impedance
presses each with about stiffness × d = 5 N when the model is right. Low, so that a wall a vision
model puts a few millimetres off still verifies, yet above the zero a missing contact reads; a
larger d instead would turn the block in its grip."""
NORMAL_STIFFNESS_N_PER_M = 1000.0
"""The contact moves' impedance stiffness along the contact normals (§VI-B, N/m)."""
MOVABLE_PRESS_N = 1.5 * CONTACT_VERIFY_N
"""A contact move presses a movable object sideways with at most this force (N): half again the
verification threshold. §VI-B's impedance presses each contact with about 5 N, which slides a
light block across the table and drags the workpiece along its face with it (docs/tuning.md).
The hand aims :data:`TARGET_BIAS_MOVABLE_M` past the contact, so that a model a little off
still verifies, and the impedance's spring along that normal stops at this force. Pressed down
onto its support a block cannot slide: those presses are not capped."""
SIDEWAYS_MAX_NORMAL_Z = float(np.cos(np.radians(45.0)))
"""A contact normal whose upward component is below this presses its object sideways."""
MODEL_ERROR_ALLOWANCE_M = 0.0015
"""How far a movable object's face may lie beyond where the model has it and a contact move
still press it with :data:`CONTACT_VERIFY_N` (m): vision's error along its line of sight."""
TARGET_BIAS_MOVABLE_M = CONTACT_VERIFY_N / NORMAL_STIFFNESS_N_PER_M + MODEL_ERROR_ALLOWANCE_M
"""d for a contact pressing a movable object sideways (m): the spring, capped at
:data:`MOVABLE_PRESS_N`, then has little way to build force past it while the hand moves."""
GUARD_OVERTRAVEL_M = 0.01
"""A guarded move aims this far past its target (which is where contact is expected), so that
the guard, not the target, ends it; a contact further off than this fails the command."""
GRASP_APPROACH_M = 0.06
"""The grasp approaches from this far above the grasp pose, straight down (m)."""
SAFE_TCP_HEIGHT_M = 0.22
"""The hand travels between places at least this high (its centre above the table, m): to a
grasp it goes over the top and comes straight down, from a release it rises this high before
it parks, and going home it first rises this high. The tallest block (0.10 m) held below the
fingertips (15 mm below the centre) still clears every other block."""
GRASP_LIFT_M = 0.005
"""After closing, the block is lifted this far and weighed (m)."""


def press_caps_n(
    directions: Sequence[tuple[str, np.ndarray]], movable: Container[str]
) -> np.ndarray:
    """The most a contact move presses along each contact direction (object, unit normal into
    the workpiece), N: :data:`MOVABLE_PRESS_N` where it presses one of the ``movable`` objects
    sideways (:data:`SIDEWAYS_MAX_NORMAL_Z`), unbounded (inf) elsewhere."""
    return np.array(
        [
            MOVABLE_PRESS_N
            if name in movable and abs(float(n[2])) < SIDEWAYS_MAX_NORMAL_Z
            else np.inf
            for name, n in directions
        ],
        dtype=np.float64,
    )


def contact_depths_m(
    directions: Sequence[tuple[str, np.ndarray]], movable: Container[str]
) -> np.ndarray:
    """How far past each contact direction a contact move aims (m):
    :data:`TARGET_BIAS_MOVABLE_M` where :func:`press_caps_n` caps the press, else
    :data:`TARGET_BIAS_M`."""
    caps = press_caps_n(directions, movable)
    return np.where(caps < np.inf, TARGET_BIAS_MOVABLE_M, TARGET_BIAS_M)


def contact_bias_W(
    directions: Sequence[tuple[str, np.ndarray]], movable: Container[str]
) -> np.ndarray:
    """The target bias Δp (3,) m, W, of a contact move with these contact directions
    (:func:`~protocol.messages.contact_directions`), ``movable`` the objects that may slide:
    :func:`~protocol.messages.target_bias` with :func:`contact_depths_m`, bounded by
    :data:`TARGET_BIAS_MAX_M`."""
    if not directions:
        return np.zeros(3)
    N = np.array([n for _, n in directions], dtype=np.float64)
    return target_bias(N, contact_depths_m(directions, movable), TARGET_BIAS_MAX_M)


def grasp_approach_W(X_WG: np.ndarray) -> list[np.ndarray]:
    """The TCP poses the empty hand comes to a grasp at ``X_WG`` through, in order: over the top
    at :data:`SAFE_TCP_HEIGHT_M` (a straight line from where the hand is may pass low over the
    blocks), then :data:`GRASP_APPROACH_M` above the grasp, from where it is guarded down; only the
    latter when it is already that high."""
    above = np.array(X_WG, dtype=np.float64)
    above[2, 3] += GRASP_APPROACH_M
    if above[2, 3] >= SAFE_TCP_HEIGHT_M:
        return [above]
    over = above.copy()
    over[2, 3] = SAFE_TCP_HEIGHT_M
    return [over, above]
