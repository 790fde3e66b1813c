"""The work-site server: steps the world in real time and talks to operator sites over zenoh.

Publishes robot state (≥ 100 Hz), grey camera frames (at the camera's rate) and a heartbeat;
declares a liveliness token; takes programs and stops from the wire. Whatever arrives is decoded
and validated first, and nothing that arrives can stop this loop.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass

import numpy as np
import zenoh

from models.scene import Scene
from protocol import (
    DEFAULT_SITE_ID,
    CameraFrame,
    ExecutionReport,
    Heartbeat,
    MotionProgram,
    ProtocolError,
    RobotState,
    Stop,
    alive_key,
    decode,
    encode,
    key,
)
from work_site.camera import CameraProcess, RenderRequest
from work_site.world import World

log = logging.getLogger("work-site")

MAX_CATCH_UP_STEPS = 50
"""Physics steps run back to back at most before the loop yields; beyond that it falls behind
real time (and says so) rather than starving the publishers."""
INBOX_CAPACITY = 64


@dataclass(frozen=True)
class ServerOptions:
    """Rates and switches of the work-site server (Hz, SI)."""

    site_id: str = DEFAULT_SITE_ID
    physics_rate_hz: float = 1000.0
    state_rate_hz: float = 100.0
    heartbeat_rate_hz: float = 1.0
    camera: bool = True
    camera_supersample: int = 1

    def __post_init__(self) -> None:
        if not 100.0 <= self.physics_rate_hz <= 10000.0:
            raise ValueError(f"physics_rate_hz must be in [100, 10000], got {self.physics_rate_hz}")
        if not 0 < self.state_rate_hz <= self.physics_rate_hz:
            raise ValueError("state_rate_hz must be in (0, physics_rate_hz]")
        if not 0 < self.heartbeat_rate_hz <= 100:
            raise ValueError("heartbeat_rate_hz must be in (0, 100]")
        if self.camera_supersample < 1:
            raise ValueError("camera_supersample must be ≥ 1")


class WorkSiteServer:
    """Owns the world, the camera process and the zenoh session while :meth:`run` runs."""

    def __init__(
        self, scene: Scene, zenoh_config: zenoh.Config, options: ServerOptions | None = None
    ) -> None:
        self.scene = scene
        self.options = options or ServerOptions()
        self._zenoh_config = zenoh_config
        self.stats = {"states": 0, "frames": 0, "refused": 0, "late_steps": 0}

    def run(self, stop: threading.Event, ready: threading.Event | None = None) -> None:
        """Serve until ``stop`` is set; ``ready`` is set once publishing has started."""
        opts = self.options
        world = World(self.scene, time_step_s=1.0 / opts.physics_rate_hz)
        camera = CameraProcess(self.scene.path, opts.camera_supersample) if opts.camera else None
        try:
            with zenoh.open(self._zenoh_config) as session:
                self._serve(session, world, camera, stop, ready)
        finally:
            if camera is not None:
                camera.close()
            world.close()

    def _serve(
        self,
        session: zenoh.Session,
        world: World,
        camera: CameraProcess | None,
        stop: threading.Event,
        ready: threading.Event | None,
    ) -> None:
        opts, site = self.options, self.options.site_id
        drop = zenoh.CongestionControl.DROP
        token = session.liveliness().declare_token(alive_key(site, "work_site"))
        pub_state = session.declare_publisher(
            key(site, "robot_state"), congestion_control=drop, priority=zenoh.Priority.DATA_HIGH
        )
        pub_camera = session.declare_publisher(
            key(site, "camera"), congestion_control=drop, priority=zenoh.Priority.DATA_LOW
        )
        pub_heartbeat = session.declare_publisher(key(site, "heartbeat"))
        self._pub_report = session.declare_publisher(
            key(site, "report"), priority=zenoh.Priority.INTERACTIVE_HIGH
        )
        # Never block inside zenoh's callbacks: samples go to bounded rings read by this loop.
        inbox_program = session.declare_subscriber(
            key(site, "program"), zenoh.handlers.RingChannel(INBOX_CAPACITY)
        )
        inbox_stop = session.declare_subscriber(
            key(site, "stop"), zenoh.handlers.RingChannel(INBOX_CAPACITY)
        )
        dt = world.time_step_s
        state_every = max(1, round(opts.physics_rate_hz / opts.state_rate_hz))
        camera_period_s = 1.0 / self.scene.camera.frame_rate_hz
        heartbeat_period_s = 1.0 / opts.heartbeat_rate_hz
        steps, t0 = 0, time.monotonic()
        next_frame_s = next_heartbeat_s = 0.0
        seq_state = seq_frame = seq_heartbeat = 0
        log.info(
            "work site %r serving; physics %.0f Hz, state %.0f Hz, camera %.1f Hz",
            site,
            opts.physics_rate_hz,
            opts.physics_rate_hz / state_every,
            self.scene.camera.frame_rate_hz if camera else 0.0,
        )
        if ready is not None:
            ready.set()
        try:
            while not stop.is_set():
                elapsed = time.monotonic() - t0
                due = int(elapsed / dt) - steps
                if due > MAX_CATCH_UP_STEPS:
                    self.stats["late_steps"] += due - MAX_CATCH_UP_STEPS
                    t0 += (due - MAX_CATCH_UP_STEPS) * dt  # drop the backlog: stay real time
                    due = MAX_CATCH_UP_STEPS
                for _ in range(due):
                    world.step()
                    steps += 1
                    if steps % state_every == 0:
                        pub_state.put(encode(self._robot_state(world, seq_state)))
                        seq_state += 1
                        self.stats["states"] += 1
                self._handle_inbox(inbox_program, inbox_stop, world)
                if camera is not None:
                    done = camera.poll()
                    if done is not None:
                        seq, stamp, image = done
                        cam = self.scene.camera
                        pub_camera.put(
                            encode(
                                CameraFrame(
                                    seq=seq,
                                    stamp_s=stamp,
                                    X_WC=cam.X_WC,
                                    K=cam.K,
                                    dist=cam.dist,
                                    image=image,
                                )
                            )
                        )
                        self.stats["frames"] += 1
                    if elapsed >= next_frame_s and not camera.busy:
                        q, fingers = world.robot_joint_positions()
                        camera.request(
                            RenderRequest(seq_frame, time.time(), world.object_poses(), q, fingers)
                        )
                        seq_frame += 1
                        next_frame_s = max(next_frame_s + camera_period_s, elapsed)
                if elapsed >= next_heartbeat_s:
                    pub_heartbeat.put(
                        encode(
                            Heartbeat(
                                site_id=site,
                                role="work_site",
                                seq=seq_heartbeat,
                                stamp_s=time.time(),
                            )
                        )
                    )
                    seq_heartbeat += 1
                    next_heartbeat_s += heartbeat_period_s
                sleep_s = t0 + (steps + 1) * dt - time.monotonic()
                if sleep_s > 0:
                    time.sleep(sleep_s)
        finally:
            inbox_program.undeclare()
            inbox_stop.undeclare()
            token.undeclare()
            log.info("work site %r stopped: %s", site, self.stats)

    @staticmethod
    def _robot_state(world: World, seq: int) -> RobotState:
        snap = world.robot_snapshot()
        return RobotState(
            seq=seq,
            stamp_s=time.time(),
            q=snap.q,
            X_WF=snap.X_WF,
            gripper_opening_m=snap.gripper_opening_m,
            wrench_S=snap.wrench_S,
        )

    def _report(self, program_id: str, status: str, message: str) -> None:
        self._pub_report.put(
            encode(
                ExecutionReport(
                    program_id=program_id,
                    command_index=-1,
                    status=status,
                    wrench_S=np.zeros(6),
                    message=message,
                    stamp_s=time.time(),
                )
            )
        )

    def _handle_inbox(
        self, inbox_program: zenoh.Subscriber, inbox_stop: zenoh.Subscriber, world: World
    ) -> None:
        while (sample := inbox_stop.try_recv()) is not None:
            try:
                msg = decode(sample.payload.to_bytes(), expected=Stop)
            except ProtocolError as e:
                self.stats["refused"] += 1
                log.warning("refused a stop message: %s", e)
                continue
            # Holding the current joint angles is the stop: no trajectory runs yet.
            world.q_target = world.robot_joint_positions()[0]
            log.info("stop: %s", msg.reason)
        while (sample := inbox_program.try_recv()) is not None:
            try:
                program = decode(sample.payload.to_bytes(), expected=MotionProgram)
            except ProtocolError as e:
                self.stats["refused"] += 1
                log.warning("refused a program: %s", e)
                self._report("invalid", "refused", f"program refused: {e}")
                continue
            self.stats["refused"] += 1
            self._report(
                program.program_id, "refused", "this work site does not execute motion programs yet"
            )
