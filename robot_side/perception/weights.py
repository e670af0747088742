"""Reading a model's ``.npz`` without torch, so the robot node starts fast.

The file holds the ``state_dict`` arrays under their torch names and a
``meta`` entry: UTF-8 JSON with the architecture and how it was trained.
"""

from __future__ import annotations

import json
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from robot_side.perception.errors import ModelLoadError

#: where the shipped model lives inside the package
MODELS_DIR = Path(__file__).resolve().parent / "models"
DEFAULT_MODEL = MODELS_DIR / "default.npz"
SUPPORTED_FORMAT_VERSIONS = (1,)


def read_weights(path: str | Path) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """(arrays by state_dict name, meta) of a model file; ModelLoadError if unusable."""
    path = Path(path)
    if not path.is_file():
        raise ModelLoadError(
            f"model file {path} does not exist; pass the .npz written by `deepxpalm train` "
            "or leave the path out to use the shipped default"
        )
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile) as e:
        raise ModelLoadError(
            f"model file {path} is not a readable .npz ({e}); retrain it"
        ) from None
    raw = arrays.pop("meta", None)
    if raw is None:
        raise ModelLoadError(f"model file {path} has no 'meta' entry: not written by this project")
    try:
        meta = json.loads(raw.tobytes().decode())
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ModelLoadError(f"model file {path}: its meta entry is not JSON ({e})") from None
    version = meta.get("format_version")
    if version not in SUPPORTED_FORMAT_VERSIONS:
        raise ModelLoadError(
            f"model file {path} has format version {version!r}; this code reads "
            f"{list(SUPPORTED_FORMAT_VERSIONS)}: retrain with `deepxpalm train`"
        )
    return arrays, meta
