"""The recogniser's tuning: hypothesis budgets, fitting, and verification thresholds.

Units: pixels (``_px``), radians (``_rad``), metres (``_m``), seconds (``_s``); fractions are of
visible projected edge length unless said otherwise. The measurements behind the values are
on docs/tuning.md.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

ENV_MATCH_TOL_PX = 1.5
"""Image lines this close to a projected edge of the fixed environment are its own."""
PART_MARGIN_PX = 1.5
"""Edge points of a grown model this far outside the outline of the part it was grown around
belong to what it adds to that part."""


@dataclass(frozen=True)
class RecognizerParams:
    """Tuning of hypothesis testing and verification (pixels, radians, metres)."""

    max_hypotheses: int = 200  # indexed hypotheses, each chain of lines in one direction
    refine_rounds: int = 2  # predict-and-refit rounds, matching within match_tol_px in turn:
    match_tol_px: tuple[float, ...] = (5.0, 1.5)  # wide first to gather, tight to settle
    match_angle_rad: float = np.deg2rad(5.0)
    fit_iterations: int = 3  # per fit; later rounds refit, so each fit need not converge
    fit_tol: float = 1e-7  # rad and m: a fit stops at steps this small (1 µm ≪ the 1 mm goal)
    init_rms_max_px: float = 4.0
    final_rms_max_px: float = 1.0
    min_matched_edges: int = 5
    min_matched_edges_few: int = 4  # down to this many, with score ≥ few_edges_min_score,
    few_edges_min_score: float = 0.6  # and the pose turned about its centre tried too: a
    # wedge fitted to 4 edges may be turned by 90° and show nearly the same outline
    verify_tol_px: float = 1.5
    verify_angle_rad: float = np.deg2rad(4.0)
    gradient_min: float = 60.0
    gradient_angle_rad: float = np.deg2rad(20.0)
    min_score: float = 0.6
    min_length_fraction: float = 0.45
    keep_better_earlier_fit: bool = True  # see verification.fit_and_verify
    candidate_min_length_fraction: float = 0.35  # a fitted pose stays a candidate with less
    candidate_min_score: float = 0.5  # than the above, to be verified in full by the selection
    # once the other objects can hide some of its edges: a block partly hidden by a neighbour
    # would otherwise count its hidden edges as missing
    min_silhouette_fraction: float = 0.65
    max_shared_fraction: float = 0.4  # of a candidate's matched image lines, at most this
    # many may be an accepted object's: blocks side by side share the lines along which they
    # touch
    grown_min_silhouette_fraction: float = 0.75  # a bigger model grown around a found part
    # must show more of its outline: a phantom part over empty table is the usual false object
    grown_min_extra_fraction: float = 0.2  # and the gradient along the edges it adds to the
    # part it was grown around (phantom L blocks around a tall block, over empty table, show
    # almost none)
    table_tol_m: float = 0.006
    early_table_tol_m: float = 0.03
    same_pose_m: float = 0.004
    same_pose_rad: float = np.deg2rad(4.0)
    max_penetration_m: float = 0.002
    max_per_model: int | None = 1
    kernel_prior: float = 0.05
    time_budget_s: float | None = None
    confident_score: float = 0.85
    hidden_support_min_score: float = 0.7  # a block that nothing found holds up is kept
    # at this score (what holds it is hidden: a block under a block), when no pose of it
    # rests on the table (see pose_sets.select); below it, it is taken for a phantom
    quick_support_min: float = 0.5
    grown_quick_support_min: float = 0.6  # the same for a bigger model grown around a found
    # part: it is nearly in place already, so a true one is well supported
    grow_support_min: float = 0.5  # batch support (no occlusion) of a bigger model grown
    # around a found part, before its full test
    grown_pre_length_min: float = 0.4  # and its verification before refitting, which tells
    grown_pre_score_min: float = 0.5  # most phantoms apart at a fraction of the full test
    grown_max_tests: int = 2  # poses of each bigger model around a found part fully tested,
    # best supported first
    grown_pre_gradient_min: float = 0.6  # its gradient agreement then
    prefilter_tilt_rad: float = np.deg2rad(30.0)
    prefilter_height_m: float = 0.06
    table_prior: bool = True
    table_prior_px_per_m: float = 1000.0
    table_prior_px_per_rad: float = 60.0
    table_hypotheses: bool = True
    max_table_hypotheses: int = 150  # the best supported, tested in turn
    table_coarse_min: float = 0.4  # table hypotheses are scored in full only if their support
    # at 2 of 6 points per edge reaches this
    table_angle_tol_rad: float = np.deg2rad(8.0)
    faint_lines: bool = True  # a second, sensitive line pass (lines.FAINT_LINE_PARAMS) whose
    # lines, beyond the first pass's, weigh only in the selection's re-check of candidates
    stacked_search: bool = True  # after the table search, the junction hypotheses of blocks
    # resting on the found objects' upward faces
    stacked_face_tilt_rad: float = np.deg2rad(5.0)  # a found face this close to horizontal
    # is a support
    free_search: bool = True  # after the table search, look for objects anywhere above the
    # table (on others, leaning), without the table prior
    table_rejection_p: float = 1e-3  # an object found on the table is weighed after its pose
    # above it when its lines, were it on the table, would be this unlikely (pose.
    # constraint_p_value): one view hardly tells depth, and the table prior puts a block that
    # sits on another further along its ray; 0 never weighs it after. Also the significance
    # at which a block's lines refuse its move along its ray out of one it sank into
    # (pose_sets._settled); 0 never moves it
    track_margin_px: float = 12.0  # tracking looks for an object's lines this far around its
    # predicted outline: well beyond a still block's frame-to-frame error (a fraction of a
    # pixel) and the match's widest tolerance, so that a block nudged a few millimetres is
    # followed too
