"""The operator's task in progress: the work-site model, the chosen workpiece and its simulator.

UI-independent, so every operator action (select, drag, capture, undo, reset) is testable without a
browser; the page calls these methods from its callbacks, under its lock.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from models.robot import load_robot
from models.scene import Scene
from operator_site.grasp import (
    MIN_GRIP_AREA_M2,
    Grasp,
    GraspChoice,
    choose_grasp,
    clear_top_grasp,
    finger_parts_O,
    grip_area_m2,
    pressed_contacts,
)
from operator_site.simulator import SimParams, Simulator, StepResult
from operator_site.simulator.stepper import SimState

MAX_UNDO = 50
"""Drags that :meth:`TaskSession.undo` can take back."""


class TaskSession:
    """The model's object poses, and at most one workpiece being dragged in the simulator."""

    def __init__(self, scene: Scene, params: SimParams | None = None) -> None:
        self.scene = scene
        self.params = params or SimParams()
        self.X_WO: dict[str, np.ndarray] = {o.name: o.X_WO.copy() for o in scene.objects}
        self.sim: Simulator | None = None
        self.start_X_WO: np.ndarray | None = None
        self.robot = load_robot(scene.robot.urdf_path)
        self.X_GP = np.eye(4)
        self.opening_m = 0.0
        self.fingers_O: tuple = ()
        self._marks: list[SimState] = []
        """Snapshots of the simulation where drags began, newest last (:meth:`undo`)."""

    @property
    def workpiece(self) -> str | None:
        return self.sim.world.workpiece if self.sim else None

    @property
    def captured(self) -> set[str]:
        return set(self.sim.state.capturable) if self.sim else set()

    def select(self, name: str, grasp: Grasp | None = None, fingers: bool = True) -> None:
        """Make movable object ``name`` the workpiece, held by the gripper's fingers in
        ``grasp``, by default a grasp from above, high enough to clear the frame's bars where
        the block is tall enough, on the pair of faces whose open fingers clear the other
        blocks, or where the chooser puts it if that would hold too little of the block (the
        fingers move with it); its last pose stays in the model. ``fingers=False``: the block
        moves alone (a demonstration whose grasp is chosen afterwards, for its path)."""
        obj = self.scene.object(name)
        if obj.fixed:
            raise ValueError(f"{name!r} is part of the fixed environment and cannot be moved")
        if self.sim is not None:
            self.X_WO[self.sim.world.workpiece] = self.sim.X_WO
        if grasp is None:
            self.X_GP, self.opening_m = clear_top_grasp(self.robot, self.scene, name, self.X_WO)
            if grip_area_m2(self.robot, self.scene, name, self.X_GP) < MIN_GRIP_AREA_M2:
                # Today's grasp would hold too little (the wedge's narrowing ends): the chooser
                # slides it to where the block is thick.
                grasp = choose_grasp(self.robot, self.scene, name, self.X_WO).grasp
        if grasp is not None:
            self.X_GP, self.opening_m = np.array(grasp.X_GP, dtype=np.float64), grasp.opening_m
        self.fingers_O = (
            tuple(finger_parts_O(self.robot, self.X_GP, self.opening_m)) if fingers else ()
        )
        self.sim = Simulator(
            self.scene, name, self.params, X_WO=self.X_WO, attached_O=self.fingers_O
        )
        self.start_X_WO = self.X_WO[name].copy()
        self._start_step = self._start_state()
        self._marks = []

    def _start_state(self) -> StepResult:
        """The workpiece where the simulator starts it, with its contacts there."""
        st = self.sim.state
        return StepResult(
            time_s=0.0,
            X_WO=st.X_WO.copy(),
            contacts=st.contacts,
            s_fraction=0.0,
            queries=0,
            min_distance_m=math.inf,
            speed_limited=False,
        )

    def choose_grasp_for_path(self) -> GraspChoice:
        """Choose the grasp again for the path demonstrated so far (:func:`choose_grasp`: no
        finger between the workpiece and a surface it presses, none run into anything on the
        way) and hold the workpiece so from now on; the path and captures are kept. When no
        grasp can do it, nothing changes and the choice says why."""
        if self.sim is None or self.start_X_WO is None:
            raise ValueError("select a workpiece first")
        name = self.sim.world.workpiece
        path = self.path_history()
        start_X_WO = self.X_WO | {name: self.start_X_WO}
        choice = choose_grasp(
            self.robot,
            self.scene,
            name,
            start_X_WO,
            [step.X_WO for step in path],
            pressed_contacts(path),
        )
        if choice.grasp is None:
            return choice
        self.X_GP, self.opening_m = choice.grasp.X_GP.copy(), choice.grasp.opening_m
        self.fingers_O = tuple(finger_parts_O(self.robot, self.X_GP, self.opening_m))
        # The new fingers ride with the workpiece from its start pose; the state (pose,
        # captures, path) carries over, so what was demonstrated stays the task.
        state = self.sim.state
        self.sim = Simulator(
            self.scene, name, self.params, X_WO=start_X_WO, attached_O=self.fingers_O
        )
        self.sim.state = state
        return choice

    def path_history(self) -> list[StepResult]:
        """The start state and every step since: the simulator's history records the pose
        after each step, so on its own the path would begin a step (up to 20 mm) away from
        where the block really is, and where the robot grasps it."""
        if self.sim is None:
            return []
        return [self._start_step, *self.sim.history]

    def set_target(self, X_WD: np.ndarray) -> None:
        """Where the dragger is (the spring's far end), for the selected workpiece."""
        if self.sim is None:
            raise ValueError("select a workpiece first")
        self.sim.set_target(X_WD)

    def toggle_capture(self, name: str) -> bool:
        """Capture ``name`` (hold contact once touched), or release it; True if now captured."""
        if self.sim is None:
            raise ValueError("select a workpiece first")
        if name == self.sim.world.workpiece:
            raise ValueError("the workpiece cannot capture itself")
        if name in self.sim.state.capturable:
            self.sim.release(name)
            return False
        self.sim.capture(name)
        return True

    def step(self) -> StepResult | None:
        """One simulator step for the workpiece, or None when nothing is selected."""
        if self.sim is None:
            return None
        result = self.sim.step()
        self.X_WO[self.sim.world.workpiece] = result.X_WO
        return result

    def replay(self, path_X_WO: list[np.ndarray]) -> None:
        """Drag the selected workpiece through ``path_X_WO`` again, one simulator step per
        pose (a saved task coming back with its history)."""
        if self.sim is None:
            raise ValueError("select a workpiece first")
        for X in path_X_WO:
            self.set_target(X)
            self.step()

    def reset(self) -> None:
        """Put the workpiece back where it was when selected and forget the path."""
        if self.sim is None or self.start_X_WO is None:
            return
        name = self.sim.world.workpiece
        self.X_WO[name] = self.start_X_WO.copy()
        captured = set(self.sim.state.capturable)
        self.sim = Simulator(
            self.scene, name, self.params, X_WO=self.X_WO, attached_O=self.fingers_O
        )
        for other in captured:
            self.sim.capture(other)
        self._start_step = self._start_state()
        self._marks = []

    def mark(self) -> None:
        """Remember the task as it is now (the page calls this as a drag begins), so that
        :meth:`undo` can come back here; the newest :data:`MAX_UNDO` are kept."""
        if self.sim is None:
            return
        st = self.sim.state
        self._marks.append(
            replace(
                st,
                X_WO=st.X_WO.copy(),
                X_WD=st.X_WD.copy(),
                capturable=set(st.capturable),
                held=set(st.held),
                history=list(st.history),
            )
        )
        del self._marks[:-MAX_UNDO]

    def undo(self) -> np.ndarray | None:
        """Back to the last :meth:`mark`: the workpiece's pose, captures and path as they were
        there; the workpiece's pose then, or None when there is nothing to undo."""
        if self.sim is None or not self._marks:
            return None
        self.sim.state = self._marks.pop()
        self.X_WO[self.sim.world.workpiece] = self.sim.state.X_WO.copy()
        return self.sim.state.X_WO.copy()
