"""Foxglove's JSON schemas for the types the recordings and the live view write.

Times as ``{sec, nsec}``, bytes as base64 strings: Foxglove's JSON forms,
with the field names and types of Foxglove's published schemas (the
``foxglove-sdk`` package's descriptors; ``tests/recording/test_foxglove.py``
compares them field by field). They need no Foxglove package to write.
"""

from __future__ import annotations

from typing import Any

_NUM = {"type": "number"}
_U32 = {"type": "integer", "minimum": 0}
_STR = {"type": "string"}
_BOOL = {"type": "boolean"}
_BYTES = {"type": "string", "contentEncoding": "base64"}
_TIME = {
    "type": "object",
    "title": "time",
    "properties": {
        "sec": {"type": "integer", "minimum": 0},
        "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999},
    },
}
_DURATION = {
    "type": "object",
    "title": "duration",
    "properties": {
        "sec": {"type": "integer"},
        "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999},
    },
}


def _obj(title: str, **props: dict[str, Any]) -> dict[str, Any]:
    return {"title": title, "type": "object", "properties": props}


def _arr(items: dict[str, Any]) -> dict[str, Any]:
    return {"type": "array", "items": items}


def _enum(title: str, *names: str) -> dict[str, Any]:
    return {"title": title, "oneOf": [{"title": n, "const": i} for i, n in enumerate(names)]}


_VEC3 = _obj("foxglove.Vector3", x=_NUM, y=_NUM, z=_NUM)
_QUAT = _obj("foxglove.Quaternion", x=_NUM, y=_NUM, z=_NUM, w=_NUM)
_POSE = _obj("foxglove.Pose", position=_VEC3, orientation=_QUAT)
_COLOR = _obj("foxglove.Color", r=_NUM, g=_NUM, b=_NUM, a=_NUM)
_POINT3 = _obj("foxglove.Point3", x=_NUM, y=_NUM, z=_NUM)
_SCENE_ENTITY = _obj(
    "foxglove.SceneEntity",
    timestamp=_TIME,
    frame_id=_STR,
    id=_STR,
    lifetime=_DURATION,
    frame_locked=_BOOL,
    metadata=_arr(_obj("foxglove.KeyValuePair", key=_STR, value=_STR)),
    arrows=_arr(
        _obj(
            "foxglove.ArrowPrimitive",
            pose=_POSE,
            shaft_length=_NUM,
            shaft_diameter=_NUM,
            head_length=_NUM,
            head_diameter=_NUM,
            color=_COLOR,
        )
    ),
    cubes=_arr(_obj("foxglove.CubePrimitive", pose=_POSE, size=_VEC3, color=_COLOR)),
    spheres=_arr(_obj("foxglove.SpherePrimitive", pose=_POSE, size=_VEC3, color=_COLOR)),
    cylinders=_arr(
        _obj(
            "foxglove.CylinderPrimitive",
            pose=_POSE,
            size=_VEC3,
            bottom_scale=_NUM,
            top_scale=_NUM,
            color=_COLOR,
        )
    ),
    lines=_arr(
        _obj(
            "foxglove.LinePrimitive",
            type=_enum("foxglove.LineType", "LINE_STRIP", "LINE_LOOP", "LINE_LIST"),
            pose=_POSE,
            thickness=_NUM,
            scale_invariant=_BOOL,
            points=_arr(_POINT3),
            color=_COLOR,
            colors=_arr(_COLOR),
            indices=_arr(_U32),
        )
    ),
    triangles=_arr(
        _obj(
            "foxglove.TriangleListPrimitive",
            pose=_POSE,
            points=_arr(_POINT3),
            color=_COLOR,
            colors=_arr(_COLOR),
            indices=_arr(_U32),
        )
    ),
    texts=_arr(
        _obj(
            "foxglove.TextPrimitive",
            pose=_POSE,
            billboard=_BOOL,
            font_size=_NUM,
            scale_invariant=_BOOL,
            color=_COLOR,
            text=_STR,
        )
    ),
    models=_arr(
        _obj(
            "foxglove.ModelPrimitive",
            pose=_POSE,
            scale=_VEC3,
            color=_COLOR,
            override_color=_BOOL,
            url=_STR,
            media_type=_STR,
            data=_BYTES,
        )
    ),
)

#: schema name -> Foxglove's JSON Schema of it
SCHEMAS: dict[str, dict[str, Any]] = {
    "foxglove.CompressedImage": _obj(
        "foxglove.CompressedImage", timestamp=_TIME, frame_id=_STR, data=_BYTES, format=_STR
    ),
    "foxglove.RawImage": _obj(
        "foxglove.RawImage",
        timestamp=_TIME,
        frame_id=_STR,
        width=_U32,
        height=_U32,
        encoding=_STR,
        step=_U32,
        data=_BYTES,
    ),
    "foxglove.FrameTransform": _obj(
        "foxglove.FrameTransform",
        timestamp=_TIME,
        parent_frame_id=_STR,
        child_frame_id=_STR,
        translation=_VEC3,
        rotation=_QUAT,
    ),
    "foxglove.SceneUpdate": _obj(
        "foxglove.SceneUpdate",
        deletions=_arr(
            _obj(
                "foxglove.SceneEntityDeletion",
                timestamp=_TIME,
                type=_enum("foxglove.SceneEntityDeletionType", "MATCHING_ID", "ALL"),
                id=_STR,
            )
        ),
        entities=_arr(_SCENE_ENTITY),
    ),
    "foxglove.Log": _obj(
        "foxglove.Log",
        timestamp=_TIME,
        level=_enum("foxglove.LogLevel", "UNKNOWN", "DEBUG", "INFO", "WARNING", "ERROR", "FATAL"),
        message=_STR,
        name=_STR,
        file=_STR,
        line=_U32,
    ),
}
