"""Message constructors validate and normalise every field, so no site can build a bad message."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from protocol import (
    ROTATION_ORTHONORMAL_TOL,
    CameraFrame,
    ContactState,
    ExecutionReport,
    Heartbeat,
    MotionCommand,
    MotionProgram,
    ProtocolError,
    Recognition,
    Recognitions,
    RobotState,
    Stop,
)
from protocol._schema import SMALL_ARRAY_SIZE
from protocol._schema import all_finite as _all_finite

K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])


def rot_z(theta: float) -> np.ndarray:
    X = np.eye(4)
    c, s = np.cos(theta), np.sin(theta)
    X[:2, :2] = [[c, -s], [s, c]]
    return X


def state(**changes: object) -> RobotState:
    fields = {
        "seq": 1,
        "stamp_s": 0.5,
        "q": np.zeros(6),
        "X_WF": np.eye(4),
        "gripper_opening_m": 0.04,
        "wrench_S": np.zeros(6),
    }
    fields.update(changes)
    return RobotState(**fields)  # type: ignore[arg-type]


def test_lists_become_read_only_float64_arrays_and_ints_floats() -> None:
    s = state(q=[0, 1, 2, 3, 4, 5], X_WF=np.eye(4).tolist(), stamp_s=2)
    assert s.q.dtype == np.float64 and s.q.shape == (6,)
    assert s.X_WF.dtype == np.float64
    assert type(s.stamp_s) is float and s.stamp_s == 2.0
    assert type(state(stamp_s=np.float64(2.5)).stamp_s) is float  # numpy scalars too
    with pytest.raises(ValueError, match="read-only"):
        s.q[0] = 1.0
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.seq = 2  # type: ignore[misc]


@pytest.mark.parametrize("size", [1, SMALL_ARRAY_SIZE, SMALL_ARRAY_SIZE + 1, 10_000])
@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_finiteness_check_either_side_of_the_small_array_size(size: int, bad: float) -> None:
    # Small arrays are checked element by element in Python, larger ones by numpy: both must
    # find one bad element wherever it is, in any shape.
    a = np.full(size, 1e300)
    assert _all_finite(a) and _all_finite(a.reshape(1, size))
    for i in {0, size // 2, size - 1}:
        b = a.copy()
        b[i] = bad
        assert not _all_finite(b) and not _all_finite(b.reshape(size, 1))


def test_caller_arrays_are_copied_not_aliased() -> None:
    q = np.zeros(6)
    s = state(q=q)
    q[0] = 7.0
    assert s.q[0] == 0.0
    assert q.flags.writeable  # the caller's array is left as it was


def test_image_accepts_uint8_and_in_range_ints_only() -> None:
    ok = CameraFrame(0, 0.0, np.eye(4), K, np.zeros(5), [[0, 255], [1, 2]])
    assert ok.image.dtype == np.uint8
    with pytest.raises(ProtocolError, match=r"CameraFrame\.image: integer values must be in"):
        CameraFrame(0, 0.0, np.eye(4), K, np.zeros(5), [[0, 256]])
    with pytest.raises(ProtocolError, match=r"CameraFrame\.image: expected uint8 array"):
        CameraFrame(0, 0.0, np.eye(4), K, np.zeros(5), np.zeros((2, 2)))
    with pytest.raises(ProtocolError, match=r"CameraFrame\.image: expected shape \(1\.\.4096, 1"):
        CameraFrame(0, 0.0, np.eye(4), K, np.zeros(5), np.zeros((0, 2), np.uint8))
    with pytest.raises(ProtocolError, match=r"CameraFrame\.image: expected shape"):
        CameraFrame(0, 0.0, np.eye(4), K, np.zeros(5), np.zeros((2, 2, 3), np.uint8))


def test_camera_matrix_must_be_an_intrinsic_matrix() -> None:
    bad = K.copy()
    bad[2, 2] = 2.0
    with pytest.raises(ProtocolError, match=r"CameraFrame\.K: expected \[\[fx"):
        CameraFrame(0, 0.0, np.eye(4), bad, np.zeros(5), np.zeros((1, 1), np.uint8))
    bad = K.copy()
    bad[0, 0] = 0.0
    with pytest.raises(ProtocolError, match=r"CameraFrame\.K: focal lengths"):
        CameraFrame(0, 0.0, np.eye(4), bad, np.zeros(5), np.zeros((1, 1), np.uint8))


@pytest.mark.parametrize(
    ("change", "text"),
    [
        ({"seq": True}, "RobotState.seq: expected int, got bool"),
        ({"seq": 1.0}, "RobotState.seq: expected int, got float"),
        ({"seq": -1}, "RobotState.seq: must be in [0, 2**63), got -1"),
        ({"seq": 2**63}, "RobotState.seq: must be in [0, 2**63)"),
        ({"stamp_s": -0.1}, "RobotState.stamp_s: must be >= 0.0, got -0.1"),
        ({"stamp_s": float("nan")}, "RobotState.stamp_s: must be finite, got nan"),
        ({"stamp_s": 10**400}, "RobotState.stamp_s: must be finite"),
        ({"stamp_s": "1"}, "RobotState.stamp_s: expected float, got str"),
        ({"gripper_opening_m": False}, "RobotState.gripper_opening_m: expected float, got bool"),
        ({"q": np.zeros(5)}, "RobotState.q: expected shape (6,), got (5,)"),
        ({"q": [0, 0, 0, 0, 0, float("inf")]}, "RobotState.q: all elements must be finite"),
        ({"q": ["0"] * 6}, "RobotState.q: expected float64 array, got dtype <U1"),
        ({"q": [True] * 6}, "RobotState.q: expected float64 array, got dtype bool"),
        ({"q": [[0, 1], [2]]}, "RobotState.q: expected a rectangular array"),
        ({"q": None}, "RobotState.q: expected array, got NoneType"),
        ({"wrench_S": np.zeros((6, 1))}, "RobotState.wrench_S: expected shape (6,), got (6, 1)"),
        ({"X_WF": np.eye(3)}, "RobotState.X_WF: expected shape (4, 4), got (3, 3)"),
    ],
)
def test_robot_state_field_errors_name_the_field(change: dict[str, object], text: str) -> None:
    with pytest.raises(ProtocolError) as info:
        state(**change)
    assert text in str(info.value)


def test_poses_must_be_rigid_transforms() -> None:
    state(X_WF=rot_z(0.3))  # fine
    X = rot_z(0.3)
    X[3, 0] = 1e-8
    with pytest.raises(ProtocolError, match=r"X_WF: last row must be \[0, 0, 0, 1\]"):
        state(X_WF=X)
    X = rot_z(0.3)
    X[3, 0] = 1e-10  # within the 1e-9 tolerance
    state(X_WF=X)
    X = rot_z(0.3)
    X[:3, :3] *= 1.0 + 10 * ROTATION_ORTHONORMAL_TOL
    with pytest.raises(ProtocolError, match="X_WF: rotation block is not orthonormal"):
        state(X_WF=X)
    X = rot_z(0.3)
    X[:3, :3] *= 1.0 + 0.1 * ROTATION_ORTHONORMAL_TOL
    state(X_WF=X)
    X = np.diag([1.0, 1.0, -1.0, 1.0])
    with pytest.raises(ProtocolError, match="X_WF: rotation block has determinant -1"):
        state(X_WF=X)
    X = np.eye(4)
    X[0, 0] = 1e200
    with pytest.raises(ProtocolError, match="X_WF: rotation block is not orthonormal"):
        state(X_WF=X)


def test_contact_normals_must_be_unit_vectors() -> None:
    ContactState("frame", [[0.0, 0.0, 1.0], [0.6, 0.8, 0.0]])
    with pytest.raises(ProtocolError, match=r"ContactState\.normals_W: row 1 is not a unit"):
        ContactState("frame", [[0.0, 0.0, 1.0], [0.6, 0.8, 0.1]])
    with pytest.raises(ProtocolError, match=r"ContactState\.normals_W: expected shape"):
        ContactState("frame", np.zeros((0, 3)))
    with pytest.raises(ProtocolError, match=r"ContactState\.normals_W: expected shape"):
        ContactState("frame", np.tile([0.0, 0.0, 1.0], (17, 1)))


def test_names_ids_and_free_text() -> None:
    Recognition("tall_block.v2-a", np.eye(4), 0.9)
    for bad in ("", "a b", "a/b", "é", "x\n", "x" * 257):
        with pytest.raises(ProtocolError, match=r"Recognition\.model"):
            Recognition(bad, np.eye(4), 0.9)
    Recognition("x" * 256, np.eye(4), 0.9)
    Stop("any text at all, even\nnewlines and é", 0.0)
    Stop("x" * 4096, 0.0)
    with pytest.raises(ProtocolError, match=r"Stop\.reason: must be at most 4096"):
        Stop("x" * 4097, 0.0)
    with pytest.raises(ProtocolError, match=r"Stop\.reason: is not encodable as UTF-8"):
        Stop("\udc80", 0.0)
    with pytest.raises(ProtocolError, match=r"Heartbeat\.site_id: must match"):
        Heartbeat("site.1", "work_site", 0, 0.0)  # no dots: a site id is one key chunk
    with pytest.raises(ProtocolError, match=r"Heartbeat\.role: must be one of"):
        Heartbeat("site1", "robot", 0, 0.0)


def test_enumerations_and_bounds_of_program_messages() -> None:
    normals = [[0.0, 0.0, 1.0]]
    contact = ContactState("frame", normals)
    MotionCommand("guarded_move", np.eye(4), 0.0, 0.0, ())
    with pytest.raises(ProtocolError, match=r"MotionCommand\.kind: must be one of"):
        MotionCommand("jump", np.eye(4), 0.1, 1.0, ())
    with pytest.raises(ProtocolError, match=r"MotionCommand\.speed_mps: must be >= 0"):
        MotionCommand("move", np.eye(4), -0.1, 1.0, ())
    with pytest.raises(ProtocolError, match=r"MotionCommand\.contacts: must have 0\.\.16"):
        MotionCommand("move", np.eye(4), 0.1, 1.0, (contact,) * 17)
    with pytest.raises(ProtocolError, match=r"MotionCommand\.contacts\[1\]: expected ContactState"):
        MotionCommand("move", np.eye(4), 0.1, 1.0, (contact, "frame"))
    command = MotionCommand("move", np.eye(4), 0.1, 1.0, [contact])
    assert command.contacts == (contact,)  # lists become tuples
    with pytest.raises(ProtocolError, match=r"MotionProgram\.commands: must have 1\.\.1000"):
        MotionProgram("p1", np.eye(4), ())
    ExecutionReport("p1", -1, "done", np.zeros(6), "", 0.0)
    with pytest.raises(ProtocolError, match=r"ExecutionReport\.command_index: must be in \[-1"):
        ExecutionReport("p1", -2, "done", np.zeros(6), "", 0.0)
    with pytest.raises(ProtocolError, match=r"ExecutionReport\.status: must be one of"):
        ExecutionReport("p1", 0, "ok", np.zeros(6), "", 0.0)
    with pytest.raises(ProtocolError, match=r"Recognitions\.objects: must have 0\.\.256"):
        Recognitions(0, 0.0, 0.0, (Recognition("cube", np.eye(4), 1.0),) * 257)


def test_messages_compare_by_identity() -> None:
    # eq=False: numpy fields make value equality ambiguous; compare fields explicitly instead.
    assert state() != state()
    s = state()
    assert s == s


def test_a_movable_object_is_pressed_sideways_gently_and_everything_else_as_before() -> None:
    """The L-block's upright (sideways, movable): capped at 1.5 N, aimed 2.5 mm past; its step
    (pressed down onto it) and the frame's wall (fixed): d = 5 mm, uncapped."""
    from protocol.execution import (
        MOVABLE_PRESS_N,
        TARGET_BIAS_M,
        TARGET_BIAS_MOVABLE_M,
        contact_bias_W,
        contact_depths_m,
        press_caps_n,
    )

    upright = ("l_block", np.array([-1.0, 0.0, 0.0]))
    step = ("l_block", np.array([0.0, 0.0, 1.0]))
    wall = ("frame", np.array([0.0, 1.0, 0.0]))
    movable = {"l_block", "cube"}
    caps = press_caps_n([upright, step, wall], movable)
    assert caps.tolist() == [MOVABLE_PRESS_N, np.inf, np.inf]
    depths = contact_depths_m([upright, step, wall], movable)
    assert depths.tolist() == [TARGET_BIAS_MOVABLE_M, TARGET_BIAS_M, TARGET_BIAS_M]
    assert TARGET_BIAS_MOVABLE_M == pytest.approx(0.0025)
    # Orthogonal normals: Δp reaches each exactly its own depth into it.
    dp = contact_bias_W([upright, step, wall], movable)
    np.testing.assert_allclose(dp, [TARGET_BIAS_MOVABLE_M, -TARGET_BIAS_M, -TARGET_BIAS_M])
    np.testing.assert_array_equal(contact_bias_W([], movable), np.zeros(3))
