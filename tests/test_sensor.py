"""The realistic camera: the sensor's noise, blur and gain behave as a camera's, the drawn
conditions stay in their ranges, and out-of-range settings are refused (issue 23)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from work_site.sensor import GREY_WHITE, CameraConditions, Lighting, Sensor


def flat(grey: float, shape=(200, 200)) -> np.ndarray:
    return np.full(shape, grey, dtype=np.uint8)


def test_the_ideal_sensor_passes_the_image_unchanged() -> None:
    image = np.random.default_rng(0).integers(0, 256, (40, 50), dtype=np.uint8)
    assert Sensor().ideal
    assert Sensor().apply(image, np.random.default_rng(1)) is image


@pytest.mark.parametrize("grey", [20.0, 120.0, 200.0])
def test_shot_noise_grows_with_the_signal_and_read_noise_does_not(grey) -> None:
    full_well_e, read, gain = 5000.0, 1.5, 1.2
    sensor = Sensor(full_well_e=full_well_e, read_noise_grey=read, gain=gain)
    out = sensor.apply(flat(grey), np.random.default_rng(2)).astype(np.float64)
    # Poisson electrons: variance = signal × (white / full well) grey², times gain², plus
    # the read noise and the quantisation's 1/12.
    expected_var = gain**2 * grey * GREY_WHITE / full_well_e + read**2 + 1 / 12
    n = out.size
    # The sample variance of n normal draws has a relative standard deviation √(2/n).
    assert out.var() == pytest.approx(expected_var, rel=6 * math.sqrt(2 / n))
    assert out.mean() == pytest.approx(gain * grey, abs=0.05)


def test_exposure_gain_and_black_level_scale_and_offset_the_signal() -> None:
    sensor = Sensor(exposure=0.5, gain=1.5, black_level_grey=10.0)
    out = sensor.apply(flat(100.0), np.random.default_rng(3))
    assert np.all(out == round(100 * 0.5 * 1.5 + 10))


def test_a_bright_scene_saturates_at_white_as_a_sensor_does() -> None:
    out = Sensor(exposure=2.0, read_noise_grey=1.0).apply(flat(200.0), np.random.default_rng(4))
    assert out.dtype == np.uint8 and np.all(out == 255)


def test_blur_spreads_an_edge_and_keeps_the_light() -> None:
    step = np.zeros((64, 64), dtype=np.uint8)
    step[:, 32:] = 200
    out = Sensor(blur_sigma_px=1.0).apply(step, np.random.default_rng(5)).astype(np.float64)
    row = out[32]
    assert row[28] < 10 and row[36] > 190  # a few σ from the edge: unchanged
    assert 40 < row[31] < 160 and 40 < row[32] < 160  # at the edge: between
    assert out.sum() == pytest.approx(step.sum(dtype=np.float64), rel=0.01)


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("blur_sigma_px", -0.1),
        ("exposure", 0.0),
        ("gain", math.nan),
        ("full_well_e", 10.0),
        ("read_noise_grey", 100.0),
    ],
)
def test_a_sensor_setting_outside_its_range_is_refused_naming_it(field, value) -> None:
    with pytest.raises(ValueError, match=field):
        Sensor(**{field: value})


def test_lighting_refuses_a_zero_direction() -> None:
    with pytest.raises(ValueError, match="direction_W"):
        Lighting(direction_W=(0.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="ambient"):
        Lighting(ambient=-1.0)


def test_drawn_conditions_stay_inside_their_ranges() -> None:
    ranges = CameraConditions()
    rng = np.random.default_rng(6)
    for _ in range(200):
        c = ranges.draw(rng)
        assert ranges.blur_sigma_px[0] <= c.sensor.blur_sigma_px <= ranges.blur_sigma_px[1]
        assert ranges.exposure[0] <= c.sensor.exposure <= ranges.exposure[1]
        assert np.all(np.abs(c.X_offset[:3, 3]) <= ranges.camera_offset_m)
        assert np.allclose(c.X_offset[:3, :3] @ c.X_offset[:3, :3].T, np.eye(3))
        elevation = math.asin(c.lighting.direction_W[2] / np.linalg.norm(c.lighting.direction_W))
        lo, hi = ranges.light_elevation_rad
        assert lo - 1e-12 <= elevation <= hi + 1e-12
        assert ranges.k1[0] <= c.dist[0] <= ranges.k1[1] and c.dist.shape == (5,)


def test_a_range_upside_down_is_refused() -> None:
    with pytest.raises(ValueError, match="blur_sigma_px"):
        CameraConditions(blur_sigma_px=(1.0, 0.5))


def test_the_stated_noise_is_the_noise_applied() -> None:
    sensor = Sensor(gain=1.3, black_level_grey=6.0, full_well_e=8000.0, read_noise_grey=1.5)
    out = sensor.apply(flat(100.0), np.random.default_rng(9)).astype(np.float64)
    level = float(out.mean())
    assert out.std() == pytest.approx(sensor.noise_grey(level), rel=0.05)
