"""The operator's web page (viser): camera with recognitions, the model, the task, the program."""

from operator_site.ui.page import NO_WORKPIECE, OperatorPage

__all__ = ["NO_WORKPIECE", "OperatorPage"]
