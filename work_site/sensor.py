"""What a real camera does between the scene's light and the 8-bit image vision reads.

The renderer gives an ideal grey image: sharp, noiseless, lit one way. A real camera blurs it
through its lens, scales it by exposure and gain, adds photon (shot) noise that grows with the
signal and read noise that does not, clips at black and white, and quantises. :class:`Sensor`
applies those in that order; :class:`Lighting` says where the light comes from and how strong
it is (the renderer's light model); :class:`CameraConditions` draws both, and the camera's
place, at random for a scene, within the ranges a bench asks for. Lens distortion is rendered
by :func:`work_site.camera.render_grey` from the camera model's ``dist``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np

from models.transforms import make_pose, rpy_to_R

GREY_WHITE = 255.0
"""The 8-bit white level: an ideal grey of 255 fills the pixel's well at exposure 1."""


def _check_range(owner: str, name: str, value: float, lo: float, hi: float) -> None:
    if not (math.isfinite(value) and lo <= value <= hi):
        raise ValueError(f"{owner}.{name} must be in [{lo:g}, {hi:g}], got {value!r}")


@dataclass(frozen=True)
class Sensor:
    """A camera's optics and sensor on the ideal image (grey levels of 0–255).

    ``blur_sigma_px``: the lens's point spread (Gaussian σ, output pixels); ``exposure``:
    light gathered relative to the renderer's (exposure time × aperture); ``gain``: analogue
    gain after the well; ``black_level_grey``: the offset added at read-out;
    ``full_well_e``: electrons of a pixel at white (exposure 1, gain 1): shot noise is the
    Poisson spread of the electrons, so it grows as √signal (``inf``: none);
    ``read_noise_grey``: Gaussian read-out noise (σ, grey levels). The defaults are an ideal
    camera: the image passes unchanged.
    """

    blur_sigma_px: float = 0.0
    exposure: float = 1.0
    gain: float = 1.0
    black_level_grey: float = 0.0
    full_well_e: float = math.inf
    read_noise_grey: float = 0.0

    def __post_init__(self) -> None:
        _check_range("Sensor", "blur_sigma_px", self.blur_sigma_px, 0.0, 10.0)
        _check_range("Sensor", "exposure", self.exposure, 0.05, 20.0)
        _check_range("Sensor", "gain", self.gain, 0.1, 20.0)
        _check_range("Sensor", "black_level_grey", self.black_level_grey, 0.0, 128.0)
        _check_range("Sensor", "read_noise_grey", self.read_noise_grey, 0.0, 64.0)
        if not (self.full_well_e == math.inf or 100.0 <= self.full_well_e <= 1e7):
            raise ValueError(
                f"Sensor.full_well_e must be in [100, 1e7] electrons or inf, got "
                f"{self.full_well_e!r}"
            )

    @property
    def ideal(self) -> bool:
        """True if :meth:`apply` returns the image unchanged."""
        return self == Sensor()

    def noise_grey(self, grey: float) -> float:
        """σ (grey levels) of :meth:`apply`'s output at level ``grey``: read noise, the shot
        noise of the signal that gives that level, and rounding to 8 bits."""
        var = self.read_noise_grey**2 + 1.0 / 12.0
        if self.full_well_e != math.inf:
            signal = max(grey - self.black_level_grey, 0.0) / self.gain
            var += self.gain**2 * signal * GREY_WHITE / self.full_well_e
        return math.sqrt(var)

    def apply(self, ideal_grey: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """The camera's 8-bit image (h, w) of the renderer's ideal grey image (h, w)."""
        if self.ideal:
            return ideal_grey
        import cv2

        signal = ideal_grey.astype(np.float64) * self.exposure
        if self.blur_sigma_px > 0:
            signal = cv2.GaussianBlur(signal, (0, 0), self.blur_sigma_px)
        if self.full_well_e != math.inf:
            e_per_grey = self.full_well_e / GREY_WHITE
            electrons = rng.poisson(np.maximum(signal, 0.0) * e_per_grey)
            signal = electrons / e_per_grey
        out = signal * self.gain + self.black_level_grey
        if self.read_noise_grey > 0:
            out = out + rng.normal(0.0, self.read_noise_grey, out.shape)
        # Black and white are where a real sensor saturates: clipping is its behaviour.
        return np.clip(np.rint(out), 0, GREY_WHITE).astype(np.uint8)


@dataclass(frozen=True)
class Lighting:
    """The renderer's one light: ``direction_W`` (towards the light, need not be unit) and the
    Phong coefficients of ambient, diffuse and specular light (pybullet's TinyRenderer
    defaults)."""

    direction_W: tuple[float, float, float] = (0.4, -0.6, 1.0)
    ambient: float = 0.6
    diffuse: float = 0.35
    specular: float = 0.05

    def __post_init__(self) -> None:
        d = np.asarray(self.direction_W, dtype=np.float64)
        if d.shape != (3,) or not np.all(np.isfinite(d)) or np.linalg.norm(d) < 1e-9:
            raise ValueError(f"Lighting.direction_W must be a finite non-zero 3-vector, got {d}")
        for f in ("ambient", "diffuse", "specular"):
            _check_range("Lighting", f, getattr(self, f), 0.0, 2.0)


@dataclass(frozen=True)
class CameraConditions:
    """Ranges from which a scene's camera and light are drawn (each ``(low, high)``, uniform
    unless said otherwise): the realistic camera of the vision benchmark and dataset.

    Exposure is drawn log-uniform (a factor either way is equally likely); the light's
    direction from elevations and any azimuth; the camera's place off its nominal pose by a
    translation of at most ``camera_offset_m`` along each axis and a rotation of at most
    ``camera_turn_rad`` about each; radial distortion ``k1``, ``k2`` (OpenCV's model).
    """

    blur_sigma_px: tuple[float, float] = (0.3, 1.0)
    exposure: tuple[float, float] = (0.6, 1.3)
    gain: tuple[float, float] = (1.0, 1.6)
    black_level_grey: tuple[float, float] = (0.0, 12.0)
    full_well_e: tuple[float, float] = (4000.0, 20000.0)
    read_noise_grey: tuple[float, float] = (0.5, 2.5)
    light_elevation_rad: tuple[float, float] = (np.deg2rad(25.0), np.deg2rad(85.0))
    ambient: tuple[float, float] = (0.35, 0.7)
    diffuse: tuple[float, float] = (0.2, 0.6)
    specular: tuple[float, float] = (0.0, 0.15)
    camera_offset_m: float = 0.03
    camera_turn_rad: float = np.deg2rad(1.5)
    k1: tuple[float, float] = (-0.12, 0.04)
    k2: tuple[float, float] = (-0.02, 0.05)

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            pair = v if isinstance(v, tuple) else (0.0, v)
            if len(pair) != 2 or not all(math.isfinite(x) for x in pair) or pair[0] > pair[1]:
                raise ValueError(f"CameraConditions.{f.name} must be a finite (low, high), got {v}")

    def draw(self, rng: np.random.Generator) -> Condition:
        """One scene's sensor, light, camera offset and distortion."""
        u = rng.uniform
        lo, hi = self.exposure
        sensor = Sensor(
            blur_sigma_px=u(*self.blur_sigma_px),
            exposure=float(np.exp(u(np.log(lo), np.log(hi)))),
            gain=u(*self.gain),
            black_level_grey=u(*self.black_level_grey),
            full_well_e=u(*self.full_well_e),
            read_noise_grey=u(*self.read_noise_grey),
        )
        elevation, azimuth = u(*self.light_elevation_rad), u(-np.pi, np.pi)
        lighting = Lighting(
            direction_W=(
                float(np.cos(elevation) * np.cos(azimuth)),
                float(np.cos(elevation) * np.sin(azimuth)),
                float(np.sin(elevation)),
            ),
            ambient=u(*self.ambient),
            diffuse=u(*self.diffuse),
            specular=u(*self.specular),
        )
        a, t = self.camera_turn_rad, self.camera_offset_m
        X_offset = make_pose(rpy_to_R(u(-a, a, 3)), u(-t, t, 3))
        dist = np.array([u(*self.k1), u(*self.k2), 0.0, 0.0, 0.0])
        return Condition(sensor, lighting, X_offset, dist)


@dataclass(frozen=True, eq=False)
class Condition:
    """One scene's draw from :class:`CameraConditions`: the sensor, the light, the camera's
    offset from its nominal pose (``X_WC = X_WC_nominal @ X_offset``, in the camera's frame)
    and its distortion coefficients (5,)."""

    sensor: Sensor
    lighting: Lighting
    X_offset: np.ndarray
    dist: np.ndarray
