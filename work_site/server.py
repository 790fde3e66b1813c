"""The work-site server: steps the world in real time and talks to operator sites over zenoh.

Publishes robot state (≥ 100 Hz), grey camera frames (at the camera's rate), the objects vision
recognises in them (searched for at ``vision_rate_hz`` or as fast as vision keeps up, and
followed in the frames between) and a heartbeat;
declares a liveliness token; takes programs, stops and operator heartbeats from the wire, each
key on its own inbox (``work_site/inbox.py``). Whatever arrives is decoded and validated first,
and nothing that arrives can stop this loop: programs are checked on a thread of their own, the
journal is written by another, and a running program stops when its operator falls silent for
``deadman_s`` (the dead-man).
"""

from __future__ import annotations

import collections
import logging
import math
import sys
import threading
import time
from functools import partial
from pathlib import Path

import numpy as np
import zenoh

from models.robot import load_robot
from models.scene import Scene
from protocol import (
    STOP_REPLY_ID,
    ExecutionReport,
    Heartbeat,
    MotionProgram,
    ObjectPose,
    Recognition,
    Recognitions,
    RobotState,
    Stop,
    TruthPoses,
    alive_key,
    encode,
    key,
)
from work_site.camera import CameraProcess, FrameEncoding, RenderedFrame, RenderRequest
from work_site.control.controller import (
    Impedance,
    TaskController,
)
from work_site.control.executor import Execution
from work_site.inbox import DropCounter, heartbeat_inbox, stop_inbox
from work_site.intake import (
    INBOX_CAPACITY,
    INVALID_REPORTS_PER_S,
    REMEMBERED_PROGRAMS,
    ProgramIntake,
)
from work_site.journal import JournalWriter, journal_line, load_journal
from work_site.lease import ControlLease
from work_site.options import DEADMAN_RANGE_S, ServerOptions
from work_site.outbox import CLOSE_DRAIN_S, Outbox
from work_site.pacing import StreamPacer, jpeg_quality
from work_site.recognition import VisionProcess
from work_site.vision.fusion import PoseFusion
from work_site.world import World

log = logging.getLogger("work-site")

MAX_CATCH_UP_TICKS = 5
"""Control periods (10 physics steps each) run back to back at most before the loop yields;
beyond that it falls behind real time (and counts it) rather than starving the publishers."""
LATE_WARNING_PERIOD_S = 10.0
"""While the loop falls behind its time scale it says so at most this often (wall s). Falling
behind changes no physics (every control period still runs its 10 steps), only how fast
simulated time passes: a user watching the robot, or a benchmark's timing, must know."""
FINAL_STATUSES = ("done", "failed", "refused", "stopped")
SWITCH_INTERVAL_S = 0.001
"""The interpreter's thread switch interval while serving: a program being checked on the
checking thread hands the control loop the GIL back within this (Python's default is 5 ms)."""
STOP_REPLY_PERIOD_S = 0.2
"""Such answers go at most this often: a stream of stops gets a stream of holds, not of
reports."""
DEADMAN_STALL_S = 0.05
"""A loop iteration this long after the last one means this process was starved (s)."""
DEADMAN_ROUND_TRIPS = 3
"""The dead-man waits this many of the operator's round trips beyond ``--deadman-s``. A beat
lost on a long link holds every later one up until TCP resends it, about a round trip (plus
200 ms) later, and twice that when the resend is lost too: over a round trip of a second, a
little loss paused a healthy operator's beats past the default dead-man. The trade: a cut link
stops the robot this much later; it cannot be known sooner than a round trip anyway."""


def deadman_timeout_s(base_s: float, round_trip_s: float | None) -> float:
    """The dead-man's timeout for an operator whose round trip is ``round_trip_s`` (None: not
    measured): ``base_s`` and :data:`DEADMAN_ROUND_TRIPS` round trips, at most the top of
    ``--deadman-s``'s range (a forged echo buys no more)."""
    if round_trip_s is None:
        return base_s
    return max(base_s, min(DEADMAN_RANGE_S[1], base_s + DEADMAN_ROUND_TRIPS * round_trip_s))


def read_journal(
    path: Path,
) -> tuple[collections.OrderedDict[str, list[bytes]], list[tuple[str, bytes]]]:
    """The reports of a journal's newest REMEMBERED_PROGRAMS programs, and the closing "failed"
    reports added for programs a restart interrupted (:func:`work_site.journal.load_journal`)."""
    state = load_journal(path, REMEMBERED_PROGRAMS)
    return state.reports, state.added


class WorkSiteServer(ProgramIntake):
    """Owns the world, the camera process and the zenoh session while :meth:`run` runs."""

    def __init__(
        self, scene: Scene, zenoh_config: zenoh.Config, options: ServerOptions | None = None
    ) -> None:
        self.scene = scene
        self.options = options or ServerOptions()
        self._zenoh_config = zenoh_config
        self.stats = {
            "states": 0,
            "frames": 0,
            "renders": 0,
            "recognitions": 0,
            "tracked": 0,
            "refused": 0,
            "late_ticks": 0,
        }
        self._execution: Execution | None = None
        self._reports: collections.OrderedDict[str, list[bytes]] = collections.OrderedDict()
        """Every report sent for each program id received (the newest REMEMBERED_PROGRAMS),
        encoded: a program re-sent with the same id is not run again, its reports are."""
        self._ids: list[str] = []
        """Every program id ever received, in order (append only)."""
        self._seen: set[str] = set()
        """The same ids, to look up: a program id is run at most once, ever."""
        self._lock = threading.Lock()
        """Guards what the checking thread and the control loop share: the reports, the
        program being checked or run (``_busy``) and the programs ready to start."""
        self._busy: str | None = None
        """The id of the program being checked, waiting to start or running."""
        self._lease = ControlLease()
        self._pacer = StreamPacer()
        self._state_credit = self._frame_credit = 0.0
        """Robot states and camera frames owed at the pacer's scale: one is sent each time
        its credit reaches one."""
        self._stops_seen = 0
        """Stops acted on so far: a program whose check began before the latest one is cancelled."""
        self._ready: collections.deque[tuple[MotionProgram, int, dict]] = collections.deque()
        """Programs that passed their check, with ``_stops_seen`` when their check began."""
        self._last_stop_reason = ""
        self._cancelled: collections.OrderedDict[str, str] = collections.OrderedDict()
        """Program ids a stop cancelled before they arrived, with its reason: they never start
        (the last :data:`~work_site.intake.REMEMBERED_CANCELS`)."""
        self._execution_started_s = 0.0
        self._still_since_s = 0.0
        """Wall-clock time (s) since which no program has moved anything: vision fuses only
        frames taken after it."""
        self._fusion = PoseFusion({o.name: o.model.symmetries for o in scene.objects})
        self._deadman_checked_s = 0.0
        self._stop_replied_s = -math.inf
        self._wrench_S = np.zeros(6)
        """The wrist wrench of the last control period, for reports sent off the loop's thread."""
        self._journal: JournalWriter | None = None
        if self.options.journal is not None:
            path = self.options.journal
            path.parent.mkdir(parents=True, exist_ok=True)
            state = load_journal(path, REMEMBERED_PROGRAMS)
            self._reports, self._ids, self._seen = state.reports, state.ids, state.seen
            with path.open("a") as f:
                f.writelines(journal_line(pid, payload) for pid, payload in state.added)
            self._journal = JournalWriter(
                path,
                self._ids,
                self._journal_snapshot,
                self._lock,
                report_lines=state.report_lines + len(state.added),
            )
        self._faults_logged: set[str] = set()
        self._invalid_programs = DropCounter("program")
        self._invalid_report_budget, self._invalid_report_s = INVALID_REPORTS_PER_S, 0.0

    def run(self, stop: threading.Event, ready: threading.Event | None = None) -> None:
        """Serve until ``stop`` is set; ``ready`` is set once publishing has started."""
        opts = self.options
        world = World(self.scene, time_step_s=1.0 / opts.physics_rate_hz)
        camera = (
            CameraProcess(
                self.scene.path,
                opts.camera_supersample,
                opts.camera_X_WC,
                opts.camera_sensor,
                FrameEncoding(opts.camera_encoding, opts.camera_quality, self.scene.camera),
            )
            if opts.camera
            else None
        )
        self._vision = (
            VisionProcess(self.scene.path, opts.vision_scale, opts.vision_index_views)
            if opts.vision_rate_hz > 0
            else None
        )
        switch_interval_s = sys.getswitchinterval()
        sys.setswitchinterval(SWITCH_INTERVAL_S)
        try:
            with zenoh.open(self._zenoh_config) as session:
                self._serve(session, world, camera, stop, ready)
        finally:
            sys.setswitchinterval(switch_interval_s)
            if self._vision is not None:
                self._vision.close()
            if camera is not None:
                camera.close()
            world.close()
            if self._journal is not None:
                self._journal.close()

    def _serve(
        self,
        session: zenoh.Session,
        world: World,
        camera: CameraProcess | None,
        stop: threading.Event,
        ready: threading.Event | None,
    ) -> None:
        opts, site = self.options, self.options.site_id
        token = session.liveliness().declare_token(alive_key(site, "work_site"))
        self._declare_publishers(session)
        # Each key its own inbox: stops are validated as they arrive and only valid ones
        # queued (no flood can push one out), and a stop wakes this loop at once.
        wake = threading.Event()
        inbox_stop = stop_inbox(session, key(site, "stop"), wake)
        inbox_heartbeat = heartbeat_inbox(session, key(site, "heartbeat"), site, self._heard)
        inbox_program = session.declare_subscriber(
            key(site, "program"), zenoh.handlers.RingChannel(INBOX_CAPACITY)
        )
        controller = TaskController(world, load_robot(self.scene.robot.urdf_path))
        self._controller = controller
        self._wake = wake
        # Programs are decoded and checked whole on a thread of their own: a long one must
        # not hold this loop (its states, its stops) up.
        checking_done = threading.Event()
        checker = threading.Thread(
            target=self._check_programs, args=(inbox_program, checking_done), name="checker"
        )
        checker.start()
        tick_s = controller.steps_per_tick * world.time_step_s
        wall_tick_s = tick_s / opts.time_scale
        state_every = max(1, round(1.0 / (tick_s * opts.state_rate_hz)))
        ticks, t0 = 0, time.monotonic()
        late_since = (t0, 0)  # wall s and ticks when lateness was last reported
        log.info(
            "work site %r serving; physics %.0f Hz, state %.0f Hz, camera %.1f Hz",
            site,
            opts.physics_rate_hz,
            1.0 / (tick_s * state_every),
            self.scene.camera.frame_rate_hz if camera else 0.0,
        )
        if ready is not None:
            ready.set()
        try:
            while not stop.is_set():
                wake.clear()
                self._handle_stops(inbox_stop.drain())  # first, before any motion this period
                self._check_deadman(inbox_heartbeat)
                elapsed = time.monotonic() - t0
                due = int(elapsed / wall_tick_s) - ticks
                if due > MAX_CATCH_UP_TICKS:
                    self.stats["late_ticks"] += due - MAX_CATCH_UP_TICKS
                    t0 += (due - MAX_CATCH_UP_TICKS) * wall_tick_s  # drop the backlog
                    due = MAX_CATCH_UP_TICKS
                    late_since = self._warn_late(late_since, ticks, tick_s)
                for _ in range(due):
                    try:
                        self._control_tick()
                        ticks += 1
                        if ticks % state_every == 0:
                            self._publish_robot_state(world)
                    except Exception as e:  # a fault of ours: stop safely, keep serving
                        ticks += 1
                        self._fault(e)
                self._handle_stops(inbox_stop.drain())
                self._start_ready()
                inbox_stop.dropped.summarize(elapsed)
                inbox_heartbeat.dropped.summarize(elapsed)
                self._invalid_programs.summarize(elapsed)
                if camera is not None:
                    self._publish_camera(camera, elapsed)
                    self._request_frame(camera, world, elapsed)
                if self._vision is not None:
                    self._publish_recognitions()
                self._publish_heartbeat(elapsed)
                sleep_s = t0 + (ticks + 1) * wall_tick_s - time.monotonic()
                if sleep_s > 0:
                    wake.wait(sleep_s)
        finally:
            checking_done.set()
            checker.join()
            if self._journal is not None:  # its reports go out once on file
                self._journal.sync(CLOSE_DRAIN_S)
            self._pub_report.close()
            inbox_program.undeclare()
            inbox_stop.undeclare()
            inbox_heartbeat.undeclare()
            token.undeclare()
            log.info("work site %r stopped: %s", site, self.stats)

    def _declare_publishers(self, session: zenoh.Session) -> None:
        """One publisher per topic, each with its sequence numbers and due times reset."""
        site = self.options.site_id
        drop = zenoh.CongestionControl.DROP
        self._pub_state = session.declare_publisher(
            key(site, "robot_state"), congestion_control=drop, priority=zenoh.Priority.DATA_HIGH
        )
        self._pub_camera = session.declare_publisher(
            key(site, "camera"), congestion_control=drop, priority=zenoh.Priority.DATA_LOW
        )
        # Heartbeats and recognitions go with the commands (protocol.session.PRIORITY_RANGES):
        # the round trip the beats measure is the commands', and the operator waits on both.
        self._pub_heartbeat = session.declare_publisher(
            key(site, "heartbeat"), priority=zenoh.Priority.REAL_TIME
        )
        self._pub_recognitions = session.declare_publisher(
            key(site, "recognitions"), priority=zenoh.Priority.INTERACTIVE_LOW
        )
        # The judge's ground truth goes with the commands too: on a link too slow for the
        # camera, the streams' link queues frames and would starve it.
        self._pub_truth = (
            session.declare_publisher(
                key(site, "truth"), congestion_control=drop, priority=zenoh.Priority.INTERACTIVE_LOW
            )
            if self.options.publish_truth
            else None
        )
        self._pub_report = Outbox(
            session.declare_publisher(
                key(site, "report"),
                priority=zenoh.Priority.INTERACTIVE_HIGH,
                congestion_control=zenoh.CongestionControl.BLOCK,
            )
        )
        self._seq_state = self._seq_frame = self._seq_heartbeat = 0
        self._next_frame_s = self._next_heartbeat_s = self._next_vision_s = 0.0

    def _control_tick(self) -> None:
        """One control period: the running program's, or the controller's holding."""
        if self._running():
            self._execution.tick()
        else:
            self._controller.tick()
        self._release_finished()

    def _release_finished(self) -> None:
        """Once the running program has finished, the next may be checked."""
        execution = self._execution
        if execution is not None and execution.finished:
            with self._lock:
                if self._busy == execution.program.program_id:
                    self._busy = None
                    self._still_since_s = time.time()

    def _publish_robot_state(self, world: World) -> None:
        """Send the arm's state, or skip it while the link asks for fewer (its ``seq`` counts
        every state all the same: the states' clock)."""
        state = self._robot_state(world, self._seq_state)
        self._wrench_S = state.wrench_S
        self._seq_state += 1
        self._state_credit, due = self._paced(self._state_credit)
        if due:
            self._pub_state.put(encode(state))
            self.stats["states"] += 1

    def _paced(self, credit: float) -> tuple[float, bool]:
        """One more message of a stream is ready: the stream's new credit, and whether this
        one goes."""
        credit = min(1.0, credit + self._stream_scale())
        return (credit - 1.0, True) if credit >= 1.0 else (credit, False)

    def _stream_scale(self) -> float:
        """The fraction of their nominal rates the streams go at (``work_site.pacing``)."""
        if not self.options.stream_pacing:
            return 1.0
        return self._pacer.scale(time.time(), self._lease.holder(time.monotonic()))

    def _publish_camera(self, camera: CameraProcess, elapsed_s: float) -> None:
        """Publish the frame the camera finished, if any, and hand it to vision."""
        done = camera.poll()
        if done is None:
            return
        self.stats["renders"] += done.rendered
        # Paced on the wire only: vision sees every frame, whatever the operator's link.
        self._frame_credit, due = self._paced(self._frame_credit)
        if due:
            self._pub_camera.put(done.payload)
            self.stats["frames"] += 1
        # Vision gets the renderer's pixels, never the wire's (possibly JPEG).
        self._recognize(done, elapsed_s)

    def _request_frame(self, camera: CameraProcess, world: World, elapsed_s: float) -> None:
        """Ask the camera for the next frame when one is due and it is idle, and publish the
        ground truth it will show."""
        if elapsed_s < self._next_frame_s or camera.busy:
            return
        q, fingers = world.robot_joint_positions()
        poses = world.object_poses()
        quality = None
        if self.options.camera_encoding == "jpeg":
            quality = jpeg_quality(self._stream_scale(), self.options.camera_quality)
        camera.request(RenderRequest(self._seq_frame, time.time(), poses, q, fingers, quality))
        self._publish_truth(self._seq_frame, poses)
        self._seq_frame += 1
        period_s = 1.0 / self.scene.camera.frame_rate_hz
        self._next_frame_s = max(self._next_frame_s + period_s, elapsed_s)

    def _publish_truth(self, seq: int, poses: dict[str, np.ndarray]) -> None:
        """The simulation's ground truth, for end-to-end evaluation only."""
        if self._pub_truth is None:
            return
        truth = tuple(ObjectPose(name=n, X_WO=X) for n, X in poses.items())
        self._pub_truth.put(encode(TruthPoses(seq=seq, stamp_s=time.time(), objects=truth)))

    def _publish_heartbeat(self, elapsed_s: float) -> None:
        if elapsed_s < self._next_heartbeat_s:
            return
        now_s = time.monotonic()
        holder = self._lease.holder(now_s)
        echo_operator, echo_stamp_s, echo_held_s = self._lease.echo(now_s)
        beat = Heartbeat(
            site_id=self.options.site_id,
            role="work_site",
            seq=self._seq_heartbeat,
            stamp_s=time.time(),
            operator=holder,
            echo_stamp_s=echo_stamp_s,
            echo_held_s=echo_held_s,
            echo_operator=echo_operator,
        )
        self._pub_heartbeat.put(encode(beat))
        self._seq_heartbeat += 1
        self._next_heartbeat_s += 1.0 / self.options.heartbeat_rate_hz

    def _warn_late(self, since: tuple[float, int], ticks: int, tick_s: float) -> tuple[float, int]:
        """Warn (at most every :data:`LATE_WARNING_PERIOD_S`, the first time that long after the
        start, past start-up's hiccups) that the simulation runs slower than its time scale,
        with the scale achieved since the last mark ``since`` (wall s, ticks);
        returns the new mark."""
        now, late = time.monotonic(), self.stats["late_ticks"]
        wall_s = now - since[0]
        if wall_s < LATE_WARNING_PERIOD_S:
            return since
        achieved = (ticks - since[1]) * tick_s / wall_s
        log.warning(
            "falling behind: simulating at %.2f× real time over the last %.1f s, asked %.2f× "
            "(the machine is too slow or too loaded; %.1f s of simulated time late so far)",
            achieved,
            wall_s,
            self.options.time_scale,
            late * tick_s,
        )
        return now, ticks

    def _recognize(self, frame: RenderedFrame, elapsed_s: float) -> None:
        """Hand a new frame to vision if it is idle: for a full search if its rate allows,
        else (with tracking on, and no program running) to follow the objects it found."""
        vision = self._vision
        if vision is None:
            return
        if elapsed_s >= self._next_vision_s:
            if vision.request(frame):
                self._next_vision_s = elapsed_s + 1.0 / self.options.vision_rate_hz
        elif self.options.vision_tracking and not self._running():
            # Tracking serves the poses fused while the scene holds still; while a program
            # moves things nothing is fused, and the cores are the control loop's and the
            # operator's heartbeats' to share.
            vision.request(frame, track=True)

    def _running(self) -> bool:
        """Whether a program is under way."""
        execution = self._execution
        return execution is not None and not execution.finished

    def _publish_recognitions(self) -> None:
        """Publish what vision found in the last frame it finished, if any."""
        result = self._vision.poll()
        if result is None:
            return
        if result.error:
            log.warning("vision failed on frame %d: %s", result.seq, result.error)
        if result.note:
            log.info("vision: %s", result.note)
        if result.tracked:
            self.stats["tracked"] += 1
        # A frame taken while a program may have moved something is reported on its own, and
        # the tracks start afresh after it.
        moving = self._running() or result.stamp_s < self._still_since_s
        if moving:
            self._fusion.reset()
        objects = tuple(
            Recognition(
                model=f.model,
                X_WO=f.X_WO,
                score=f.score,
                frames=f.frames,
                spread_m=f.spread_m,
                spread_rad=f.spread_rad,
                searches=f.searches,
                rivals=f.rivals,
            )
            for f in self._fusion.add(result.objects, searched=not result.tracked)
        )
        if moving:
            self._fusion.reset()
        self._pub_recognitions.put(
            encode(
                Recognitions(
                    seq=result.seq,
                    stamp_s=result.stamp_s,
                    elapsed_s=result.elapsed_s,
                    objects=objects,
                    tracked=result.tracked,
                )
            )
        )
        self.stats["recognitions"] += 1

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

    def _fault(self, error: Exception) -> None:
        """An internal error in a control period: hold the arm, fail the program, log it
        (with the traceback once per kind), and go on serving."""
        self.stats["faults"] = self.stats.get("faults", 0) + 1
        kind = type(error).__name__
        if kind not in self._faults_logged:
            self._faults_logged.add(kind)
            log.exception("internal fault in the control loop; arm held")
        else:
            log.error("internal fault in the control loop (%s); arm held", error)
        try:
            if self._running():
                self._execution.stop(f"work-site fault: {kind}: {error}")
            else:
                self._controller.stop()
            self._release_finished()
        except Exception:
            log.exception("could not stop cleanly after the fault")

    def _report(
        self, program_id: str, command_index: int, status: str, message: str, fresh: bool = True
    ) -> None:
        """Send (and journal) a report; ``fresh``: with the wrench read now (the control
        loop's thread only), else the last control period's."""
        wrench_S = self._controller.world.robot_snapshot().wrench_S if fresh else self._wrench_S
        with self._lock:
            payload = encode(
                ExecutionReport(
                    program_id=program_id,
                    command_index=command_index,
                    status=status,
                    wrench_S=wrench_S,
                    message=message[:4096],
                    stamp_s=time.time(),
                    seq=len(self._reports.get(program_id, ())),
                )
            )
            remembered = self._reports.get(program_id)
            if remembered is not None:
                remembered.append(payload)
            if remembered is not None and self._journal is not None:
                # Sent once on file: a restart then knows every report the operators saw.
                self._journal.append(program_id, payload, partial(self._pub_report.put, payload))
            else:
                self._pub_report.put(payload)
        log.info("program %s command %d: %s %s", program_id, command_index, status, message)

    def _handle_stops(self, stops: list[Stop]) -> None:
        """Act on the valid stops received: end the running program, or hold the arm; a
        program being checked or waiting to start is cancelled."""
        for msg in stops:
            self._stops_seen += 1
            self._last_stop_reason = msg.reason
            if msg.cancels:
                self._cancel_ahead(msg.cancels, msg.reason)
            if self._running():
                self._execution.stop(f"stop: {msg.reason}")  # its report is the reply
            else:
                self._controller.stop(ease=True)
                now = time.monotonic()
                if now - self._stop_replied_s >= STOP_REPLY_PERIOD_S:
                    self._stop_replied_s = now
                    self._report(
                        STOP_REPLY_ID, -1, "stopped",
                        f"stop received ({msg.reason}): no program was running; the arm is held",
                    )  # fmt: skip
            log.info("stop: %s", msg.reason)

    def _start_ready(self) -> None:
        """Start the program that passed its check, unless a stop came since its check began
        (control loop's thread)."""
        with self._lock:
            item = self._ready.popleft() if self._ready else None
        if item is None:
            return
        program, stops_seen, approaches = item
        if stops_seen != self._stops_seen:
            self._cancel(program.program_id, "before it started")
            return
        surface = self.options.surface_stiffness_n_per_m
        impedance = Impedance(tangential_stiffness_n_per_m=surface)
        # A resumed program goes on where the stopped one was (the intake made sure it is the
        # last to have run): holding what it held, at the command it was in.
        last = self._execution if program.continues else None
        self._execution = Execution(
            program,
            self._controller,
            self._report,
            impedance=impedance,
            holding=last is not None and last.holding,
            start=0 if last is None else last.index,
            approaches=approaches,
        )
        self._execution_started_s = time.monotonic()

    def _heard(self, beat: Heartbeat) -> None:
        """An operator's heartbeat came (zenoh's thread): the lease hears it, with the round
        trip it measured when it echoes one of ours, and the pacer how late our streams
        arrive when it echoes a robot state."""
        now_s, now_mono_s = time.time(), time.monotonic()
        round_trip_s = beat.round_trip_s(now_s)
        self._lease.heard(beat.operator, now_mono_s, round_trip_s, beat.stamp_s, beat.echo_stamp_s)
        if (state_round_trip_s := beat.state_round_trip_s(now_s)) is not None:
            arrived_s = beat.stamp_s - beat.state_echo_held_s  # the operator's clock
            self._pacer.heard(
                beat.operator, now_s, state_round_trip_s, beat.state_echo_s, arrived_s
            )

    def _check_deadman(self, inbox_heartbeat) -> None:
        """Stop the running program when the operator's heartbeats stopped coming: the newest
        beat, or the program's start if later, is older than :func:`deadman_timeout_s`."""
        now = time.monotonic()
        stalled_s = now - self._deadman_checked_s
        stalled = stalled_s > DEADMAN_STALL_S
        self._deadman_checked_s = now
        inbox_heartbeat.pull()  # every iteration: the lease hears its holder while idle too
        execution = self._execution
        if execution is None or execution.finished:
            return
        inbox_heartbeat.drain()  # only when the newest came matters
        # A named operator's program lives on its own operator's beats, not a watcher's.
        operator = execution.program.operator
        heard_s = self._lease.last_heard_s(operator) if operator else inbox_heartbeat.last_s
        last_s = max(heard_s or 0.0, self._execution_started_s)
        # After a stall of this process, beats that came meanwhile may still be in the socket's
        # buffers: judge at the next iteration (unless silence is long past doubt).
        silent_s = now - last_s
        round_trip_s = self._lease.round_trip_s(operator) if operator else None
        deadman_s = deadman_timeout_s(self.options.deadman_s, round_trip_s)
        if silent_s > deadman_s and (not stalled or silent_s > 2 * deadman_s):
            beat = inbox_heartbeat.last
            # Whether the beat was sent late or arrived late (the operator's clock may differ).
            log.warning(
                "dead-man: %.3f s without a heartbeat (the last, #%s, sent %s s ago by the "
                "operator's clock); this loop's last iteration %.3f s ago",
                silent_s,
                "-" if beat is None else beat.seq,
                "-" if beat is None else f"{time.time() - beat.stamp_s:.3f}",
                stalled_s,
            )
            why = f"no heartbeat from the operator for {deadman_s:.3g} s"
            if deadman_s != self.options.deadman_s:
                why += f" ({self.options.deadman_s:g} s and round trips of {round_trip_s:.3f} s)"
            execution.stop(why)
            self.stats["deadman"] = self.stats.get("deadman", 0) + 1
            self._release_finished()
