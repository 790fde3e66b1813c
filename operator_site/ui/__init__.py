"""The operator's web page (viser): camera with recognitions, the model, the task, the program."""

from operator_site.ui.page import OperatorPage
from operator_site.ui.task_panel import NO_WORKPIECE

__all__ = ["NO_WORKPIECE", "OperatorPage"]
