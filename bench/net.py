"""``python -m bench net``: round trips and camera frames over zenoh, beside plain TCP.

What is measured (all round trips sequential ping-pong: send, wait for the answer, repeat; the
kinds interleaved sample by sample, taking turns to go first, so they share the same conditions):

- ``raw_zenoh_rtt``: bare zenoh, a put on ``bench/raw/ping`` answered by the same bytes on
  ``bench/raw/pong`` by another process (no codec).
- ``zenoh_rtt``: our command path: an encoded :class:`~protocol.Stop` on ``key(site, "stop")``
  (priority REAL_TIME, as ``operator_site.link`` sends it), decoded and validated by an echo
  process that answers with an encoded :class:`~protocol.ExecutionReport` on
  ``key(site, "report")`` (priority INTERACTIVE_HIGH, as the work site does), decoded and checked
  here. The work site itself has no reply to a stop, and its reply to a program waits for its
  10 ms control tick, so the echo process stands in for it; ``site_program_reply_ms_*`` is that
  real work-site round trip (a program refused as unsafe), for reference.
- ``tcp_rtt``: the same Stop bytes, length-prefixed, echoed over one plain TCP connection
  (TCP_NODELAY both ends).
- ``frame_fps``, ``frame_latency_ms_median``: a real ``work-site serve`` (camera on) on loopback;
  latency from the render request (the image's capture time) to the decoded frame here.
- ``command_delay_by_images_ms``: how much later a command's answer comes while the echo process
  also publishes raw camera frames (the scene camera's size and rate, DROP, DATA_LOW: as the work
  site does) over the same session: median round trip with images minus without.
- ``link_*``: the same over the emulated link of ``deploy/netns.py`` (default 50 ms each way,
  1 % loss each way): echo process in the work namespace, client in the operator namespace.
- ``net_frames.*`` (written apart from ``net.json``; ``--net-only-frames`` runs just this):
  camera frame size on the wire as a knob, per ``--net-frame-encodings`` (raw, png, jpeg:Q):
  bytes per frame, encode and decode ms, the decoded pixels' error, frames from a real work
  site on loopback, and over the emulated link (also rate-limited, ``--net-frame-rates-mbit``)
  fps, latency and the command delay while a real work-site frame streams in that encoding.
- Every zenoh session here uses two links as the sites do (``protocol.session.link_endpoints``:
  priorities 0-3 on one port, robot state's and camera frames' 4-7 on the next);
  ``link_single_*`` repeats the link measurements over one link for all priorities, for comparison.

zenoh's shared memory is off (``make_config``'s default), as between two machines.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import signal
import socket
import statistics
import struct
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from deploy import netns
from protocol import (
    CameraFrame,
    ExecutionReport,
    MotionCommand,
    MotionProgram,
    Stop,
    decode,
    encode,
    key,
    make_config,
    parse_image_encoding,
)
from protocol.session import free_port_pair, link_endpoints, split_endpoints
from protocol.signals import install_stop_signals

REPO = Path(__file__).resolve().parents[1]
RAW_PING, RAW_PONG, CONTROL = "bench/raw/ping", "bench/raw/pong", "bench/control"
SITE_ID = "bench"
LENGTH = struct.Struct("!I")
READY_TIMEOUT_S = 60.0
ZEROS6 = np.zeros(6)


def _percentile(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) if values else float("nan")


def _summary(values: list[float]) -> tuple[float, float]:
    return (statistics.median(values) if values else float("nan")), _percentile(values, 99)


# ------------------------------------------------------------------------ the echo process


def _recv_exact(conn: socket.socket, n: int) -> bytes:
    buf = bytearray()
    while len(buf) < n:
        chunk = conn.recv(n - len(buf))
        if not chunk:
            raise ConnectionError("peer closed")
        buf += chunk
    return bytes(buf)


def _tcp_echo(server: socket.socket) -> None:
    while True:
        conn, _ = server.accept()
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        threading.Thread(target=_tcp_echo_conn, args=(conn,), daemon=True).start()


def _tcp_echo_conn(conn: socket.socket) -> None:
    with conn:
        try:
            while True:
                (n,) = LENGTH.unpack(_recv_exact(conn, LENGTH.size))
                conn.sendall(LENGTH.pack(n) + _recv_exact(conn, n))
        except (ConnectionError, OSError):
            return


def _camera_frames(session: zenoh.Session, stop: threading.Event, spec: list[str]) -> None:
    """Publish frames of ``spec = [width, height, rate_hz[, encoding, quality[, image.npy]]]``
    until ``stop`` is set: random pixels unless an image file is given, ``raw`` unless an
    encoding is. Each frame is encoded anew (the encoding's CPU cost is part of its latency, as
    at the work site)."""
    width, height, rate_hz = int(spec[0]), int(spec[1]), float(spec[2])
    encoding, quality = (spec[3], int(spec[4])) if len(spec) > 4 else ("raw", 90)
    pub = session.declare_publisher(
        key(SITE_ID, "camera"),
        congestion_control=zenoh.CongestionControl.DROP,
        priority=zenoh.Priority.DATA_LOW,
    )
    if len(spec) > 5:
        image = np.load(spec[5])
        height, width = image.shape
    else:
        image = np.random.default_rng(0).integers(0, 256, (height, width), dtype=np.uint8)
    K = np.array([[500.0, 0, width / 2], [0, 500.0, height / 2], [0, 0, 1]])
    seq, next_s = 0, time.monotonic()
    while not stop.is_set():
        pub.put(
            encode(
                CameraFrame(
                    seq=seq,
                    stamp_s=time.time(),
                    X_WC=np.eye(4),
                    K=K,
                    dist=np.zeros(5),
                    image=image,
                    encoding=encoding,
                    quality=quality,
                )
            )
        )
        seq += 1
        next_s += 1.0 / rate_hz
        stop.wait(max(0.0, next_s - time.monotonic()))
    pub.undeclare()


def serve_echo(zenoh_listen: list[str], tcp_port: int) -> int:
    """The echo process: raw pong, Stop→ExecutionReport echo, TCP echo, camera on demand."""
    server = socket.create_server(("0.0.0.0", tcp_port))
    threading.Thread(target=_tcp_echo, args=(server,), daemon=True).start()
    with zenoh.open(make_config(listen=zenoh_listen)) as session:
        fifo = zenoh.handlers.FifoChannel
        remote = zenoh.Locality.REMOTE
        raw_in = session.declare_subscriber(RAW_PING, fifo(1024), allowed_origin=remote)
        raw_out = session.declare_publisher(RAW_PONG, priority=zenoh.Priority.REAL_TIME)
        stop_in = session.declare_subscriber(
            key(SITE_ID, "stop"), fifo(1024), allowed_origin=remote
        )
        report_out = session.declare_publisher(
            key(SITE_ID, "report"), priority=zenoh.Priority.INTERACTIVE_HIGH
        )
        control = session.declare_subscriber(CONTROL, fifo(16), allowed_origin=remote)

        def raw_loop() -> None:
            for sample in raw_in.handler:  # ends with an error when the session closes
                raw_out.put(sample.payload)

        def stop_loop() -> None:
            # Blocking receive on our own thread, never work inside zenoh's callback.
            for sample in stop_in.handler:
                msg = decode(sample.payload.to_bytes(), expected=Stop)
                report = ExecutionReport(
                    program_id="bench",
                    command_index=-1,
                    status="stopped",
                    wrench_S=ZEROS6,
                    message=msg.reason,
                    stamp_s=time.time(),
                )
                report_out.put(encode(report))

        camera_stop = threading.Event()
        done = threading.Event()

        def control_loop() -> None:
            nonlocal camera_stop
            for sample in control.handler:
                words = sample.payload.to_bytes().decode().split()
                camera_stop.set()
                if words[:2] == ["camera", "on"]:
                    camera_stop = threading.Event()
                    threading.Thread(
                        target=_camera_frames, args=(session, camera_stop, words[2:]), daemon=True
                    ).start()
                elif words == ["quit"]:
                    done.set()

        for loop in (raw_loop, stop_loop, control_loop):
            threading.Thread(target=_quietly, args=(loop,), daemon=True).start()
        install_stop_signals(done, "netbench")
        print("netbench: ready", flush=True)
        # The main thread only waits (with a timeout, so that a signal's handler gets to run).
        while not done.wait(0.2):
            pass
        camera_stop.set()
        time.sleep(0.1)  # the camera thread undeclares its publisher before the session closes
    return 0


def _quietly(loop: Any) -> None:
    try:
        loop()
    except Exception:  # the session closed under a blocking receive: the process is ending
        return


# ----------------------------------------------------------------------------- the client


class _Client:
    """The measuring side: one zenoh session and one TCP connection to the echo process."""

    def __init__(self, zenoh_connect: list[str], tcp_addr: str) -> None:
        self.session = zenoh.open(make_config(connect=zenoh_connect))
        s = self.session
        fifo, remote = zenoh.handlers.FifoChannel, zenoh.Locality.REMOTE
        self.raw_out = s.declare_publisher(RAW_PING, priority=zenoh.Priority.REAL_TIME)
        self.raw_in = s.declare_subscriber(RAW_PONG, fifo(1024), allowed_origin=remote)
        self.stop_out = s.declare_publisher(key(SITE_ID, "stop"), priority=zenoh.Priority.REAL_TIME)
        self.report_in = s.declare_subscriber(
            key(SITE_ID, "report"), fifo(1024), allowed_origin=remote
        )
        self.control = s.declare_publisher(CONTROL)
        host, port = tcp_addr.rsplit(":", 1)
        self.sock = socket.create_connection((host, int(port)), timeout=30.0)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.payload = encode(Stop(reason="bench 000000", stamp_s=time.time()))
        deadline = time.monotonic() + READY_TIMEOUT_S
        while not (
            self.raw_out.matching_status.matching and self.stop_out.matching_status.matching
        ):
            if time.monotonic() > deadline:
                raise TimeoutError("the echo process's subscribers never matched")
            time.sleep(0.05)
        time.sleep(0.5)  # and the echo's publishers have our subscribers too

    def raw_rtt(self) -> float:
        t = time.perf_counter()
        self.raw_out.put(self.payload)
        self.raw_in.handler.recv()
        return (time.perf_counter() - t) * 1000.0

    def command_rtt(self, seq: int) -> float:
        t = time.perf_counter()
        self.stop_out.put(encode(Stop(reason=f"bench {seq:06d}", stamp_s=time.time())))
        while True:  # an answer to an earlier, timed-out command is skipped
            report = decode(self.report_in.handler.recv().payload.to_bytes(), ExecutionReport)
            if report.message == f"bench {seq:06d}":
                return (time.perf_counter() - t) * 1000.0

    def tcp_rtt(self) -> float:
        t = time.perf_counter()
        self.sock.sendall(LENGTH.pack(len(self.payload)) + self.payload)
        _recv_exact(self.sock, LENGTH.size + len(self.payload))
        return (time.perf_counter() - t) * 1000.0

    def close(self) -> None:
        self.sock.close()
        self.session.close()


def run_client(args: argparse.Namespace) -> dict[str, Any]:
    """Measure round trips (and with ``--frame``, the image phase); returns raw samples."""
    client = _Client(args.zenoh_connect.split(","), args.tcp)
    kinds: dict[str, Callable[[int], float]] = {
        "raw": lambda i: client.raw_rtt(),
        "command": client.command_rtt,
        "tcp": lambda i: client.tcp_rtt(),
    }
    names = list(kinds)
    out: dict[str, Any] = {name: [] for name in names}
    try:
        for i in range(args.warmup):
            for name in names:
                kinds[name](-1 - i)
        for i in range(args.count):
            # Which kind goes first takes turns: the first round trip of a cycle was measured
            # 12-35 µs slower than the same work after it (loopback, 2 cores), a bias that a
            # fixed order would put on one kind.
            for j in range(len(names)):
                name = names[(i + j) % len(names)]
                out[name].append(kinds[name](i))
        if args.frame:
            out.update(_image_phase(client, args))
    finally:
        client.close()
    return out


def _image_phase(client: _Client, args: argparse.Namespace) -> dict[str, Any]:
    latencies_ms: list[float] = []
    seqs: list[int] = []
    sub = client.session.declare_subscriber(
        key(SITE_ID, "camera"), zenoh.handlers.RingChannel(1), allowed_origin=zenoh.Locality.REMOTE
    )

    def frames() -> None:
        for sample in sub.handler:
            frame = decode(sample.payload.to_bytes(), CameraFrame)
            latencies_ms.append((time.time() - frame.stamp_s) * 1000.0)
            seqs.append(frame.seq)

    threading.Thread(target=_quietly, args=(frames,), daemon=True).start()
    client.control.put(("camera on " + " ".join(args.frame.split(":"))).encode())
    time.sleep(2.0)  # let the stream reach its steady state
    n0, t0 = len(seqs), time.monotonic()
    with_images = [client.command_rtt(1_000_000 + i) for i in range(args.image_count)]
    elapsed_s = time.monotonic() - t0
    n1 = len(seqs)
    client.control.put(b"camera off")
    time.sleep(1.0)
    without = [client.command_rtt(2_000_000 + i) for i in range(args.image_count)]
    sub.undeclare()
    return {
        "command_with_images": with_images,
        "command_without_images": without,
        "frame_fps": (n1 - n0) / elapsed_s,
        "frame_latency_ms": latencies_ms[n0:n1],
        "frames_sent_span": (seqs[n1 - 1] - seqs[n0] + 1) if n1 > n0 else 0,
    }


# ----------------------------------------------------------------------- the orchestrator


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _self_argv(*args: str) -> list[str]:
    return [sys.executable, "-m", "bench", "net", *args]


def _start_echo(argv: list[str]) -> subprocess.Popen:
    proc = subprocess.Popen(argv, cwd=REPO, stdout=subprocess.PIPE, text=True)
    line = proc.stdout.readline() if proc.stdout else ""
    if "ready" not in line:
        proc.kill()
        proc.wait()
        raise RuntimeError(f"netbench echo process did not start ({line.strip()!r})")
    return proc


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    if proc.stdout is not None:
        proc.stdout.close()


def _stop_group(proc: subprocess.Popen) -> None:
    """SIGTERM a process started in its own session (and its children), SIGKILL after 15 s."""
    os.killpg(proc.pid, signal.SIGTERM)
    try:
        proc.wait(timeout=15)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()


def _run_client(argv: list[str], timeout_s: float) -> dict[str, Any]:
    done = subprocess.run(argv, cwd=REPO, capture_output=True, text=True, timeout=timeout_s)
    if done.returncode != 0:
        raise RuntimeError(f"netbench client failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def _client_args(zenoh_ep: str, tcp: str, count: int, frame: str, image_count: int) -> list[str]:
    return [
        "--role=client",
        f"--zenoh-connect={zenoh_ep}",
        f"--tcp={tcp}",
        f"--count={count}",
        f"--frame={frame}",
        f"--image-count={image_count}",
    ]


def measure_pair(
    echo_prefix: list[str],
    client_prefix: list[str],
    host: str,
    count: int,
    frame: str,
    image_count: int,
    timeout_s: float,
    split: bool = False,
) -> dict[str, Any]:
    """Start the echo process (``echo_prefix`` e.g. ``ip netns exec``) and run the client;
    ``split``: one zenoh link per priority range (:func:`protocol.session.split_endpoints`)."""
    endpoints = ",".join(split_endpoints(host, (_free_port(), _free_port()), split))
    tport = _free_port()
    echo = _start_echo(
        [
            *echo_prefix,
            *_self_argv("--role=echo", f"--zenoh-listen={endpoints}", f"--tcp-port={tport}"),
        ]
    )
    try:
        client_args = _client_args(endpoints, f"{host}:{tport}", count, frame, image_count)
        return _run_client([*client_prefix, *_self_argv(*client_args)], timeout_s)
    finally:
        _stop(echo)


def refused_program(program_id: str) -> MotionProgram:
    """A well-formed program that a work site's check refuses (its move would take the gripper
    into the robot's base): its "refused" report times a command's round trip, nothing moves."""
    command = MotionCommand(
        kind="move", X_WP=np.eye(4), speed_mps=0.05, force_limit_n=10.0, contacts=()
    )
    return MotionProgram(program_id=program_id, X_GP=np.eye(4), commands=(command,))


def measure_work_site(
    seconds: float, program_samples: int, encoding: str | None = None
) -> dict[str, Any]:
    """A real ``work-site serve`` on loopback: camera frames (in ``encoding``, default the work
    site's), and a program's refusal round trip; ``last_image`` is the last frame's pixels."""
    endpoint = f"tcp/127.0.0.1:{free_port_pair()}"  # the work site listens on it and the next
    extra = ["--camera-encoding", encoding] if encoding else []
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "work_site",
            "serve",
            "--listen",
            endpoint,
            "--site-id",
            SITE_ID,
            *extra,
        ],
        cwd=REPO,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    try:
        # Connected as `operator-site serve --connect ENDPOINT` is: one link per priority range.
        with zenoh.open(make_config(connect=link_endpoints([endpoint])[0])) as session:
            ring, fifo = zenoh.handlers.RingChannel, zenoh.handlers.FifoChannel
            cam = session.declare_subscriber(key(SITE_ID, "camera"), ring(1))
            reports = session.declare_subscriber(key(SITE_ID, "report"), fifo(256))
            pub = session.declare_publisher(
                key(SITE_ID, "program"), priority=zenoh.Priority.INTERACTIVE_HIGH
            )
            deadline = time.monotonic() + READY_TIMEOUT_S
            while cam.try_recv() is None:  # the first frame: rendering is warm
                if time.monotonic() > deadline:
                    raise TimeoutError("the work site sent no camera frame")
                time.sleep(0.01)
            latencies: list[float] = []
            t0 = time.monotonic()
            while time.monotonic() - t0 < seconds:
                frame = decode(cam.handler.recv().payload.to_bytes(), CameraFrame)
                latencies.append((time.time() - frame.stamp_s) * 1000.0)
            fps = len(latencies) / (time.monotonic() - t0)
            last_image = frame.image
            replies: list[float] = []
            for i in range(program_samples):
                pid = f"bench-{os.getpid()}-{i}"
                payload = encode(refused_program(pid))
                t = time.perf_counter()
                pub.put(payload)
                while decode(reports.handler.recv().payload.to_bytes(), ExecutionReport) \
                        .program_id != pid:  # fmt: skip
                    pass
                replies.append((time.perf_counter() - t) * 1000.0)
            cam.undeclare()
            reports.undeclare()
    finally:
        _stop_group(proc)
    return {
        "frame_fps": fps,
        "frame_latency_ms": latencies,
        "site_program_reply_ms": replies,
        "last_image": last_image,
    }


def measure_programs_over_link(params: dict[str, Any], runs: int) -> dict:
    """A harsh link (e.g. 100 ± 20 ms each way, 2 % loss): per run, a fresh real work
    site in the work namespace (link seed ``params["seed"] + run``) and
    ``deploy/operator_probe.py``'s pick-and-place from the operators' namespace. Per run: the
    sends, the acknowledgement time (program sent → "accepted" back: the command latency), the
    reports the operator got (in order?) and the times the work site's journal accepted it."""
    probe = REPO / "deploy" / "operator_probe.py"
    endpoint = f"tcp/{netns.WORK_ADDR}:7447"
    rows: list[dict[str, Any]] = []
    for run in range(runs):
        run_params = {**params, "seed": int(params["seed"]) + run}
        journal = Path(tempfile.mkdtemp(prefix="netbench-")) / "journal.jsonl"
        with netns.emulated_link(prefix="trharsh", **run_params) as link:
            site = subprocess.Popen(
                link.pair.exec_argv(
                    link.pair.work,
                    [sys.executable, "-m", "work_site", "serve", "--listen", endpoint,
                     "--site-id", SITE_ID, "--no-camera", "--insecure",
                     "--journal", str(journal)],
                ),
                cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                start_new_session=True,
            )  # fmt: skip
            try:
                done = subprocess.run(
                    link.pair.exec_argv(
                        link.pair.ops,
                        [sys.executable, str(probe), "program", f"--connect={endpoint}",
                         f"--site-id={SITE_ID}", "--connect-timeout=60", "--timeout=120"],
                    ),
                    cwd=REPO, capture_output=True, text=True, timeout=300,
                )  # fmt: skip
            finally:
                _stop_group(site)
        try:
            result = json.loads(done.stdout.strip().splitlines()[-1])
        except (IndexError, ValueError):
            result = {"error": f"the probe printed no result: {done.stderr[-2000:]}"}
        pid = result.get("program_id")
        journaled = [
            decode(bytes.fromhex(json.loads(line)["report"]), ExecutionReport)
            for line in (journal.read_text().splitlines() if journal.exists() else ())
            if json.loads(line)["program_id"] == pid
        ]
        journal_statuses = [r.status for r in journaled if r.command_index == -1]
        reports = [tuple(r) for r in result.get("reports", [])]
        steps = [i for i, _ in reports[1:-1]]
        row = {
            "seed": run_params["seed"],
            "error": result.get("error"),
            "sends": result.get("sends"),
            "ack_ms": result.get("ack_ms"),
            "reports": len(reports),
            "reports_in_order": bool(reports)
            and reports[0] == (-1, "accepted")
            and reports[-1] == (-1, "done")
            and steps == sorted(steps),
            "accepted_at_work_site": journal_statuses.count("accepted"),
            "done_at_work_site": journal_statuses.count("done"),
        }
        rows.append(row)
        print(f"netbench:   run {run}: {row}", flush=True)
    acks = [r["ack_ms"] for r in rows if r["ack_ms"] is not None]
    return {
        "harsh_link": params,
        "harsh_runs": rows,
        "harsh_programs_delivered_exactly_once": sum(
            r["accepted_at_work_site"] == 1 and r["done_at_work_site"] == 1 for r in rows
        ),
        "harsh_programs_reports_in_order": sum(bool(r["reports_in_order"]) for r in rows),
        "harsh_programs": len(rows),
        "harsh_command_latency_ms_median": statistics.median(acks) if acks else None,
        "harsh_command_latency_ms_max": max(acks) if acks else None,
    }


def codec_cpu_us_per_round_trip(n: int = 5000) -> float:
    """CPU time (µs) of the codec work in one command round trip, in-process: encode a Stop,
    decode it, build and encode the ExecutionReport, decode that."""

    def cycle() -> None:
        stop = decode(encode(Stop(reason="bench 000001", stamp_s=time.time())), Stop)
        report = ExecutionReport(
            program_id="bench",
            command_index=-1,
            status="stopped",
            wrench_S=ZEROS6,
            message=stop.reason,
            stamp_s=time.time(),
        )
        decode(encode(report), ExecutionReport)

    for _ in range(n // 10):
        cycle()
    t = time.perf_counter()
    for _ in range(n):
        cycle()
    return (time.perf_counter() - t) / n * 1e6


def codec_costs(image: np.ndarray, spec: str, n: int = 30) -> dict[str, float]:
    """One camera frame in encoding ``spec`` (``raw``, ``png``, ``jpeg:Q``), in-process: bytes of
    the whole encoded message, median ms to encode it (``protocol.encode``) and to decode and
    validate it (``protocol.decode``), and the decoded pixels' error (grey levels)."""
    from models.scene import load_scene

    cam = load_scene().camera
    encoding, quality = parse_image_encoding(spec)
    msg = CameraFrame(
        seq=0,
        stamp_s=time.time(),
        X_WC=cam.X_WC,
        K=cam.K,
        dist=cam.dist,
        image=image,
        encoding=encoding,
        quality=quality,
    )
    encode_s, decode_s = [], []
    for _ in range(n):
        t = time.perf_counter()
        payload = encode(msg)
        encode_s.append(time.perf_counter() - t)
        t = time.perf_counter()
        out = decode(payload, CameraFrame)
        decode_s.append(time.perf_counter() - t)
    err = np.abs(out.image.astype(np.int16) - image)
    return {
        "bytes_per_frame": len(payload),
        "encode_ms": statistics.median(encode_s) * 1000.0,
        "decode_ms": statistics.median(decode_s) * 1000.0,
        "mean_abs_error_grey": float(err.mean()),
        "max_abs_error_grey": int(err.max()),
    }


def measure_frames(args: argparse.Namespace) -> list[dict[str, Any]]:
    """Camera frame size on the wire as a knob: each of ``--net-frame-encodings`` measured
    (1) in-process on a real work-site frame (bytes, encode and decode ms, error), (2) from a
    real ``work-site serve --camera-encoding`` on loopback (fps, latency), and (3) over the
    emulated link (``--net-link-*``; and again at each ``--net-frame-rates-mbit``): the echo
    process publishes that real frame in the encoding at the camera's rate while commands run
    (fps, latency, and how much the stream delays commands). One row per encoding and link."""
    import tempfile

    from models.scene import load_scene

    specs = [s.strip() for s in args.net_frame_encodings.split(",") if s.strip()]
    for spec in specs:
        parse_image_encoding(spec)  # a typo fails now, not after minutes of measuring
    cam = load_scene().camera
    rows: list[dict[str, Any]] = []
    site: dict[str, dict[str, Any]] = {}
    for spec in specs:
        print(f"netbench: frames: a real work site sending {spec} frames...", flush=True)
        site[spec] = measure_work_site(args.net_frame_seconds, 0, encoding=spec)
    raw = [s for s in specs if s == "raw"]
    image = (
        site[raw[0]]["last_image"]
        if raw
        else measure_work_site(3.0, 0, encoding="raw")["last_image"]
    )
    for spec in specs:
        fps, lat = site[spec]["frame_fps"], site[spec]["frame_latency_ms"]
        med, p99 = _summary(lat)
        rows.append(
            {
                "encoding": spec,
                "link": "loopback, real work site",
                **codec_costs(image, spec),
                "frame_fps": fps,
                "frame_latency_ms_median": med,
                "frame_latency_ms_p99": p99,
                "command_delay_by_images_ms": None,  # no commands to a real work site here
            }
        )
    if args.net_no_link:
        return rows
    reason = netns.unavailable_reason()
    if reason is not None:
        print(f"netbench: frames over the emulated link skipped: {reason}", flush=True)
        return rows
    costs = {r["encoding"]: r for r in rows}
    base = {
        "delay_ms": args.net_link_delay_ms,
        "loss": args.net_link_loss,
        "seed": args.net_link_seed,
    }
    rates = [float(r) for r in args.net_frame_rates_mbit.split(",") if r.strip()]
    with (
        tempfile.TemporaryDirectory() as tmp,
        netns.emulated_link(prefix="trframe", **base) as link,
    ):
        path = Path(tmp) / "frame.npy"
        np.save(path, image)
        for i, rate in enumerate(rates):
            if i > 0 or rate > 0:
                link.reconfigure(**base, rate_mbit=rate)
            name = f"{base['delay_ms']:g} ms + {base['loss'] * 100:g} % loss" + (
                f", {rate:g} Mbit/s" if rate > 0 else ""
            )
            for spec in specs:
                print(f"netbench: frames: {spec} over the emulated link ({name})...", flush=True)
                encoding, quality = parse_image_encoding(spec)
                frame = f"{cam.width}:{cam.height}:{cam.frame_rate_hz}:{encoding}:{quality}:{path}"
                res = measure_pair(
                    ["ip", "netns", "exec", link.pair.work],
                    ["ip", "netns", "exec", link.pair.ops],
                    netns.WORK_ADDR,
                    0,
                    frame,
                    args.net_frame_link_commands,
                    3600,
                    split=True,
                )
                med, p99 = _summary(res["frame_latency_ms"])
                delay = statistics.median(res["command_with_images"]) - statistics.median(
                    res["command_without_images"]
                )
                rows.append(
                    {
                        **{k: costs[spec][k] for k in CODEC_COLUMNS},
                        "encoding": spec,
                        "link": name,
                        "frame_fps": res["frame_fps"],
                        "frame_latency_ms_median": med,
                        "frame_latency_ms_p99": p99,
                        "command_delay_by_images_ms": delay,
                    }
                )
    return rows


CODEC_COLUMNS = (
    "bytes_per_frame",
    "encode_ms",
    "decode_ms",
    "mean_abs_error_grey",
    "max_abs_error_grey",
)
FRAME_COLUMNS = (
    "encoding",
    "link",
    "bytes_per_frame",
    "encode_ms",
    "decode_ms",
    "mean_abs_error_grey",
    "max_abs_error_grey",
    "frame_fps",
    "frame_latency_ms_median",
    "frame_latency_ms_p99",
    "command_delay_by_images_ms",
)


def write_frame_outputs(out: Path, rows: list[dict[str, Any]]) -> None:
    """``net_frames.csv`` and ``net_frames.json`` (one row per encoding and link),
    ``net_frames.png`` (bytes per frame, codec time, latency by link)."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "net_frames.json").write_text(json.dumps(rows, indent=2) + "\n")
    with (out / "net_frames.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=FRAME_COLUMNS)
        writer.writeheader()
        for row in rows:
            writer.writerow(
                {k: (f"{v:.4f}" if isinstance(v, float) else v) for k, v in row.items()}
            )
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("netbench: matplotlib missing (pip install -e '.[bench]'): no plot", flush=True)
        return
    specs = list(dict.fromkeys(r["encoding"] for r in rows))
    links = list(dict.fromkeys(r["link"] for r in rows))
    first = {s: next(r for r in rows if r["encoding"] == s) for s in specs}
    fig, axes = plt.subplots(1, 3, figsize=(16, 4))
    x = np.arange(len(specs))
    axes[0].bar(x, [first[s]["bytes_per_frame"] / 1000.0 for s in specs])
    axes[0].set_ylabel("kB per frame (whole message)")
    axes[0].set_title("frame size on the wire")
    axes[1].bar(x - 0.2, [first[s]["encode_ms"] for s in specs], 0.4, label="encode")
    axes[1].bar(x + 0.2, [first[s]["decode_ms"] for s in specs], 0.4, label="decode + check")
    axes[1].set_ylabel("ms per frame")
    axes[1].set_title("codec time (one core)")
    axes[1].legend(fontsize=8)
    width = 0.8 / max(1, len(links))
    for j, link_name in enumerate(links):
        lat = [
            next((r["frame_latency_ms_median"] for r in rows
                  if r["encoding"] == s and r["link"] == link_name), np.nan)
            for s in specs
        ]  # fmt: skip
        axes[2].bar(x - 0.4 + width * (j + 0.5), lat, width, label=link_name)
    axes[2].set_ylabel("frame latency, median (ms)")
    axes[2].set_title("capture → decoded at the operator")
    axes[2].legend(fontsize=7)
    for ax in axes:
        ax.set_xticks(x, specs)
        ax.grid(True, axis="y", alpha=0.3)
    fig.tight_layout()
    fig.savefig(out / "net_frames.png", dpi=100)
    plt.close(fig)


def _frame_spec(args: argparse.Namespace) -> str:
    from models.scene import load_scene

    cam = load_scene().camera
    w, h = (args.net_frame_size or f"{cam.width}x{cam.height}").split("x")
    return f"{int(w)}:{int(h)}:{cam.frame_rate_hz}"


def run(args: argparse.Namespace) -> tuple[dict[str, Any], dict[str, list[float]]]:
    """All measurements; returns (summary, samples by series name)."""
    frame = _frame_spec(args)
    samples: dict[str, list[float]] = {}
    summary: dict[str, Any] = {"frame_spec_w_h_hz": frame, "count": args.net_count}
    runs = args.net_loopback_runs
    print(
        f"netbench: loopback round trips ({runs} runs of {args.net_count} of each kind)...",
        flush=True,
    )
    lo = measure_pair(
        [], [], "127.0.0.1", args.net_count, frame, args.net_image_count, 900, split=True
    )
    # Our overhead is a small difference of two medians that moved 0.07-0.18 ms between single
    # runs: each run has fresh processes, and the figure is the median over the runs.
    overheads_ms = [statistics.median(lo["command"]) - statistics.median(lo["raw"])]
    for _ in range(runs - 1):
        more = measure_pair([], [], "127.0.0.1", args.net_count, "", 0, 900, split=True)
        overheads_ms.append(statistics.median(more["command"]) - statistics.median(more["raw"]))
        for name in ("raw", "command", "tcp"):
            lo[name] += more[name]
    for name in ("raw", "command", "tcp", "command_with_images", "command_without_images"):
        samples[f"loopback_{name}"] = lo[name]
    summary["loopback_runs"] = runs
    summary["raw_zenoh_rtt_ms_median"], summary["raw_zenoh_rtt_ms_p99"] = _summary(lo["raw"])
    summary["zenoh_rtt_ms_median"], summary["zenoh_rtt_ms_p99"] = _summary(lo["command"])
    summary["tcp_rtt_ms_median"], summary["tcp_rtt_ms_p99"] = _summary(lo["tcp"])
    summary["zenoh_over_tcp_rtt_ratio_median"] = (
        summary["zenoh_rtt_ms_median"] / summary["tcp_rtt_ms_median"]
    )
    summary["codec_overhead_over_raw_zenoh_ms_median"] = statistics.median(overheads_ms)
    summary["codec_overhead_over_raw_zenoh_ms_runs"] = overheads_ms
    summary["codec_cpu_us_per_round_trip"] = codec_cpu_us_per_round_trip()
    summary["command_delay_by_images_ms"] = statistics.median(
        lo["command_with_images"]
    ) - statistics.median(lo["command_without_images"])
    print("netbench: a real work site's camera and program replies...", flush=True)
    ws = measure_work_site(args.net_frame_seconds, 50)
    samples["loopback_frame_latency"] = ws["frame_latency_ms"]
    samples["loopback_site_program_reply"] = ws["site_program_reply_ms"]
    summary["frame_fps"] = ws["frame_fps"]
    summary["frame_latency_ms_median"], summary["frame_latency_ms_p99"] = _summary(
        ws["frame_latency_ms"]
    )
    summary["site_program_reply_ms_median"], summary["site_program_reply_ms_p99"] = _summary(
        ws["site_program_reply_ms"]
    )
    if args.net_no_link:
        summary["link"] = "skipped (--net-no-link)"
        return summary, samples
    reason = netns.unavailable_reason()
    if reason is not None:
        print(f"netbench: emulated link skipped: {reason}", flush=True)
        summary["link"] = f"skipped: {reason}"
        return summary, samples
    link_params = {
        "delay_ms": args.net_link_delay_ms,
        "loss": args.net_link_loss,
        "seed": args.net_link_seed,
    }
    summary["link"] = link_params
    print(f"netbench: emulated link {link_params} ({args.net_link_count} of each)...", flush=True)
    with netns.emulated_link(prefix="trbench", **link_params) as link:
        pair = link.pair
        ln = measure_pair(
            ["ip", "netns", "exec", pair.work],
            ["ip", "netns", "exec", pair.ops],
            netns.WORK_ADDR,
            args.net_link_count,
            frame,
            args.net_link_image_count,
            3600,
            split=True,
        )
        single = None
        if not args.net_no_single:
            print("netbench: the same over one zenoh link for all priorities...", flush=True)
            single = measure_pair(
                ["ip", "netns", "exec", pair.work],
                ["ip", "netns", "exec", pair.ops],
                netns.WORK_ADDR,
                args.net_link_count // 5,
                frame,
                args.net_link_image_count,
                3600,
                split=False,
            )
    summary["link_relay_counters"] = link.counters
    if args.net_harsh_runs > 0:
        harsh = {
            "delay_ms": args.net_harsh_delay_ms,
            "jitter_ms": args.net_harsh_jitter_ms,
            "loss": args.net_harsh_loss,
            "seed": args.net_link_seed,
        }
        print(f"netbench: programs over a harsher link {harsh} ({args.net_harsh_runs} runs)...")
        summary.update(measure_programs_over_link(harsh, args.net_harsh_runs))
    if single is not None:
        for name in ("command", "command_with_images", "command_without_images"):
            samples[f"link_single_{name}"] = single[name]
        samples["link_single_frame_latency"] = single["frame_latency_ms"]
        s_with, s_with_p99 = _summary(single["command_with_images"])
        s_without, s_without_p99 = _summary(single["command_without_images"])
        summary["link_single_zenoh_rtt_ms_median"] = _summary(single["command"])[0]
        summary["link_single_command_rtt_with_images_ms_median"] = s_with
        summary["link_single_command_rtt_with_images_ms_p99"] = s_with_p99
        summary["link_single_command_delay_by_images_ms"] = s_with - s_without
        summary["link_single_command_delay_by_images_ms_p99"] = s_with_p99 - s_without_p99
        summary["link_single_frame_fps"] = single["frame_fps"]
        summary["link_single_frame_latency_ms_median"] = _summary(single["frame_latency_ms"])[0]
    for name in ("raw", "command", "tcp", "command_with_images", "command_without_images"):
        samples[f"link_{name}"] = ln[name]
    samples["link_frame_latency"] = ln["frame_latency_ms"]
    summary["link_raw_zenoh_rtt_ms_median"], summary["link_raw_zenoh_rtt_ms_p99"] = _summary(
        ln["raw"]
    )
    summary["link_zenoh_rtt_ms_median"], summary["link_zenoh_rtt_ms_p99"] = _summary(ln["command"])
    summary["link_tcp_rtt_ms_median"], summary["link_tcp_rtt_ms_p99"] = _summary(ln["tcp"])
    summary["link_zenoh_over_tcp_ratio_median"] = (
        summary["link_zenoh_rtt_ms_median"] / summary["link_tcp_rtt_ms_median"]
    )
    summary["link_zenoh_over_tcp_ratio_p99"] = (
        summary["link_zenoh_rtt_ms_p99"] / summary["link_tcp_rtt_ms_p99"]
    )
    with_med, with_p99 = _summary(ln["command_with_images"])
    without_med, without_p99 = _summary(ln["command_without_images"])
    summary["link_command_rtt_with_images_ms_median"] = with_med
    summary["link_command_rtt_with_images_ms_p99"] = with_p99
    summary["link_command_rtt_without_images_ms_median"] = without_med
    summary["link_command_delay_by_images_ms"] = with_med - without_med
    summary["link_command_delay_by_images_ms_p99"] = with_p99 - without_p99
    summary["link_frame_fps"] = ln["frame_fps"]
    summary["link_frame_latency_ms_median"], summary["link_frame_latency_ms_p99"] = _summary(
        ln["frame_latency_ms"]
    )
    return summary, samples


def write_outputs(out: Path, summary: dict[str, Any], samples: dict[str, list[float]]) -> None:
    """``net.json`` (summary), ``net_samples.csv`` (every sample), ``net_rtt.png`` (CDFs)."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "net.json").write_text(json.dumps(summary, indent=2) + "\n")
    with (out / "net_samples.csv").open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["series", "index", "ms"])
        for name, values in samples.items():
            writer.writerows((name, i, f"{v:.4f}") for i, v in enumerate(values))
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("netbench: matplotlib missing (pip install -e '.[bench]'): no plot", flush=True)
        return
    panels = [
        ("loopback", ["loopback_raw", "loopback_command", "loopback_tcp",
                      "loopback_command_with_images"]),
        ("emulated link", ["link_raw", "link_command", "link_tcp", "link_command_with_images",
                           "link_single_command_with_images"]),
    ]  # fmt: skip
    panels = [(t, [s for s in names if samples.get(s)]) for t, names in panels]
    panels = [(t, names) for t, names in panels if names]
    fig, axes = plt.subplots(1, len(panels), figsize=(6 * len(panels), 4), squeeze=False)
    for ax, (title, names) in zip(axes[0], panels, strict=True):
        for name in names:
            v = np.sort(samples[name])
            ax.plot(v, np.arange(1, len(v) + 1) / len(v), label=name.split("_", 1)[1])
        ax.set_xscale("log")
        ax.set_xlabel("round trip (ms)")
        ax.set_ylabel("fraction ≤")
        ax.set_title(f"round trips, {title}")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "net_rtt.png", dpi=100)
    plt.close(fig)


def _positive_int(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if n < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {n}")
    return n


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``python -m bench net``."""
    parser.add_argument(
        "--out",
        type=Path,
        default=Path("docs/bench"),
        help="directory for net.json, net_samples.csv, net_rtt.png and net_frames.* "
        "(default: %(default)s)",
    )
    g = parser.add_argument_group("what is measured")
    g.add_argument(
        "--net-count",
        type=int,
        default=2000,
        help="round trips of each kind in each loopback run (default: %(default)s)",
    )
    g.add_argument(
        "--net-loopback-runs",
        type=_positive_int,
        default=5,
        help="loopback runs, each with fresh processes; our overhead on zenoh is the median "
        "over them (default: %(default)s)",
    )
    g.add_argument(
        "--net-image-count",
        type=int,
        default=500,
        help="loopback command round trips timed with and without camera frames streaming "
        "(default: %(default)s)",
    )
    g.add_argument(
        "--net-frame-size",
        default=None,
        metavar="WxH",
        help="size of the echo's raw frames (default: the scene camera's)",
    )
    g.add_argument(
        "--net-frame-seconds",
        type=float,
        default=5.0,
        help="seconds of camera frames received from a real work site (default: %(default)s)",
    )
    g.add_argument(
        "--net-no-link", action="store_true", help="skip every measurement over the emulated link"
    )
    g.add_argument(
        "--net-link-delay-ms",
        type=float,
        default=50.0,
        help="the emulated link's one-way delay, ms (default: %(default)s)",
    )
    g.add_argument(
        "--net-link-loss",
        type=float,
        default=0.01,
        help="the emulated link's loss fraction each way (default: %(default)s)",
    )
    g.add_argument(
        "--net-link-seed",
        type=int,
        default=1,
        help="seed of the emulated link's delay and loss schedule (default: %(default)s)",
    )
    g.add_argument(
        "--net-no-single",
        action="store_true",
        help="skip the comparison run over one zenoh link for all priorities (the sites use "
        "two: commands apart from images)",
    )
    g.add_argument(
        "--net-link-count",
        type=int,
        default=500,
        help="round trips of each kind over the emulated link (default: %(default)s)",
    )
    g.add_argument(
        "--net-frame-encodings",
        default="raw,png,jpeg:90,jpeg:80",
        metavar="LIST",
        help="camera encodings to compare, as work-site serve --camera-encoding takes them "
        "(default: %(default)s)",
    )
    g.add_argument(
        "--net-frame-rates-mbit",
        default="0,10",
        metavar="LIST",
        help="link rate limits (Mbit/s, 0: none) to compare the encodings over, on top of "
        "--net-link-delay-ms and --net-link-loss (default: %(default)s)",
    )
    g.add_argument(
        "--net-frame-link-commands",
        type=int,
        default=100,
        help="command round trips over the emulated link with and without each encoding's "
        "frames streaming (default: %(default)s)",
    )
    g.add_argument(
        "--net-only-frames",
        action="store_true",
        help="measure only the camera encodings (net_frames.*), not the round trips (net.json)",
    )
    g.add_argument(
        "--net-no-frames", action="store_true", help="skip the camera encodings' comparison"
    )
    g.add_argument(
        "--net-harsh-runs",
        type=int,
        default=3,
        help="pick-and-place programs run by a real work site over the harsher link, 0 for "
        "none (default: %(default)s)",
    )
    g.add_argument(
        "--net-harsh-delay-ms",
        type=float,
        default=100.0,
        help="the harsher link's one-way delay, ms (default: %(default)s)",
    )
    g.add_argument(
        "--net-harsh-jitter-ms",
        type=float,
        default=20.0,
        help="the harsher link's delay jitter, ± ms (default: %(default)s)",
    )
    g.add_argument(
        "--net-harsh-loss",
        type=float,
        default=0.02,
        help="the harsher link's loss fraction each way (default: %(default)s)",
    )
    g.add_argument(
        "--net-link-image-count",
        type=int,
        default=200,
        help="command round trips over the emulated link timed with and without camera "
        "frames streaming (default: %(default)s)",
    )
    # The roles of the helper processes this benchmark starts (not for users).
    parser.add_argument("--role", choices=["echo", "client"], help=argparse.SUPPRESS)
    parser.add_argument("--zenoh-listen", help=argparse.SUPPRESS)
    parser.add_argument("--zenoh-connect", help=argparse.SUPPRESS)
    parser.add_argument("--tcp-port", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--tcp", help=argparse.SUPPRESS)
    parser.add_argument("--count", type=int, default=1000, help=argparse.SUPPRESS)
    parser.add_argument("--warmup", type=int, default=20, help=argparse.SUPPRESS)
    parser.add_argument("--frame", default="", help=argparse.SUPPRESS)
    parser.add_argument("--image-count", type=int, default=200, help=argparse.SUPPRESS)


def main(args: argparse.Namespace) -> int:
    """Run the benchmark (or a helper role); print the figures and the JSON summary last."""
    if args.role == "echo":
        return serve_echo(args.zenoh_listen.split(","), args.tcp_port)
    if args.role == "client":
        print(json.dumps(run_client(args)), flush=True)
        return 0
    summary: dict[str, Any] = {}
    if not args.net_only_frames:
        summary, samples = run(args)
        write_outputs(args.out, summary, samples)
        for name, value in summary.items():
            if isinstance(value, float):
                print(f"  {name:48s} {value:10.3f}")
        print(f"netbench: wrote {args.out}/net.json, net_samples.csv, net_rtt.png", flush=True)
    if not args.net_no_frames:
        rows = measure_frames(args)
        write_frame_outputs(args.out, rows)
        print(f"  {'encoding':10s} {'link':34s} {'kB':>7s} {'enc ms':>7s} {'dec ms':>7s} "
              f"{'fps':>5s} {'lat ms':>7s} {'p99 ms':>7s} {'cmd +ms':>7s}")  # fmt: skip
        for r in rows:
            print(
                f"  {r['encoding']:10s} {r['link']:34s} {r['bytes_per_frame'] / 1000:7.1f} "
                f"{r['encode_ms']:7.2f} {r['decode_ms']:7.2f} {r['frame_fps']:5.2f} "
                f"{r['frame_latency_ms_median']:7.1f} {r['frame_latency_ms_p99']:7.1f} "
                + (f"{d:7.1f}" if (d := r["command_delay_by_images_ms"]) is not None else "      -")
            )
        print(f"netbench: wrote {args.out}/net_frames.csv, net_frames.json, net_frames.png")
        summary["frames"] = rows
    print(json.dumps(summary), flush=True)
    return 0
