"""Errors raised while loading model files."""


class ModelError(ValueError):
    """A model file is missing or malformed; the message names the file and the problem."""
