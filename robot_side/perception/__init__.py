"""Tilt and position recognition from the two tactile pads.

``load_classifier()`` returns the shipped model behind the fastest exact
backend; nothing imported here pulls in torch, so the robot node starts
without paying for it. Training lives in ``train`` and ``cli`` (``deepxpalm
train``), the data set in ``dataset``.
"""

from robot_side.perception.errors import DatasetError, ModelLoadError
from robot_side.perception.inference import (
    BACKENDS,
    DEFAULT_BACKEND_ORDER,
    Prediction,
    TiltClassifier,
    load_classifier,
)
from robot_side.perception.weights import DEFAULT_MODEL, MODELS_DIR

__all__ = [
    "BACKENDS",
    "DEFAULT_BACKEND_ORDER",
    "DEFAULT_MODEL",
    "MODELS_DIR",
    "DatasetError",
    "ModelLoadError",
    "Prediction",
    "TiltClassifier",
    "load_classifier",
]
