"""Cost of each wire path per message type: construct, encode, decode (with validation), in ns.

A plain script, imported by nothing: ``python bench/wire_paths.py [--tree DIR]`` measures the
``protocol`` package of checkout DIR (default: this one). Always measured: the public
constructors, ``encode`` and ``decode``. In a checkout that still has ``protocol/_fast.py``
(before the codec kept one validation path), also the old paths one by one: the Python
reference codec, the msgspec fast path, unpacking + the generated constructors, and the
reference constructors. Paths of one (message, operation) alternate repeat by repeat, so load
from other processes falls on all of them alike. Prints medians per path, then a JSON summary.
To compare two checkouts, alternate runs of each (A B A B A B) and compare medians.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import statistics
import sys
import time
from collections.abc import Callable
from typing import Any


def _messages(p: Any, np: Any) -> dict[str, Any]:
    """Realistic messages of each type, from a seeded generator."""
    rng = np.random.default_rng(0)

    def pose() -> Any:
        w, x, y, z = (q := rng.normal(size=4)) / np.linalg.norm(q)
        X = np.eye(4)
        X[:3, :3] = [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
        X[:3, 3] = rng.normal(size=3)
        return X

    def program(n: int) -> Any:
        normals = rng.normal(size=(2, 3))
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        kinds = p.MOTION_KINDS
        commands = tuple(
            p.MotionCommand(
                kinds[i % len(kinds)],
                pose(),
                0.05,
                10.0,
                (p.ContactState("table", normals),) if i % 2 else (),
            )
            for i in range(n)
        )
        return p.MotionProgram("prog-1", pose(), commands)

    K = np.array([[580.0, 0.0, 319.5], [0.0, 580.0, 239.5], [0.0, 0.0, 1.0]])
    image = rng.integers(0, 256, (480, 640), dtype=np.uint8)
    return {
        "RobotState": p.RobotState(
            12345, 17.25, rng.normal(size=6), pose(), 0.04, rng.normal(size=6)
        ),
        "CameraFrame": p.CameraFrame(7, 17.2, pose(), K, np.zeros(5), image),
        "MotionProgram10": program(10),
        "MotionProgram1000": program(1000),
        "Recognitions": p.Recognitions(
            7, 17.3, 0.12, tuple(p.Recognition(f"block_{i}", pose(), 0.9) for i in range(6))
        ),
        "ExecutionReport": p.ExecutionReport(
            "prog-1", 3, "done", rng.normal(size=6), "command 3 done", 18.0, 5
        ),
        "Stop": p.Stop("operator pressed stop", 18.5),
        "Heartbeat": p.Heartbeat("site1", "operator_site", 99, 18.6),
    }


def _paths(p: Any, np: Any, old: Any, msg: Any) -> dict[str, dict[str, Callable[[], Any]]]:
    """The callables to time for ``msg``: {operation: {path: fn}}."""
    cls, payload = type(msg), p.encode(msg)
    values = {f.name: getattr(msg, f.name) for f in dataclasses.fields(msg)}
    out: dict[str, dict[str, Callable[[], Any]]] = {
        "construct": {"public": lambda: cls(**values)},
        "encode": {"public": lambda: p.encode(msg)},
        "decode": {"public": lambda: p.decode(payload, cls)},
    }
    if old is None:
        return out
    import msgpack

    fast, spec, codec = old
    ref_init = spec.REFERENCE_INITS[cls]

    def construct_reference() -> Any:
        obj = object.__new__(cls)
        ref_init(obj, **values)
        return obj

    def build(rcls: type, body: dict[str, Any]) -> Any:
        fields = {}
        for name, field in rcls._SPEC.items():  # type: ignore[attr-defined]
            v = body[name]
            if isinstance(field, spec.ImageField):
                v = p.decode_image(v[1], body["encoding"], tuple(v[0]))
            elif isinstance(field, spec.ArrayField):
                v = np.frombuffer(v[1], field.dtype).reshape(v[0])
            elif isinstance(field, spec.TupleField):
                v = tuple(build(field.cls, item) for item in v)
            fields[name] = v
        return rcls(**fields)

    out["construct"]["reference"] = construct_reference
    out["encode"]["reference"] = lambda: codec._reference_encode(msg)
    if fast.fast_encode(msg) is not None:
        out["encode"]["fast"] = lambda: fast.fast_encode(msg)
    out["decode"]["reference"] = lambda: codec._reference_decode(payload, (cls,))
    decoder = fast.decoder((cls,))
    if decoder is not None:
        out["decode"]["fast"] = lambda: fast.fast_decode(decoder, payload)
    out["decode"]["init"] = lambda: build(cls, msgpack.unpackb(payload, raw=False)["b"])
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--tree", default=".", help="checkout whose protocol/ to measure")
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--ms", type=float, default=4.0, help="duration of one repeat")
    args = ap.parse_args(argv)
    tree = os.path.abspath(args.tree)
    sys.path.insert(0, tree)

    import numpy as np

    import protocol as p

    assert os.path.abspath(p.__file__).startswith(tree), p.__file__
    old = None
    if os.path.exists(os.path.join(tree, "protocol", "_fast.py")):
        from protocol import _fast, _spec, codec

        old = (_fast, _spec, codec)

    def calls_for(fn: Callable[[], Any]) -> int:
        n = 1
        while True:
            t0 = time.perf_counter_ns()
            for _ in range(n):
                fn()
            dt = time.perf_counter_ns() - t0
            if dt >= args.ms * 1e6 / 4 or n >= 1 << 20:
                return max(1, int(n * args.ms * 1e6 / max(dt, 1)))
            n *= 4

    messages = _messages(p, np)
    results: dict[str, dict[str, dict[str, float]]] = {}
    for case, msg in messages.items():
        results[case] = {}
        for op, fns in _paths(p, np, old, msg).items():
            counts = {name: calls_for(fn) for name, fn in fns.items()}  # also warms up
            samples: dict[str, list[float]] = {name: [] for name in fns}
            for r in range(args.repeats):
                for name in list(fns) if r % 2 == 0 else list(reversed(fns)):
                    fn, n = fns[name], counts[name]
                    t0 = time.perf_counter_ns()
                    for _ in range(n):
                        fn()
                    samples[name].append((time.perf_counter_ns() - t0) / n)
            results[case][op] = {name: statistics.median(s) for name, s in samples.items()}
            line = "  ".join(f"{k} {v / 1e3:10.2f} µs" for k, v in results[case][op].items())
            print(f"{case:18s} {op:9s} {line}", flush=True)
    sizes = {case: len(p.encode(msg)) for case, msg in messages.items()}
    print(json.dumps({"tree": tree, "payload_bytes": sizes, "ns": results}))


if __name__ == "__main__":
    main()
