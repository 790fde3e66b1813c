"""The whole chain against a work site, for any task: connect (or start a work site on
loopback), build the model from vision as a person would, let the task's operator demonstrate,
make the program, send it, follow it, see with vision where the block ended
(:mod:`operator_site.placement`), and judge the block's true final pose.

The scripted rehearsed tasks (:mod:`operator_site.scripted`) and task files
(:mod:`operator_site.runner`) differ only in their :class:`ChainTask`: the operator's drag and
the judging.
"""

from __future__ import annotations

import itertools
import math
import os
import re
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from models.scene import Scene, load_scene
from operator_site.failures import RunError
from operator_site.link import WorkSiteLink
from operator_site.model_editor import Correction, WorkSiteModel
from operator_site.placement import check_placement
from operator_site.program import Generated
from operator_site.session import (
    ACCEPT_SCORE,
    OperatorSession,
    generated_program,
)
from operator_site.task import TaskSession
from operator_site.taskfile import pose_error
from protocol import Recognition, Recognitions, TruthPoses, decode, make_config
from protocol.messages import contact_directions
from protocol.session import free_port_pair, link_endpoints

_RUN_NUMBERS = itertools.count()
"""Numbers the runs of this process (their work sites' ids and logs)."""

CONNECT_TIMEOUT_S = 60.0
VISION_TIMEOUT_S = 120.0
VISION_FRAMES = 3
"""Searched frames waited for at most while they come back empty."""
MIN_SEARCHES = 3
"""A block is taken into the model once this many of vision's full searches have found it in
one placement (``Recognition.searches``): its pose is then the median of that placement's
sightings, which one frame's outlier moves little, and not a single search's mistake that
tracking carried on."""
WORKPIECE_FRAMES = 8
"""Searched frames looked at in all, at most, while none fit for the task's workpiece is
among them (4 s at the work site's 2 Hz); the tracked frames between are read too."""
FRAME_TIMEOUT_S = 10.0
"""A next recognised frame is waited for at most this long (the work site sends one a 0.5 s)."""
EXECUTE_TIMEOUT_S = 240.0
STATE_RATE_HZ = 100.0
"""The started work site's robot-state rate: one state a simulated control period, so that
counting states over the execution measures the time scale it really achieved."""
SLOW_TIME_SCALE_FRACTION = 0.9
"""A work site simulating at less than this fraction of its asked time scale is reported: the
physics is stepped alike (per control period, not per wall second), but the run takes longer
than asked."""


@dataclass(frozen=True, eq=False)
class RecognisedModel:
    """The model the scripted operator built from vision: the model, the model editor's
    corrections, the searched frames looked at, the vision time of every frame looked at
    summed (s), the model editor's time for the last build (s), the tracked frames looked
    at, and the blocks left out of the model that some frame saw in more than one place."""

    model: WorkSiteModel
    corrections: list[Correction]
    frames: int
    vision_s: float
    model_s: float
    tracked_frames: int = 0
    contested: tuple[str, ...] = ()


def model_from_frames(
    scene: Scene,
    frames: Iterable[Recognitions],
    ready: Callable[[WorkSiteModel], bool],
    log: Callable[[str], None] = lambda _: None,
    max_frames: int = WORKPIECE_FRAMES,
    operator: OperatorSession | None = None,
    trusted: bool = False,
) -> RecognisedModel:
    """The model built as a person builds it in the page (``operator``'s, or a new operator
    session's), who takes a block into the model once vision's searches have found it in the
    same place :data:`MIN_SEARCHES` times and in no other place lately (no
    :attr:`~protocol.Recognition.rivals`): a recognition scoring at least
    :data:`~operator_site.session.ACCEPT_SCORE` that says so is accepted, and the model made
    consistent. Each frame has its own sensor noise: one that mistakes a block for another, or
    turns it, is not taken at its word. Frames are read until ``ready`` says the model holds
    what the task needs, ``max_frames`` searched frames in all at most (and the tracked frames
    between). ``trusted``: the frames are the ground truth, each taken at its word."""
    op = operator or OperatorSession(scene)
    corrections: dict[str, Correction] = {}
    n, vision_s, model_s = 0, 0.0, 0.0
    tracked = 0
    contested: set[str] = set()  # seen in more than one place by some frame
    for recs in frames:
        n += not recs.tracked
        tracked += recs.tracked
        vision_s += recs.elapsed_s
        log(f"frame {n}: recognised {[(r.model, round(r.score, 2)) for r in recs.objects]}")
        seen = {}
        for r in recs.objects:
            if r.score >= ACCEPT_SCORE:
                seen.setdefault(r.model, r)  # a second of one block is not a block of the scene
        steady = [
            r
            for name, r in seen.items()
            if name not in op.model.poses
            and (trusted or (r.searches >= MIN_SEARCHES and r.rivals == 0))
        ]
        contested |= {name for name, r in seen.items() if r.rivals}
        if steady:
            t0 = time.monotonic()
            try:
                op.accept_all(replace(recs, objects=tuple(steady)))
            except ValueError as e:
                log(f"frame {n}: not added to the model: {e}")
            corrections |= {c.name: c for c in op.corrections}
            model_s += time.monotonic() - t0
        if ready(op.model) or (n >= max_frames and not recs.tracked):
            break
    unsure = tuple(sorted(contested - set(op.model.poses)))
    return RecognisedModel(
        op.model, list(corrections.values()), n, vision_s, model_s, tracked, unsure
    )


ProgramMaker = Callable[[TaskSession, str], Generated]
"""Makes the program for a demonstration's task session and a program id."""


class _Truth:
    """The work site's ground truth as the link hears it (``WorkSiteLink.follow``: also after
    the link renewed its session)."""

    def __init__(self, link: WorkSiteLink) -> None:
        self.latest: TruthPoses | None = None
        link.follow("truth", self._on)

    def _on(self, sample) -> None:
        self.latest = decode(sample.payload.to_bytes(), expected=TruthPoses)

    def latest_after(self, t_s: float, timeout_s: float = 5.0) -> TruthPoses:
        """The first ground truth stamped at or after ``t_s`` (wall-clock s)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            truth = self.latest
            if truth is not None and truth.stamp_s >= t_s:
                return truth
            time.sleep(0.05)
        raise TimeoutError(
            "no ground truth from the work site (a simulated work site publishes it with "
            "--publish-truth; a real one has none to judge the task by)"
        )


def _model_error(model: WorkSiteModel, X_truth: dict[str, np.ndarray]) -> dict[str, list]:
    """Each modelled block's pose against the truth ``X_truth``, up to its symmetries:
    ``{name: [mm, degrees]}``."""
    out = {}
    for name, X in model.poses.items():
        if name in X_truth:
            error_m, error_rad = pose_error(X_truth[name], X, model.symmetries(name))
            out[name] = [round(error_m * 1e3, 2), round(math.degrees(error_rad), 2)]
    return out


class _ExecutionWatch:
    """What the operator waits for while its program runs: its first report, and the camera
    (how old each frame is as it arrives, how often they come)."""

    def __init__(self, link: WorkSiteLink, program_id: str, sent_s: float) -> None:
        self._link, self._program_id, self._sent_s = link, program_id, sent_s
        self._first_report_s: float | None = None
        self._frame_seq = -1 if link.camera_frame is None else link.camera_frame.seq
        self._ages_s: list[float] = []
        self._rates_hz: list[float] = []

    def look(self) -> None:
        """Take in what the link holds now."""
        status = self._link.status
        if self._first_report_s is None and any(
            r.program_id == self._program_id for r in status.reports
        ):
            self._first_report_s = time.monotonic() - self._sent_s
        frame = self._link.camera_frame
        if frame is not None and frame.seq != self._frame_seq:
            self._frame_seq = frame.seq
            self._rates_hz.append(status.frame_rate_hz)
            if status.frame_age_s is not None:
                self._ages_s.append(status.frame_age_s)

    def summary(self) -> dict:
        """``first_report_s`` (program sent to its first report heard, s), and the median
        ``frame_age_s`` and ``frame_rate_hz`` over the frames that arrived (None: none)."""
        return {
            "first_report_s": self._first_report_s,
            "frame_age_s": statistics.median(self._ages_s) if self._ages_s else None,
            "frame_rate_hz": statistics.median(self._rates_hz) if self._rates_hz else None,
        }


def _wait(predicate: Callable[[], bool], link: WorkSiteLink, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        link.poll()
        if predicate():
            return True
        time.sleep(0.02)
    return False


def _start_work_site(
    site_id: str,
    endpoint: str,
    log_path: Path,
    time_scale: float,
    extra_args: tuple[str, ...] = (),
) -> subprocess.Popen:
    cmd = [
        sys.executable, "-m", "work_site", "serve", "--listen", endpoint, "--site-id", site_id,
        "--vision-rate", "2", "--time-scale", str(time_scale),
        "--state-rate", str(STATE_RATE_HZ), "--publish-truth", *extra_args,
    ]  # fmt: skip
    with log_path.open("w") as out:
        return subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)


def _frames_after(link: WorkSiteLink, after_s: float) -> Iterator[Recognitions]:
    """Vision's frames taken after ``after_s`` (the work site's clock, s) as they arrive, until
    none comes within :data:`FRAME_TIMEOUT_S`."""
    last = -1

    def fresh() -> bool:
        r = link.recognitions
        return r is not None and r.seq != last and r.stamp_s > after_s

    while _wait(fresh, link, FRAME_TIMEOUT_S):
        recs = link.recognitions
        last = recs.seq
        yield recs


def _recognised_frames(link: WorkSiteLink) -> Iterator[Recognitions]:
    """The work site's recognised frames as they arrive: first the first one with objects (or
    the :data:`VISION_FRAMES`-th searched one if they all come back empty; RuntimeError if
    none within :data:`VISION_TIMEOUT_S`), then each next one until none comes within
    :data:`FRAME_TIMEOUT_S`."""
    seen: list[Recognitions] = []

    def arrived(after: int, need_objects: bool) -> Callable[[], bool]:
        def check() -> bool:
            r = link.recognitions
            if r is not None and (not seen or seen[-1].seq != r.seq):
                seen.append(r)
            if len(seen) <= after:
                return False
            searched = sum(not r.tracked for r in seen)
            return not need_objects or bool(seen[-1].objects) or searched >= VISION_FRAMES

        return check

    if not _wait(arrived(0, need_objects=True), link, VISION_TIMEOUT_S):
        raise RuntimeError(f"no recognitions within {VISION_TIMEOUT_S:.0f} s")
    yield seen[-1]
    while _wait(arrived(len(seen), need_objects=False), link, FRAME_TIMEOUT_S):
        yield seen[-1]


@dataclass(frozen=True)
class Judgement:
    """How the block ended at the work site against the task's goal: distance (m), angle
    (rad), whether that is within the goal's tolerances, the goal contacts that must be
    verified by force (by object), and more fields for the result."""

    error_m: float
    error_rad: float
    within: bool
    goal_contacts: tuple[str, ...] = ()
    extra: dict | None = None


@dataclass(frozen=True)
class ChainTask:
    """What one end-to-end run needs of its task: a label (the result's ``task``, the program
    id's prefix), when a model holds what the task needs (``ready``), the operator's
    demonstration on a model (an object with ``session``, ``workpiece``, ``ideal_X_WO``; raises
    :class:`RunError` or RuntimeError), a check of that demonstration before a program is
    made (raises :class:`RunError`), and the judgement of the block's true final pose given
    the work site's ground truth of every object."""

    label: str
    program_label: str
    ready: Callable[[WorkSiteModel], bool]
    demonstrate: Callable[[WorkSiteModel], object]
    judge: Callable[[object, WorkSiteModel, dict[str, np.ndarray]], Judgement]
    check: Callable[[object, WorkSiteModel], None] = lambda _demo, _model: None
    describe: Callable[[object], dict] = lambda _demo: {}


_VERIFIED_RE = re.compile(r"([A-Za-z0-9_.-]+) -?[0-9.]+ N along ")


def run_chain(
    task: ChainTask,
    seed: int,
    connect: str | None = None,
    site_id: str | None = None,
    scene: Scene | None = None,
    make_program: ProgramMaker = generated_program,
    log: Callable[[str], None] = lambda s: print(s, file=sys.stderr, flush=True),
    oracle: bool = False,
    time_scale: float = 1.0,
    work_site_args: tuple[str, ...] = (),
    seeded_layout: bool = True,
    dry_run: bool = False,
) -> dict:
    """The whole chain for ``task`` (see :func:`run_scripted`); ``seeded_layout``: the started
    work site lays the blocks out by ``seed`` (else as its scene file has them, unseeded);
    ``dry_run``: stop once the program is made and checked, sending nothing (``success`` then
    says there is a program). The result says ``failure`` (None, or its ``kind`` among
    :data:`FAILURES` and a ``message``)."""
    scene = scene or load_scene()
    stage_s: dict[str, float] = {}
    out: dict = {"task": task.label, "seed": seed, "success": False, "failure": None}
    out["stage_s"] = stage_s
    proc = None
    # The started work site's id names this process and this run too: two runs of one seed on
    # one machine (two benchmarks at once, or two tasks of one benchmark) must not hear each
    # other's ground truth, nor share a log.
    run = next(_RUN_NUMBERS)
    site_id = site_id or (f"e2e-{seed}-{os.getpid()}-{run}" if connect is None else "site1")
    if connect is None:
        connect = f"tcp/127.0.0.1:{free_port_pair()}"
        log_path = Path(tempfile.gettempdir()) / f"telerobot-{site_id}-work-site.log"
        # Its journal beside its log: a run's own, not one more file in the user's state.
        journal = log_path.with_name(f"telerobot-{site_id}-programs.jsonl")
        work_site_args = ("--journal", str(journal), *work_site_args)
        seed_args = ("--seed", str(seed)) if seeded_layout else ()
        proc = _start_work_site(
            site_id, connect, log_path, time_scale, (*seed_args, *work_site_args)
        )
        log(f"work site started (log: {log_path})")
    link = WorkSiteLink(make_config(connect=link_endpoints([connect])[0]), site_id)
    truth = _Truth(link)
    kind = "execution_failed"  # what an unexpected error means at the stage reached
    try:
        t0 = time.monotonic()
        if not _wait(lambda: link.status.label == "connected", link, CONNECT_TIMEOUT_S):
            raise RuntimeError(f"no work site at {connect} within {CONNECT_TIMEOUT_S:.0f} s")
        stage_s["connect"] = time.monotonic() - t0
        t0 = time.monotonic()
        kind = "not_recognised"
        if oracle:
            X_truth = {o.name: o.X_WO for o in truth.latest_after(time.time()).objects}
            truth_frame = Recognitions(
                seq=0,
                stamp_s=time.time(),
                elapsed_s=0.0,
                objects=tuple(
                    Recognition(model=n, X_WO=X, score=1.0)
                    for n, X in X_truth.items()
                    if not scene.object(n).fixed
                ),
            )
            frames: Iterable[Recognitions] = [truth_frame]
        else:
            frames = _recognised_frames(link)
        operator = OperatorSession(scene, link)
        rec = model_from_frames(scene, frames, task.ready, log, operator=operator, trusted=oracle)
        model, corrections = rec.model, rec.corrections
        stage_s["vision"], stage_s["model"] = rec.vision_s, rec.model_s
        out["vision_frames"] = rec.frames
        out["vision_tracked_frames"] = rec.tracked_frames
        stage_s["vision_wait"] = time.monotonic() - t0
        out["recognised"] = sorted(model.poses)
        out["corrections_mm"] = {c.name: round(c.moved_mm, 2) for c in corrections}
        if not oracle:  # the model against the truth before anything moved: vision's error
            X_before = {o.name: o.X_WO for o in truth.latest_after(time.time()).objects}
            out["model_error"] = _model_error(model, X_before)

        t0 = time.monotonic()
        try:
            demo = task.demonstrate(model)
        except (RunError, ValueError) as e:
            if not rec.contested:
                raise
            raise RunError(
                e.kind if isinstance(e, RunError) else kind,
                f"{e} (vision saw the {', '.join(rec.contested)} in more than one place)",
            ) from None
        session, workpiece, ideal = demo.session, demo.workpiece, demo.ideal_X_WO
        out["workpiece"] = workpiece
        out |= task.describe(demo)
        goal = session.X_WO[workpiece]
        final = session.sim.history[-1]
        stage_s["operator"] = time.monotonic() - t0
        required = sorted({c.object for c in final.contacts})
        out["contacts_required"] = len(contact_directions(final.contacts))
        out["contacts_required_objects"] = required
        out["goal_off_ideal_mm"] = float(np.linalg.norm(goal[:3, 3] - ideal[:3, 3]) * 1e3)
        kind = "infeasible"
        task.check(demo, model)

        t0 = time.monotonic()
        try:
            program = make_program(session, _program_id(task.program_label, seed)).program
        except ValueError as e:
            raise RunError("infeasible", f"no program for the demonstration: {e}") from None
        stage_s["program"] = time.monotonic() - t0
        out["commands"] = len(program.commands)
        stage_s["computation"] = sum(stage_s[k] for k in ("vision", "model", "program"))
        out["sent"] = not dry_run
        if dry_run:
            out["success"] = True
            return out

        t0 = time.monotonic()
        kind = "execution_failed"
        state0 = link.robot_state
        program = operator.send(program)
        watch = _ExecutionWatch(link, program.program_id, t0)

        def finished() -> bool:
            watch.look()
            return operator.outcome(program.program_id) is not None

        if not _wait(finished, link, EXECUTE_TIMEOUT_S):
            raise RuntimeError(f"the program did not finish within {EXECUTE_TIMEOUT_S:.0f} s")
        stage_s["execute"] = time.monotonic() - t0
        out |= watch.summary()
        if proc is not None and state0 is not None and link.robot_state is not None:
            simulated_s = (link.robot_state.seq - state0.seq) / STATE_RATE_HZ
            out["time_scale"] = time_scale
            out["time_scale_achieved"] = simulated_s / stage_s["execute"]
            if out["time_scale_achieved"] < SLOW_TIME_SCALE_FRACTION * time_scale:
                log(
                    f"warning: the work site simulated at {out['time_scale_achieved']:.2f}× "
                    f"real time, asked {time_scale:g}× (the machine is too slow or loaded: "
                    "the physics is the same, the run slower)"
                )
        reports = [r for r in link.status.reports if r.program_id == program.program_id]
        out["execution"] = f"{reports[-1].status}: {reports[-1].message}"
        verified = [r for r in reports if r.status == "contact_verified"]
        out["contacts_verified"] = verified[-1].message.count(" N along ") if verified else 0
        verified_objects = set(_VERIFIED_RE.findall(verified[-1].message)) if verified else set()
        out["contacts_verified_objects"] = sorted(verified_objects)

        kind = "goal_missed"
        check = None
        if reports[-1].status == "done" and not oracle:
            # What the operator can know without the truth: where vision sees the block now.
            t0 = time.monotonic()
            others = {
                name: (X_WO, model.symmetries(name))
                for name, X_WO in model.poses.items()
                if name != workpiece
            }
            check = check_placement(
                workpiece, goal, model.symmetries(workpiece),
                _frames_after(link, reports[-1].stamp_s), others=others,
            )  # fmt: skip
            stage_s["vision_check"] = time.monotonic() - t0
            out["vision_check"] = check.to_json()
            log(check.sentence())
        X_truth = {o.name: o.X_WO for o in truth.latest_after(time.time() + 0.3).objects}
        if workpiece not in X_truth:
            raise ValueError(f"the work site's ground truth has no {workpiece!r}")
        for obj in scene.objects:  # the fixed objects where the truth does not list them
            X_truth.setdefault(obj.name, obj.X_WO)
        judgement = task.judge(demo, model, X_truth)
        out["final_error_mm"] = judgement.error_m * 1e3
        out["final_error_deg"] = math.degrees(judgement.error_rad)
        out |= judgement.extra or {}
        missing = sorted(set(judgement.goal_contacts) - verified_objects)
        contacts_ok = out["contacts_verified"] >= out["contacts_required"] and not missing
        moved = check is not None and check.verdict == "moved"
        out["success"] = bool(
            reports[-1].status == "done" and judgement.within and contacts_ok and not moved
        )
        if reports[-1].status == "refused":
            out["failure"] = _failure("program_refused", out["execution"])
        elif reports[-1].status != "done":
            out["failure"] = _failure("execution_failed", out["execution"])
        elif moved:
            out["failure"] = _failure("goal_missed", f"the program ended, but {check.sentence()}")
        elif not judgement.within:
            off = f"{out['final_error_mm']:.2f} mm, {out['final_error_deg']:.2f}°"
            out["failure"] = _failure("goal_missed", f"the block ended {off} from the goal")
        elif not contacts_ok:
            why = ", ".join(missing) or f"{out['contacts_verified']} of the directions"
            out["failure"] = _failure("goal_missed", f"contacts not verified: {why}")
    except RunError as e:
        out["error"] = str(e)
        out["failure"] = _failure(e.kind, str(e))
    except (RuntimeError, TimeoutError, ValueError) as e:
        out["error"] = str(e)
        out["failure"] = _failure(kind, str(e))
    finally:
        link.close()
        if proc is not None:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
            # The started work site's log and journal tell why a run failed; a run that did
            # its task leaves nothing behind (a benchmark runs hundreds).
            if out["success"]:
                log_path.unlink(missing_ok=True)
                journal.unlink(missing_ok=True)
            else:
                out["work_site_log"] = str(log_path)
    return out


def _failure(kind: str, message: str) -> dict:
    return {"kind": kind, "message": message}


def _program_id(label: str, seed: int) -> str:
    """A program id (letters, digits, ``_.-`` only) made of ``label``, the seed and the time."""
    slug = re.sub(r"[^A-Za-z0-9_.-]+", "-", label).strip("-")[:40] or "task"
    return f"{slug}-{seed}-{int(time.time())}"
