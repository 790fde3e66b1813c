"""Camera image encodings on the wire: ``raw``, ``png`` (lossless) and ``jpeg`` (lossy, quality).

:func:`encode_image` turns a grey image (h, w) uint8 into the bytes a :class:`CameraFrame` carries;
:func:`decode_image` turns them back and trusts nothing: the encoding must be known, the compressed
header must declare an 8-bit grey image of exactly the frame's declared shape (checked before
OpenCV decodes anything, so a small payload cannot make it allocate a large image), the stream
must be complete, and the decoded pixels must have that shape. Anything else raises
:class:`ProtocolError`.
"""

from __future__ import annotations

import struct
from typing import Literal, get_args

import cv2
import numpy as np

from .errors import ProtocolError

ImageEncoding = Literal["raw", "png", "jpeg"]
IMAGE_ENCODINGS: tuple[str, ...] = get_args(ImageEncoding)
"""What ``CameraFrame.encoding`` may be."""

DEFAULT_JPEG_QUALITY = 80
"""JPEG quality (1..100) when none is given: its error stays below the camera's own noise, at a
fraction of a raw frame's size and time on the link (docs/benchmarks.md, "Camera frames on the
wire")."""

PNG_COMPRESSION = 1
"""zlib level for PNG: a little larger than the default level's output, and faster to encode."""

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_IEND = b"\x00\x00\x00\x00IEND\xaeB`\x82"
_JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
"""Start-of-frame markers (baseline, progressive, …); C4/C8/CC are other segments."""


def _unknown(encoding: object) -> ProtocolError:
    return ProtocolError(f"unknown image encoding {encoding!r}, expected one of {IMAGE_ENCODINGS}")


def parse_image_encoding(text: str) -> tuple[str, int]:
    """``raw``, ``png``, ``jpeg`` or ``jpeg:QUALITY`` (1..100) → (encoding, quality).

    Raises ``ValueError`` naming the accepted forms (for command-line options).
    """
    name, sep, quality_text = text.partition(":")
    if name not in IMAGE_ENCODINGS or (sep and name != "jpeg"):
        raise ValueError(f"image encoding must be raw, png, jpeg or jpeg:QUALITY, got {text!r}")
    quality = DEFAULT_JPEG_QUALITY
    if sep:
        try:
            quality = int(quality_text)
        except ValueError:
            quality = -1
        if not 1 <= quality <= 100:
            raise ValueError(f"JPEG quality must be an integer in 1..100, got {quality_text!r}")
    return name, quality


def encode_image(image: np.ndarray, encoding: str, quality: int = DEFAULT_JPEG_QUALITY) -> bytes:
    """The wire bytes of a grey ``image`` (h, w) uint8 in ``encoding`` (``quality``: JPEG's)."""
    if encoding == "raw":
        return np.ascontiguousarray(image, dtype=np.uint8).tobytes()
    if encoding == "png":
        ok, buf = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, PNG_COMPRESSION])
    elif encoding == "jpeg":
        ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    else:
        raise _unknown(encoding)
    if not ok:
        raise ProtocolError(f"OpenCV could not encode a {image.shape} image as {encoding}")
    return buf.tobytes()


def _png_header(data: bytes) -> tuple[int, int]:
    """(height, width) from a PNG's IHDR; refuses anything but 8-bit grey, non-interlaced."""
    if len(data) < 33 or data[:8] != _PNG_SIGNATURE or data[12:16] != b"IHDR":
        raise ProtocolError("not a PNG stream (no signature and IHDR chunk)")
    width, height, depth, colour, _, _, interlace = struct.unpack(">IIBBBBB", data[16:29])
    if depth != 8 or colour != 0:
        raise ProtocolError(f"PNG must be 8-bit grey, got bit depth {depth}, colour type {colour}")
    if interlace != 0:
        raise ProtocolError("PNG must not be interlaced")
    if not data.endswith(_PNG_IEND):
        raise ProtocolError("PNG stream is truncated (no IEND chunk at its end)")
    return height, width


def _jpeg_header(data: bytes) -> tuple[int, int]:
    """(height, width) from a JPEG's start-of-frame segment; refuses anything but 8-bit grey."""
    if len(data) < 4 or data[:2] != b"\xff\xd8":
        raise ProtocolError("not a JPEG stream (no start-of-image marker)")
    if not data.endswith(b"\xff\xd9"):
        raise ProtocolError("JPEG stream is truncated (no end-of-image marker at its end)")
    i = 2
    while i + 4 <= len(data):
        if data[i] != 0xFF:
            raise ProtocolError(f"JPEG: expected a marker at byte {i}")
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        (length,) = struct.unpack(">H", data[i + 2 : i + 4])
        if length < 2 or i + 2 + length > len(data):
            raise ProtocolError(f"JPEG: segment at byte {i} has a bad length {length}")
        if marker in _JPEG_SOF:
            if length < 8:
                raise ProtocolError("JPEG: start-of-frame segment too short")
            precision, height, width, components = struct.unpack(">BHHB", data[i + 4 : i + 10])
            if precision != 8 or components != 1:
                raise ProtocolError(
                    f"JPEG must be 8-bit grey, got {precision}-bit with {components} components"
                )
            return height, width
        if marker == 0xDA:  # start of scan before any frame header
            break
        i += 2 + length
    raise ProtocolError("JPEG: no start-of-frame segment before the image data")


def decode_image(data: bytes, encoding: str, shape: tuple[int, int]) -> np.ndarray:
    """The grey image (h, w) uint8 in ``data``, which must be ``encoding`` of that ``shape``.

    ``shape`` is the frame's declared shape, already checked against the schema's limits.
    Raises :class:`ProtocolError` for anything else (unknown encoding, wrong header, truncated or
    corrupt stream, shape mismatch).
    """
    if encoding == "raw":
        expected = shape[0] * shape[1]
        if len(data) != expected:
            raise ProtocolError(
                f"raw image is {len(data)} bytes, expected {expected} for shape {shape}"
            )
        return np.frombuffer(data, dtype=np.uint8).reshape(shape)
    if encoding == "png":
        header = _png_header(data)
    elif encoding == "jpeg":
        header = _jpeg_header(data)
    else:
        raise _unknown(encoding)
    if header != tuple(shape):
        raise ProtocolError(f"{encoding} header says shape {header}, the frame declares {shape}")
    try:
        image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error as e:
        raise ProtocolError(f"{encoding} image could not be decoded ({e})".strip()) from None
    if image is None:
        raise ProtocolError(f"{encoding} image could not be decoded (corrupt data)")
    if image.dtype != np.uint8 or image.shape != tuple(shape):
        raise ProtocolError(
            f"{encoding} image decoded to {image.dtype} {image.shape}, expected uint8 {shape}"
        )
    return image
