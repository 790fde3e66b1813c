"""The Cramér–Rao bound of a one-view pose against a brute-force reference: many noisy views
fitted by least squares (scipy, a numerical Jacobian, another parametrisation) scatter as the
bound says, and the edge-position bound matches its closed form (issue 23)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from bench.vision_crb import edge_sigma_px, pose_bound, visible_edge_points
from models.scene import load_scene
from models.transforms import make_pose
from work_site.vision.model import project, transform, vision_model


def test_many_noisy_views_fitted_scatter_as_the_bound_says() -> None:
    scene = load_scene()
    model = vision_model(scene.object("cube").model)
    K = scene.camera.K
    R = Rotation.from_rotvec([0.4, -0.5, 0.3]).as_matrix()
    X_CO = make_pose(R, [0.03, -0.02, 0.7])
    P_O, edge = visible_edge_points(model, X_CO, K, [])
    sigma = np.full(len(P_O), 0.4)
    bound = pose_bound(model, X_CO, K, P_O, edge, sigma)
    assert bound is not None

    uv0 = project(transform(X_CO, P_O), K)
    ends = project(transform(X_CO, model.edges_O[edge]), K)
    d = ends[:, 1] - ends[:, 0]
    nrm = np.column_stack([-d[:, 1], d[:, 0]]) / np.linalg.norm(d, axis=1, keepdims=True)

    def pose(x: np.ndarray) -> np.ndarray:  # a rotation vector and O's origin, in C
        return make_pose(Rotation.from_rotvec(x[:3]).as_matrix() @ R, X_CO[:3, 3] + x[3:])

    rng = np.random.default_rng(5)
    est = []
    for _ in range(300):
        offsets = rng.normal(0.0, sigma)
        fit = least_squares(
            lambda x, o=offsets: (np.sum(nrm * (project(transform(pose(x), P_O), K) - uv0), 1)
                                  - o) / sigma,
            np.zeros(6), xtol=1e-12, ftol=1e-12,
        )  # fmt: skip
        est.append(fit.x)
    est = np.array(est)
    ray = X_CO[:3, 3] / np.linalg.norm(X_CO[:3, 3])
    along = est[:, 3:] @ ray
    across = np.linalg.norm(est[:, 3:] - along[:, None] * ray, axis=1)
    turn = np.linalg.norm(est[:, :3], axis=1)
    measured = (np.median(across), np.median(np.abs(along)), np.median(turn))
    predicted = bound.median_errors(X_CO, np.random.default_rng(6))
    # 300 fits put a median within about ±6 % (twice its standard error), the bound's 4,000
    # draws within ±2 %: 12 % leaves room for both and for the fits' small nonlinearity.
    for m, p, what in zip(measured, predicted, ("across", "along", "turn"), strict=True):
        assert m == pytest.approx(p, rel=0.12), f"{what}: fitted {m:.3g}, bound {p:.3g}"
    # The depth along the ray is what one view tells least.
    assert predicted[1] > predicted[0]


def test_the_edge_bound_follows_noise_contrast_and_blur() -> None:
    s = edge_sigma_px(np.array([20.0, 40.0]), noise_grey=2.0, blur_sigma_px=1.0)
    expected = 2.0 * math.sqrt(2 * math.sqrt(math.pi) * math.sqrt(1.0 + 1.0 / 12.0)) / 20.0
    assert s[0] == pytest.approx(expected)
    assert s[1] == pytest.approx(expected / 2)  # twice the contrast, half the spread
