"""Camera frames on the wire in each encoding (raw, png, jpeg): round trips and refusals."""

from __future__ import annotations

import importlib.util
import struct
import zlib

import cv2
import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from protocol import (
    IMAGE_ENCODINGS,
    CameraFrame,
    ProtocolError,
    decode,
    encode,
    parse_image_encoding,
)
from tests.conftest import examples

K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])


def scene_like_image(h: int = 120, w: int = 160, seed: int = 0) -> np.ndarray:
    """A grey image like the camera's: smooth shading, a few sharp-edged blocks, σ = 1 noise."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w]
    image = 80.0 + 60.0 * x / w + 20.0 * y / h
    for _ in range(4):
        r, c = rng.integers(0, h - h // 4), rng.integers(0, w - w // 4)
        image[r : r + h // 4, c : c + w // 4] = rng.uniform(20, 230)
    image += rng.normal(0.0, 1.0, image.shape)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def frame(image: np.ndarray, encoding: str = "raw", quality: int = 90) -> CameraFrame:
    return CameraFrame(7, 1.5, np.eye(4), K, np.zeros(5), image, encoding, quality)


def body_of(msg: CameraFrame) -> dict:
    return msgpack.unpackb(encode(msg), raw=False)


def repack(env: dict) -> bytes:
    return msgpack.packb(env, use_bin_type=True)


def reject(payload: bytes, match: str) -> None:
    with pytest.raises(ProtocolError, match=match):
        decode(payload, expected=CameraFrame)


# ---------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("encoding", IMAGE_ENCODINGS)
def test_each_encoding_round_trips(encoding: str) -> None:
    image = scene_like_image()
    msg = frame(image, encoding, quality=85)
    payload = encode(msg)
    out = decode(payload, expected=CameraFrame)
    assert (out.encoding, out.quality, out.seq, out.stamp_s) == (encoding, 85, 7, 1.5)
    assert out.image.shape == image.shape and out.image.dtype == np.uint8
    assert not out.image.flags.writeable
    if encoding == "jpeg":  # lossy, by about the noise's size
        err = np.abs(out.image.astype(int) - image)
        assert 0 < err.mean() < 2.0, err.mean()
        assert len(payload) < image.size / 4  # and much smaller than raw
    else:
        np.testing.assert_array_equal(out.image, image)
    if encoding == "png":
        assert len(payload) < image.size  # lossless but smaller than raw
    # Encoding the decoded frame again decodes to the same pixels (lossless) or close (jpeg).
    again = decode(encode(out), expected=CameraFrame)
    assert np.abs(again.image.astype(int) - out.image).max() <= (0 if encoding != "jpeg" else 8)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    st.integers(1, 48),
    st.integers(1, 48),
    st.integers(0, 2**32 - 1),
    st.sampled_from(IMAGE_ENCODINGS),
    st.integers(1, 100),
)
def test_any_shape_round_trips(h: int, w: int, seed: int, encoding: str, quality: int) -> None:
    image = np.random.default_rng(seed).integers(0, 256, (h, w), dtype=np.uint8)
    out = decode(encode(frame(image, encoding, quality)), expected=CameraFrame)
    assert out.image.shape == (h, w) and out.quality == quality
    if encoding != "jpeg":
        np.testing.assert_array_equal(out.image, image)


def test_higher_jpeg_quality_is_larger_and_closer() -> None:
    image = scene_like_image(240, 320)
    sizes, errors = [], []
    for q in (30, 60, 90, 100):
        payload = encode(frame(image, "jpeg", q))
        out = decode(payload, expected=CameraFrame).image
        sizes.append(len(payload))
        errors.append(float(np.abs(out.astype(int) - image).mean()))
    assert sizes == sorted(sizes) and errors == sorted(errors, reverse=True), (sizes, errors)


def test_parse_image_encoding() -> None:
    assert parse_image_encoding("raw") == ("raw", 80)
    assert parse_image_encoding("png") == ("png", 80)
    assert parse_image_encoding("jpeg") == ("jpeg", 80)
    assert parse_image_encoding("jpeg:75") == ("jpeg", 75)
    for bad in ("gif", "jpeg:0", "jpeg:101", "jpeg:x", "png:5", "", "JPEG"):
        with pytest.raises(ValueError, match=r"raw, png, jpeg|1\.\.100"):
            parse_image_encoding(bad)


# ------------------------------------------------------------------------------- refusals


def test_constructor_refuses_unknown_encodings_and_qualities() -> None:
    image = scene_like_image(8, 8)
    with pytest.raises(ProtocolError, match=r"CameraFrame\.encoding: must be one of"):
        frame(image, "gif")
    for q in (0, 101):
        with pytest.raises(ProtocolError, match=r"CameraFrame\.quality: must be in \[1, 101\)"):
            frame(image, "jpeg", q)


def test_decoder_refuses_unknown_encodings() -> None:
    env = body_of(frame(scene_like_image(8, 8)))
    for bad in ("gif", "JPEG", "", 3, None, b"png"):
        env["b"]["encoding"] = bad
        reject(repack(env), r"CameraFrame\.encoding: ")
    del env["b"]["encoding"]
    reject(repack(env), r"CameraFrame: missing field\(s\) \['encoding'\]")


def _with_image(msg: CameraFrame, shape: list, data: bytes, encoding: str | None = None) -> bytes:
    env = body_of(msg)
    env["b"]["image"] = [shape, data]
    if encoding is not None:
        env["b"]["encoding"] = encoding
    return repack(env)


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def _png(width: int, height: int, depth: int = 8, colour: int = 0, rows: bytes = b"") -> bytes:
    ihdr = struct.pack(">IIBBBBB", width, height, depth, colour, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + _png_chunk(b"IHDR", ihdr)
        + _png_chunk(b"IDAT", zlib.compress(rows))
        + _png_chunk(b"IEND", b"")
    )


def test_decoder_refuses_images_that_do_not_match_their_encoding() -> None:
    image = scene_like_image(24, 32)
    raw, png, jpeg = (frame(image, e) for e in IMAGE_ENCODINGS)
    png_bytes = body_of(png)["b"]["image"][1]
    jpeg_bytes = body_of(jpeg)["b"]["image"][1]
    raw_bytes = image.tobytes()
    # The encoding names one format, the bytes are another.
    reject(_with_image(png, [24, 32], raw_bytes), "image: not a PNG stream")
    reject(_with_image(jpeg, [24, 32], png_bytes), "image: not a JPEG stream")
    reject(_with_image(raw, [24, 32], jpeg_bytes), "raw image is .* bytes, expected 768")
    reject(_with_image(png, [24, 32], jpeg_bytes, "png"), "not a PNG stream")
    # The header's shape must be the frame's.
    reject(_with_image(png, [32, 24], png_bytes), r"png header says shape \(24, 32\).*\(32, 24\)")
    reject(_with_image(jpeg, [24, 31], jpeg_bytes), r"jpeg header says shape \(24, 32\)")
    # Truncated streams.
    for cut in (1, 12, len(png_bytes) // 2, len(png_bytes) - 1):
        reject(_with_image(png, [24, 32], png_bytes[:cut]), "PNG")
    for cut in (1, 3, len(jpeg_bytes) // 2, len(jpeg_bytes) - 1):
        reject(_with_image(jpeg, [24, 32], jpeg_bytes[:cut]), "JPEG")
    # Not grey, or not 8-bit.
    colour = cv2.imencode(".png", np.zeros((24, 32, 3), np.uint8))[1].tobytes()
    reject(_with_image(png, [24, 32], colour), "PNG must be 8-bit grey")
    deep = cv2.imencode(".png", np.zeros((24, 32), np.uint16))[1].tobytes()
    reject(_with_image(png, [24, 32], deep), "PNG must be 8-bit grey")
    colour_jpeg = cv2.imencode(".jpg", np.zeros((24, 32, 3), np.uint8))[1].tobytes()
    reject(_with_image(jpeg, [24, 32], colour_jpeg), "JPEG must be 8-bit grey")
    # A well-formed header over corrupt data.
    reject(_with_image(png, [2, 2], _png(2, 2, rows=b"\x07" * 3)), "could not be decoded")
    body = bytearray(png_bytes)
    body[45] ^= 0xFF  # inside IDAT: the CRC no longer matches
    reject(_with_image(png, [24, 32], bytes(body)), "could not be decoded")


def test_the_schema_bounds_the_image_before_any_decoding() -> None:
    """A small PNG declaring a huge image is refused on its declared shape: OpenCV never
    allocates it (its own limit is 2**30 pixels)."""
    msg = frame(scene_like_image(8, 8), "png")
    bomb = _png(100_000, 100_000)
    reject(_with_image(msg, [100_000, 100_000], bomb), r"expected shape \(1\.\.4096, 1\.\.4096\)")
    reject(_with_image(msg, [8, 8], bomb), r"png header says shape \(100000, 100000\)")


_SMALL = scene_like_image(16, 20, seed=3)
_PAYLOADS = {e: encode(frame(_SMALL, e, 50)) for e in IMAGE_ENCODINGS}


@settings(
    max_examples=examples(1500),
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.too_slow],
)
@given(
    st.sampled_from(IMAGE_ENCODINGS),
    st.sampled_from(IMAGE_ENCODINGS),
    st.lists(st.tuples(st.integers(0, 10_000), st.integers(0, 255)), min_size=1, max_size=8),
    st.integers(0, 10_000),
)
def test_mutated_frames_decode_to_a_valid_frame_or_are_refused(
    encoding: str, claimed: str, edits: list, cut: int
) -> None:
    """Corrupted image bytes (and a wrong encoding claimed for them): decode either returns a
    frame of the declared shape or raises ProtocolError, never anything else."""
    env = msgpack.unpackb(_PAYLOADS[encoding], raw=False)
    data = bytearray(env["b"]["image"][1])
    for where, value in edits:
        data[where % len(data)] = value
    env["b"]["image"][1] = bytes(data[: max(1, len(data) - cut % 64)] if cut % 3 == 0 else data)
    env["b"]["encoding"] = claimed
    try:
        out = decode(repack(env), expected=CameraFrame)
    except ProtocolError as e:
        assert "internal error" not in str(e)
        return
    assert out.image.shape == _SMALL.shape and out.image.dtype == np.uint8


def test_the_benchmark_measures_each_encoding(tmp_path) -> None:
    """``python -m bench net``'s codec figures, and its net_frames outputs."""
    from bench.net import FRAME_COLUMNS, codec_costs, write_frame_outputs

    image = scene_like_image(480, 640)
    costs = {spec: codec_costs(image, spec, n=3) for spec in ("raw", "png", "jpeg:90", "jpeg:50")}
    sizes = [costs[s]["bytes_per_frame"] for s in ("raw", "png", "jpeg:90", "jpeg:50")]
    assert sizes == sorted(sizes, reverse=True) and sizes[0] > image.size, sizes
    assert costs["raw"]["max_abs_error_grey"] == costs["png"]["max_abs_error_grey"] == 0
    assert 0 < costs["jpeg:90"]["mean_abs_error_grey"] < costs["jpeg:50"]["mean_abs_error_grey"]
    assert all(c["encode_ms"] > 0 and c["decode_ms"] > 0 for c in costs.values())
    rows = [
        {"encoding": s, "link": "test", **c, "frame_fps": 5.0, "frame_latency_ms_median": 1.0,
         "frame_latency_ms_p99": 2.0, "command_delay_by_images_ms": None}
        for s, c in costs.items()
    ]  # fmt: skip
    write_frame_outputs(tmp_path, rows)
    lines = (tmp_path / "net_frames.csv").read_text().splitlines()
    assert lines[0] == ",".join(FRAME_COLUMNS) and len(lines) == 1 + len(rows)
    if importlib.util.find_spec("matplotlib") is None:  # only the [bench] extra has it
        print("matplotlib not installed: net_frames.png not drawn, not checked")
    else:
        assert (tmp_path / "net_frames.png").stat().st_size > 0
