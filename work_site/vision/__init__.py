"""Model-based vision (§IV): recognise and locate the blocks in one grey camera image.

``Recognizer(...).recognize(image, camera[, robot_q_rad, finger_opening_m])`` → list of
:class:`Detection` (model name, pose ``X_WO``, score); the arm's joints, when given, make the
arm part of the environment (:mod:`.robot_parts`). Lines (:mod:`.lines`) → groups and the
model index (:mod:`.index`) → hypotheses (:mod:`.hypotheses`) → Lowe's pose fit (:mod:`.pose`)
→ verification (:mod:`.verification`) → selection (:mod:`.pose_sets`), run by
:mod:`.recognizer` and tuned by :mod:`.params`. Calibration: :mod:`.calibration`; rendered
scenes with ground truth and their scoring are in ``bench/``.
"""

from work_site.vision.index import GroupParams, IndexParams
from work_site.vision.lines import LineParams, detect_lines
from work_site.vision.params import RecognizerParams
from work_site.vision.pose import PoseFit, fit_pose
from work_site.vision.pose_sets import Detection
from work_site.vision.recognizer import Recognizer

__all__ = [
    "Detection",
    "GroupParams",
    "IndexParams",
    "LineParams",
    "PoseFit",
    "Recognizer",
    "RecognizerParams",
    "detect_lines",
    "fit_pose",
    "recognize",
]


def recognize(image, camera, recognizer: Recognizer | None = None) -> list[tuple]:
    """``(model name, X_WO (4, 4), score)`` for each object found in ``image`` (grey uint8) seen
    by ``camera``. Builds a default :class:`Recognizer` (index cached on disk) if none is
    given; keep one for repeated calls."""
    rec = recognizer or _default()
    return [(r.model, r.X_WO, r.score) for r in rec.recognize(image, camera)]


_DEFAULT: list[Recognizer] = []


def _default() -> Recognizer:
    if not _DEFAULT:
        _DEFAULT.append(Recognizer())
    return _DEFAULT[0]
