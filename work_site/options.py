"""The work-site server's options: rates, switches and their accepted ranges (Hz, SI)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from protocol import DEFAULT_SITE_ID, IMAGE_ENCODINGS
from protocol.images import DEFAULT_JPEG_QUALITY
from work_site.control.controller import CONTROL_PERIOD_S, DEFAULT_SURFACE_STIFFNESS_N_PER_M
from work_site.sensor import Sensor

PHYSICS_RATE_RANGE_HZ = (500.0, 2000.0)
"""Physics rates a work site accepts (Hz): within the range where grasping and placing were
verified, with a margin (too slow, the held block slips; too fast, the grasp's descent reads a
touch)."""
MAX_CAMERA_SUPERSAMPLE = 4
"""Rendering cost grows with its square: beyond it a frame takes seconds."""
DEADMAN_RANGE_S = (0.2, 5.0)
"""Accepted dead-man timeouts (s): above two heartbeat periods of the operator's link (0.1 s),
so that one late beat stops nothing; at most a few seconds of motion nobody watches."""


DEFAULT_CAMERA_SENSOR = Sensor(
    blur_sigma_px=0.65,
    gain=1.3,
    black_level_grey=6.0,
    full_well_e=12000.0,
    read_noise_grey=1.5,
)
"""The work site's camera: a real one's blur, shot and read noise, gain and black level, each
in the middle of the vision benchmark's realistic ranges (``CameraConditions``)."""


@dataclass(frozen=True)
class ServerOptions:
    """Rates and switches of the work-site server (Hz, SI)."""

    site_id: str = DEFAULT_SITE_ID
    physics_rate_hz: float = 1000.0
    state_rate_hz: float = 100.0
    heartbeat_rate_hz: float = 1.0
    camera: bool = True
    camera_supersample: int = 2
    """Render this many times larger and average down: a real camera's anti-aliased edges
    (vision finds nothing in aliased 1× renders; see docs/benchmarks.md)."""
    camera_sensor: Sensor = DEFAULT_CAMERA_SENSOR
    """The camera's blur, exposure, gain and noise on the rendered image."""
    camera_encoding: str = "jpeg"
    """How camera frames travel to operators: ``raw``, ``png`` or ``jpeg`` (protocol/images.py).
    Vision always works on the uncompressed frame, here. JPEG by default: far smaller than raw
    and faster to an operator, and it differs from raw by less than the sensor's own noise
    (docs/benchmarks.md, "Camera frames on the wire")."""
    camera_quality: int = DEFAULT_JPEG_QUALITY
    """JPEG quality 1..100 (with ``camera_encoding="jpeg"``)."""
    camera_X_WC: tuple | None = None
    """Where the camera really is (4×4 nested tuples), when not where its calibration says:
    frames are rendered from here, vision still uses the calibrated model."""
    time_scale: float = 1.0
    """Simulated seconds per second of wall time: 1 is real time; more runs programs faster
    (for benchmarks), as far as the machine keeps up."""
    surface_stiffness_n_per_m: float = DEFAULT_SURFACE_STIFFNESS_N_PER_M
    """Contact moves' impedance stiffness along the contact surfaces (N/m; along the normals
    it is §VI-B's 1,000); see :class:`~work_site.control.controller.Impedance`."""
    journal: Path | None = None
    """Where every program id and its reports are appended (JSON lines), so that a program
    re-sent after a restart of this server is not run again; None keeps them in memory."""
    vision_rate_hz: float = 0.0
    """Frames recognised per second at most (0: no vision). Vision runs in its own process,
    on the newest frame whenever it is idle."""
    vision_tracking: bool = True
    """Between two full recognitions (at ``vision_rate_hz``), follow the objects found in
    every camera frame (:meth:`~work_site.vision.recognizer.Recognizer.track`): poses fused
    over the camera's rate, for a fraction of a full recognition's time."""
    vision_scale: float = 1.0
    """Vision works on the frame resized by this factor (0.5: 320×240 from 640×480): less time
    per frame, less accuracy (docs/benchmarks.md, vision's resolution sweep)."""
    vision_index_views: int | None = None
    """Viewing directions sampled for vision's model index (None: its default)."""
    publish_truth: bool = False
    """Publish every object's true pose with each camera frame (``TruthPoses``), for
    end-to-end evaluation; a real cell has no such thing to publish."""
    stream_pacing: bool = True
    """Send robot states and camera frames less often while the operator's link queues them
    (``work_site/pacing.py``); off, they go at their full rates whatever the link."""
    deadman_s: float = 0.5
    """A running program is stopped when the operator's heartbeats have not come for this
    long (s; :data:`DEADMAN_RANGE_S`): its process died, or the link to it was cut."""

    def __post_init__(self) -> None:
        low, high = DEADMAN_RANGE_S
        if not low <= self.deadman_s <= high:
            raise ValueError(
                f"deadman_s must be in [{low:g}, {high:g}] s (the dead-man's timeout), "
                f"got {self.deadman_s}"
            )
        low, high = PHYSICS_RATE_RANGE_HZ
        rate = self.physics_rate_hz
        if not low <= rate <= high:
            raise ValueError(
                f"physics_rate_hz must be in [{low:g}, {high:g}] Hz (where grasping works), "
                f"got {rate}"
            )
        steps = rate * CONTROL_PERIOD_S
        if abs(steps - round(steps)) > 1e-9:
            raise ValueError(
                f"physics_rate_hz must be a whole number of steps per {CONTROL_PERIOD_S} s "
                f"control period (a multiple of {1 / CONTROL_PERIOD_S:g} Hz), got {rate}"
            )
        if not 0 < self.state_rate_hz <= 1.0 / CONTROL_PERIOD_S:
            raise ValueError(
                f"state_rate_hz must be in (0, {1.0 / CONTROL_PERIOD_S:g}] (the control rate)"
            )
        if not 0 < self.heartbeat_rate_hz <= 100:
            raise ValueError("heartbeat_rate_hz must be in (0, 100]")
        if not 1 <= self.camera_supersample <= MAX_CAMERA_SUPERSAMPLE:
            raise ValueError(
                f"camera_supersample must be in 1..{MAX_CAMERA_SUPERSAMPLE}, "
                f"got {self.camera_supersample}"
            )
        if self.camera_encoding not in IMAGE_ENCODINGS:
            raise ValueError(
                f"camera_encoding must be one of {IMAGE_ENCODINGS}, got {self.camera_encoding!r}"
            )
        if not 1 <= self.camera_quality <= 100:
            raise ValueError(f"camera_quality must be in 1..100, got {self.camera_quality}")
        k = self.surface_stiffness_n_per_m
        if not 100.0 <= k <= 1e5:
            raise ValueError(f"surface_stiffness_n_per_m must be in [100, 1e5] N/m, got {k}")
        if not 0.1 <= self.time_scale <= 100.0:
            raise ValueError(f"time_scale must be in [0.1, 100], got {self.time_scale}")
        if not 0.0 <= self.vision_rate_hz <= 100.0:
            raise ValueError(f"vision_rate_hz must be in [0, 100], got {self.vision_rate_hz}")
        if self.vision_rate_hz > 0 and not self.camera:
            raise ValueError("vision needs the camera")
        if not 0.25 <= self.vision_scale <= 2.0:
            raise ValueError(f"vision_scale must be in [0.25, 2], got {self.vision_scale}")
        views = self.vision_index_views
        if views is not None and not 50 <= views <= 20000:
            raise ValueError(f"vision_index_views must be in [50, 20000], got {views}")
