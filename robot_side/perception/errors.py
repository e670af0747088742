"""Errors of the perception package, each with a message that says what to do."""

from __future__ import annotations

from common.errors import DeepXPalmError


class ModelLoadError(DeepXPalmError):
    """A model file is missing, damaged, or needs a backend that is not installed."""


class DatasetError(DeepXPalmError, ValueError):
    """A data set file does not follow the documented layout."""
