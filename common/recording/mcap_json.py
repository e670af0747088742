"""The JSON a recording's MCAP channels carry, and the JSON Schema beside it.

Messages are JSON with an inferred JSON Schema, because Foxglove plots JSON
channels without any plugin. NumPy arrays become nested lists and bytes
become base64 strings; the schema marks them (``x-numpy-dtype``,
``contentEncoding: base64``) so a reader gives back the same arrays and
bytes (``restore``). Shared by the writer (``common.recording.mcap_recorder``) and the
reader (``common.recording.mcap_reader``).
"""

from __future__ import annotations

import base64
import dataclasses
import logging
import math
from typing import Any

import numpy as np
from mcap.writer import CompressionType

from common.errors import DeepXPalmError

log = logging.getLogger(__name__)

MESSAGE_ENCODING = "json"
SCHEMA_ENCODING = "jsonschema"
SCHEMA_PREFIX = "deepxpalm/"
LIBRARY = "deepxpalm McapRecorder"
ENC_KEY = "_enc"  # per-message encodings, only where the channel's schema does not say them
NONFINITE_KEY = "_nonfinite"  # paths of NaN/inf values written as null (a bug to look at)
VIEW_OF_KEY = "deepxpalm.view_of"  # channel metadata: a Foxglove view, and of which channel
COMPRESSION = {
    "zstd": CompressionType.ZSTD,
    "lz4": CompressionType.LZ4,
    "none": CompressionType.NONE,
}


class RecordingError(DeepXPalmError):
    """A recording cannot be opened or read; the message names the file."""


def to_json(value: Any, path: str, encs: dict[str, str], nonfinite: list[str]) -> Any:
    """A JSON-ready copy of ``value``; ``encs`` collects where bytes and arrays were."""
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, (int, np.integer)) and not isinstance(value, np.bool_):
        return int(value)
    if isinstance(value, (float, np.floating)):
        v = float(value)
        if math.isfinite(v):
            return v
        nonfinite.append(path)
        return None
    if isinstance(value, np.bool_):
        return bool(value)
    if isinstance(value, (bytes, bytearray, memoryview)):
        encs[path] = "base64"
        return base64.b64encode(bytes(value)).decode("ascii")
    if isinstance(value, np.ndarray):
        encs[path] = value.dtype.str
        if value.dtype.kind == "f" and not np.isfinite(value).all():
            nonfinite.append(path)
            out = value.astype(object)
            out[~np.isfinite(value)] = None
            return out.tolist()
        return value.tolist()
    if isinstance(value, dict):
        return {
            str(k): to_json(v, f"{path}.{k}" if path else str(k), encs, nonfinite)
            for k, v in value.items()
        }
    if isinstance(value, (list, tuple)):
        return [to_json(v, f"{path}[]", {}, nonfinite) for v in value]
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return to_json(dataclasses.asdict(value), path, encs, nonfinite)
    return str(value)


def nan_for_none(value: Any) -> Any:
    if isinstance(value, list):
        return [nan_for_none(v) for v in value]
    return math.nan if value is None else value


def schema_of(value: Any, path: str, encs: dict[str, str]) -> dict[str, Any] | None:
    """JSON Schema of one converted value; None where nothing can be said (a null)."""
    enc = encs.get(path)
    if value is None:
        return None
    if isinstance(value, bool):
        return {"type": "boolean"}
    if isinstance(value, int):
        return {"type": "integer"}
    if isinstance(value, float):
        return {"type": "number"}
    if isinstance(value, str):
        if enc == "base64":
            return {"type": "string", "contentEncoding": "base64"}
        return {"type": "string"}
    if isinstance(value, list):
        out: dict[str, Any] = {"type": "array"}
        item = next((v for v in value if v is not None), None)
        item_schema = schema_of(item, f"{path}[]", {}) if item is not None else None
        if item_schema is not None:
            out["items"] = item_schema
        if enc is not None:
            out["x-numpy-dtype"] = enc
        return out
    if isinstance(value, dict):
        props = {}
        for k, v in value.items():
            s = schema_of(v, f"{path}.{k}" if path else k, encs)
            if s is not None:
                props[k] = s
        return {"type": "object", "properties": props}
    return None


def encodings_in_schema(schema: dict[str, Any], path: str = "") -> dict[str, str]:
    """Where a channel's schema says bytes (base64) and arrays (their dtype) are."""
    out: dict[str, str] = {}
    if schema.get("contentEncoding") == "base64":
        out[path] = "base64"
    if "x-numpy-dtype" in schema:
        out[path] = schema["x-numpy-dtype"]
    for k, sub in schema.get("properties", {}).items():
        out.update(encodings_in_schema(sub, f"{path}.{k}" if path else k))
    return out


def restore(record: dict[str, Any], encs: dict[str, str]) -> None:
    """Turn base64 strings and nested lists back into bytes and arrays, in place."""
    for path, enc in encs.items():
        *parents, leaf = path.split(".")
        node: Any = record
        for key in parents:
            node = node.get(key) if isinstance(node, dict) else None
        if not isinstance(node, dict) or node.get(leaf) is None:
            continue
        value = node[leaf]
        try:
            if enc == "base64":
                node[leaf] = base64.b64decode(value)
            else:
                dtype = np.dtype(enc)
                if dtype.kind == "f":
                    value = nan_for_none(value)
                node[leaf] = np.asarray(value, dtype=dtype)
        except (ValueError, TypeError):
            log.debug("cannot restore %s as %s; left as is", path, enc)


def decoded_fields(wire: bytes) -> dict[str, Any]:
    """The fields of a wire message, for plotting; the codec's own validation applies."""
    from common.wire.codec import DecodeError, decode  # the codec is only needed for "wire" records

    try:
        msg = decode(wire)
    except DecodeError as e:
        return {"error": f"{type(e).__name__}: {e}"}
    out: dict[str, Any] = {"type": type(msg).TYPE}
    for f in dataclasses.fields(msg):
        out[f.name] = getattr(msg, f.name)
    return out
