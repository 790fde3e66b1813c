"""Lowe's line-based pose fit: exact on exact lines, statistically right on noisy lines."""

from __future__ import annotations

import numpy as np
import pytest

from models.scene import load_scene
from models.transforms import invert_pose, so3_log
from work_site.vision.model import visible_edges, vision_model
from work_site.vision.pose import (
    apply_update,
    constraint_p_value,
    fit_pose,
    line_residuals,
    residuals_and_jacobian,
)


@pytest.fixture(scope="module")
def setup():
    scene = load_scene()
    return scene.camera, {o.name: (vision_model(o.model), o.X_WO) for o in scene.movable}


def _true_lines(camera, model, X_WO):
    X_CO = invert_pose(camera.X_WC) @ X_WO
    ids, segs, _ = visible_edges(model, X_CO, camera.K)
    return X_CO, model.edges_O[ids], segs


@pytest.mark.parametrize("name", ["cube", "wedge", "l_block", "hex_prism"])
def test_exact_lines_give_the_pose_to_1e6(setup, name) -> None:
    camera, models = setup
    model, X_WO = models[name]
    X_CO, edges, segs = _true_lines(camera, model, X_WO)
    rng = np.random.default_rng(3)
    # Image segments are only parts of the edges (occlusion, missed corners).
    t = rng.uniform(0.0, 0.35, (len(segs), 2))
    a, b = segs[:, :2], segs[:, 2:]
    partial = np.column_stack([a + t[:, :1] * (b - a), b - t[:, 1:] * (b - a)])
    start = apply_update(X_CO, np.r_[rng.normal(0, 0.08, 3), rng.normal(0, 0.01, 3)])
    fit = fit_pose(start, edges, partial, camera.K)
    assert fit.converged
    assert np.max(np.abs(fit.X_CO - X_CO)) < 1e-6
    assert fit.rms_px < 1e-6


def test_analytic_jacobian_matches_finite_differences(setup) -> None:
    camera, models = setup
    model, X_WO = models["l_block"]
    X_CO, edges, segs = _true_lines(camera, model, X_WO)
    X = apply_update(X_CO, np.array([0.02, -0.03, 0.01, 0.004, -0.002, 0.01]))
    r, J = residuals_and_jacobian(X, edges, segs, camera.K)
    np.testing.assert_allclose(r, line_residuals(X, edges, segs, camera.K), atol=1e-12)
    h = 1e-6
    J_num = np.column_stack(
        [
            (
                line_residuals(apply_update(X, h * e), edges, segs, camera.K)
                - line_residuals(apply_update(X, -h * e), edges, segs, camera.K)
            )
            / (2 * h)
            for e in np.eye(6)
        ]
    )
    np.testing.assert_allclose(J, J_num, atol=1e-4 * np.max(np.abs(J)))


def test_noisy_lines_give_the_error_the_jacobian_predicts(setup) -> None:
    """End-point noise σ gives pose errors with covariance σ² (JᵀJ)⁻¹ (to first order)."""
    camera, models = setup
    model, X_WO = models["tall_block"]
    X_CO, edges, segs = _true_lines(camera, model, X_WO)
    sigma_px = 0.3
    _, J = residuals_and_jacobian(X_CO, edges, segs, camera.K)
    predicted_std = sigma_px * np.sqrt(np.diag(np.linalg.inv(J.T @ J)))
    rng = np.random.default_rng(11)
    errors = []
    for _ in range(200):
        noisy = segs + rng.normal(0.0, sigma_px, segs.shape)
        fit = fit_pose(X_CO, edges, noisy, camera.K)
        R_err = so3_log(fit.X_CO[:3, :3] @ X_CO[:3, :3].T)
        errors.append(np.r_[R_err, fit.X_CO[:3, 3] - X_CO[:3, 3]])
    measured_std = np.std(errors, axis=0)
    np.testing.assert_array_less(np.abs(np.mean(errors, axis=0)), 4 * predicted_std / np.sqrt(20))
    ratio = measured_std / predicted_std
    # Noise along the line direction does not count, and the end point noise is isotropic:
    # the prediction σ²(JᵀJ)⁻¹ is exact to first order, so only sampling error remains.
    assert np.all((ratio > 0.75) & (ratio < 1.3)), ratio
    # And the depth is the worst-determined translation, as §IV-B says.
    assert predicted_std[5] > predicted_std[3] and predicted_std[5] > predicted_std[4]


def test_jacobian_with_skewed_intrinsics_matches_finite_differences(setup) -> None:
    """The elementwise Jacobian carries every term of K, the skew ``K[0, 1]`` included."""
    camera, models = setup
    model, X_WO = models["wedge"]
    X_CO, edges, segs = _true_lines(camera, model, X_WO)
    K = camera.K.copy()
    K[0, 1] = 3.5
    X = apply_update(X_CO, np.array([-0.01, 0.02, 0.03, -0.003, 0.002, 0.006]))
    r, J = residuals_and_jacobian(X, edges, segs, K)
    np.testing.assert_allclose(r, line_residuals(X, edges, segs, K), atol=1e-12)
    h = 1e-6
    J_num = np.column_stack(
        [
            (
                line_residuals(apply_update(X, h * e), edges, segs, K)
                - line_residuals(apply_update(X, -h * e), edges, segs, K)
            )
            / (2 * h)
            for e in np.eye(6)
        ]
    )
    np.testing.assert_allclose(J, J_num, atol=1e-4 * np.max(np.abs(J)))


def test_a_fit_at_its_minimum_evaluates_nothing_more(setup, monkeypatch) -> None:
    """Steps below ``tol`` are not tried: a fit started at its optimum evaluates the residuals
    once, and a coarser ``tol`` stops sooner at a pose within that tolerance."""
    import work_site.vision.pose as pose_module

    camera, models = setup
    model, X_WO = models["cube"]
    X_CO, edges, segs = _true_lines(camera, model, X_WO)
    rng = np.random.default_rng(8)
    noisy = segs + rng.normal(0.0, 0.3, segs.shape)
    start = apply_update(X_CO, np.r_[rng.normal(0, 0.05, 3), rng.normal(0, 0.005, 3)])
    calls = []
    real = pose_module.residuals_and_jacobian
    monkeypatch.setattr(
        pose_module, "residuals_and_jacobian", lambda *a: calls.append(1) or real(*a)
    )
    fine = fit_pose(start, edges, noisy, camera.K, iterations=50, tol=1e-12)
    n_fine = len(calls)
    calls.clear()
    coarse = fit_pose(start, edges, noisy, camera.K, iterations=50, tol=1e-7)
    assert coarse.converged and len(calls) < n_fine
    assert np.max(np.abs(coarse.X_CO - fine.X_CO)) < 1e-6
    calls.clear()
    again = fit_pose(fine.X_CO, edges, noisy, camera.K, iterations=50, tol=1e-7)
    assert len(calls) == 1 and again.converged
    np.testing.assert_array_equal(again.X_CO, fine.X_CO)


def test_a_constraint_s_p_value_is_uniform_when_it_holds_and_tiny_when_it_does_not(setup):
    """The F-test of a fit with a prior against the free fit, against Monte Carlo: with the
    prior "the object is at this depth" (stiff, one residual) and end-point noise σ, its
    p-values are uniform when the depth is right (each decile gets its tenth, within sampling
    error), and tiny when the prior puts it 2 cm further."""
    camera, models = setup
    model, X_WO = models["tall_block"]
    X_CO, edges, segs = _true_lines(camera, model, X_WO)
    sigma_px, stiffness_px_per_m = 0.3, 1e6

    def at_depth(z_m: float):
        def prior(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            J = np.zeros((1, 6))
            J[0, 5] = stiffness_px_per_m
            return np.array([stiffness_px_per_m * (X[2, 3] - z_m)]), J

        return prior

    rng = np.random.default_rng(5)
    trials = 400
    p_right, p_wrong = [], []
    for _ in range(trials):
        noisy = segs + rng.normal(0.0, sigma_px, segs.shape)
        p_right.append(
            constraint_p_value(X_CO, X_CO, edges, noisy, camera.K, at_depth(X_CO[2, 3]), 30, 1e-10)
        )
        further = X_CO[2, 3] + 0.02
        p_wrong.append(
            constraint_p_value(X_CO, X_CO, edges, noisy, camera.K, at_depth(further), 30, 1e-10)
        )
    counts = np.histogram(p_right, bins=10, range=(0.0, 1.0))[0]
    expected = trials / 10
    assert np.all(np.abs(counts - expected) < 4 * np.sqrt(expected * 0.9)), counts
    assert np.mean(np.array(p_wrong) < 1e-3) > 0.95
    # No degree of freedom left to measure the noise: nothing can be rejected.
    few = constraint_p_value(X_CO, X_CO, edges[:3], segs[:3], camera.K, at_depth(0.0), 30, 1e-10)
    assert few == 1.0
