"""The quarter-car picture for Foxglove's 3D panel (well-known ``foxglove.SceneUpdate``
and ``foxglove.FrameTransform`` messages, JSON form).

Frames: ``world`` (the road surface at z = 0), ``wheel`` (fixed above the road: the rig's
wheel pan does not move in this picture) and ``body``, which sits
:data:`NOMINAL_GAP_M` above the wheel less the measured rattlespace (compression
positive brings the body down).  Drawn: the road (a line), the wheel and the body
(cubes), the actuator (a line between wheel and body, green while the controller drives
the valve, grey passive, red in FAULT), the suspension spring (a zig-zag) and the
measured actuator force as a vertical line from the body centre (up = pushes the body
up, :data:`FORCE_SCALE_M_PER_N` long per newton), and a label with the lifecycle state,
rattlespace and force.  The recording writes one transform and one scene every
:data:`SCENE_PERIOD_NS` of loop time; the live view publishes them at the same period.
"""

from __future__ import annotations

from typing import Any, Final

__all__ = [
    "FORCE_SCALE_M_PER_N",
    "FRAME_TRANSFORM_SCHEMA",
    "NOMINAL_GAP_M",
    "SCENE_PERIOD_NS",
    "SCENE_UPDATE_SCHEMA",
    "body_height_m",
    "scene_messages",
]

#: one picture per 50 ms of loop time (20 Hz): smooth enough to watch, ~1 % of the
#: recording's bytes
SCENE_PERIOD_NS: Final = 50_000_000
#: body bottom to wheel top at zero rattlespace [m] (drawing only)
NOMINAL_GAP_M: Final = 0.30
WHEEL_CENTRE_M: Final = 0.25
WHEEL_SIZE_M: Final = (0.25, 0.25, 0.5)
BODY_SIZE_M: Final = (0.8, 0.8, 0.3)
#: measured force drawn 0.1 m per kN
FORCE_SCALE_M_PER_N: Final = 1e-4

_LIFECYCLE_COLOUR: Final = {
    "ACTIVE": (0.10, 0.70, 0.25, 1.0),
    "FAULT": (0.85, 0.10, 0.10, 1.0),
}
_PASSIVE_COLOUR: Final = (0.55, 0.55, 0.55, 1.0)

_VEC3: Final[dict[str, Any]] = {
    "type": "object",
    "properties": {"x": {"type": "number"}, "y": {"type": "number"}, "z": {"type": "number"}},
    "required": ["x", "y", "z"],
}
_QUAT: Final[dict[str, Any]] = {
    "type": "object",
    "properties": {k: {"type": "number"} for k in ("x", "y", "z", "w")},
    "required": ["x", "y", "z", "w"],
}
_COLOR: Final[dict[str, Any]] = {
    "type": "object",
    "properties": {k: {"type": "number", "minimum": 0, "maximum": 1}
                   for k in ("r", "g", "b", "a")},
    "required": ["r", "g", "b", "a"],
}
_TIME: Final[dict[str, Any]] = {
    "type": "object",
    "properties": {"sec": {"type": "integer", "minimum": 0},
                   "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999}},
    "required": ["sec", "nsec"],
}
_POSE: Final[dict[str, Any]] = {
    "type": "object", "properties": {"position": _VEC3, "orientation": _QUAT},
    "required": ["position", "orientation"],
}
_CUBE: Final[dict[str, Any]] = {
    "type": "object", "properties": {"pose": _POSE, "size": _VEC3, "color": _COLOR},
    "required": ["pose", "size", "color"],
}
_LINE: Final[dict[str, Any]] = {
    "type": "object",
    "properties": {
        "type": {"oneOf": [{"title": "LINE_STRIP", "const": 0},
                           {"title": "LINE_LOOP", "const": 1},
                           {"title": "LINE_LIST", "const": 2}]},
        "pose": _POSE, "thickness": {"type": "number", "minimum": 0},
        "scale_invariant": {"type": "boolean"},
        "points": {"type": "array", "items": _VEC3},
        "color": _COLOR, "colors": {"type": "array", "items": _COLOR},
        "indices": {"type": "array", "items": {"type": "integer", "minimum": 0}},
    },
    "required": ["type", "pose", "thickness", "scale_invariant", "points", "color"],
}
_TEXT: Final[dict[str, Any]] = {
    "type": "object",
    "properties": {"pose": _POSE, "billboard": {"type": "boolean"},
                   "font_size": {"type": "number"}, "scale_invariant": {"type": "boolean"},
                   "color": _COLOR, "text": {"type": "string"}},
    "required": ["pose", "billboard", "font_size", "scale_invariant", "color", "text"],
}
_ANY_ARRAY: Final[dict[str, Any]] = {"type": "array", "maxItems": 0}

#: ``foxglove.SceneUpdate`` (the fields this picture uses; the other primitive lists are
#: always empty)
SCENE_UPDATE_SCHEMA: Final[dict[str, Any]] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "foxglove.SceneUpdate",
    "description": "the quarter car: road, wheel, body, spring, actuator, measured force",
    "type": "object",
    "properties": {
        "deletions": {"type": "array", "maxItems": 0},
        "entities": {"type": "array", "items": {
            "title": "foxglove.SceneEntity",
            "type": "object",
            "properties": {
                "timestamp": _TIME, "frame_id": {"type": "string"}, "id": {"type": "string"},
                "lifetime": _TIME, "frame_locked": {"type": "boolean"},
                "metadata": _ANY_ARRAY, "arrows": _ANY_ARRAY,
                "cubes": {"type": "array", "items": _CUBE}, "spheres": _ANY_ARRAY,
                "cylinders": _ANY_ARRAY, "lines": {"type": "array", "items": _LINE},
                "triangles": _ANY_ARRAY, "texts": {"type": "array", "items": _TEXT},
                "models": _ANY_ARRAY,
            },
            "required": ["timestamp", "frame_id", "id", "lifetime", "frame_locked",
                         "cubes", "lines", "texts"],
        }},
    },
    "required": ["deletions", "entities"],
}

#: ``foxglove.FrameTransform``: ``world`` -> ``body``
FRAME_TRANSFORM_SCHEMA: Final[dict[str, Any]] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "foxglove.FrameTransform",
    "description": "the body frame, moving with the measured rattlespace",
    "type": "object",
    "properties": {
        "timestamp": _TIME, "parent_frame_id": {"type": "string"},
        "child_frame_id": {"type": "string"}, "translation": _VEC3, "rotation": _QUAT,
    },
    "required": ["timestamp", "parent_frame_id", "child_frame_id", "translation",
                 "rotation"],
}


def body_height_m(rattlespace_m: float) -> float:
    """Height of the body frame's origin (its bottom face) above the road [m]."""
    return WHEEL_CENTRE_M + WHEEL_SIZE_M[2] / 2 + NOMINAL_GAP_M - rattlespace_m


def _v(x: float, y: float, z: float) -> dict[str, float]:
    return {"x": x, "y": y, "z": z}


def _c(rgba: tuple[float, float, float, float]) -> dict[str, float]:
    return {"r": rgba[0], "g": rgba[1], "b": rgba[2], "a": rgba[3]}


_IDENTITY: Final = {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}


def _pose(x: float, y: float, z: float) -> dict[str, Any]:
    return {"position": _v(x, y, z), "orientation": dict(_IDENTITY)}


def _line(points: list[tuple[float, float, float]], rgba: tuple[float, float, float, float],
          thickness: float) -> dict[str, Any]:
    return {"type": 0, "pose": _pose(0.0, 0.0, 0.0), "thickness": thickness,
            "scale_invariant": False, "points": [_v(*p) for p in points],
            "color": _c(rgba), "colors": [], "indices": []}


def _entity(stamp: dict[str, int], frame: str, ident: str, *,
            cubes: list[dict[str, Any]] | None = None,
            lines: list[dict[str, Any]] | None = None,
            texts: list[dict[str, Any]] | None = None) -> dict[str, Any]:
    return {"timestamp": stamp, "frame_id": frame, "id": ident,
            "lifetime": {"sec": 0, "nsec": 0}, "frame_locked": True, "metadata": [],
            "arrows": [], "cubes": cubes or [], "spheres": [], "cylinders": [],
            "lines": lines or [], "triangles": [], "texts": texts or [], "models": []}


def _finite(x: Any) -> float:
    try:
        v = float(x)
    except (TypeError, ValueError):
        return 0.0
    return v if v == v and abs(v) < 1e9 else 0.0


def scene_messages(wall_ns: int, rattlespace_m: Any, force_meas_n: Any, lifecycle: str
                   ) -> tuple[dict[str, Any], dict[str, Any]]:
    """(``foxglove.FrameTransform`` world -> body, ``foxglove.SceneUpdate``) for one
    moment.  Non-finite or missing readings are drawn as zero."""
    rs = _finite(rattlespace_m)
    force = _finite(force_meas_n)
    sec, nsec = divmod(max(int(wall_ns), 0), 1_000_000_000)
    stamp = {"sec": sec, "nsec": nsec}
    z_body = body_height_m(rs)
    transform = {"timestamp": stamp, "parent_frame_id": "world", "child_frame_id": "body",
                 "translation": _v(0.0, 0.0, z_body), "rotation": dict(_IDENTITY)}
    wheel_top = WHEEL_CENTRE_M + WHEEL_SIZE_M[2] / 2
    colour = _LIFECYCLE_COLOUR.get(lifecycle, _PASSIVE_COLOUR)
    n_coils = 8
    spring = [(-0.25 + (0.06 if i % 2 else -0.06) * (0 < i < 2 * n_coils), 0.0,
               wheel_top + (z_body - wheel_top) * i / (2 * n_coils))
              for i in range(2 * n_coils + 1)]
    force_len = force * FORCE_SCALE_M_PER_N
    body_mid = z_body + BODY_SIZE_M[2] / 2
    entities = [
        _entity(stamp, "world", "road",
                lines=[_line([(-1.0, 0.0, 0.0), (1.0, 0.0, 0.0)], (0.2, 0.2, 0.2, 1.0),
                             0.02)]),
        _entity(stamp, "world", "wheel",
                cubes=[{"pose": _pose(0.0, 0.0, WHEEL_CENTRE_M), "size": _v(*WHEEL_SIZE_M),
                        "color": _c((0.1, 0.1, 0.1, 1.0))}]),
        _entity(stamp, "body", "body",
                cubes=[{"pose": _pose(0.0, 0.0, BODY_SIZE_M[2] / 2),
                        "size": _v(*BODY_SIZE_M), "color": _c((0.25, 0.45, 0.75, 0.8))}],
                texts=[{"pose": _pose(0.0, 0.0, BODY_SIZE_M[2] + 0.1), "billboard": True,
                        "font_size": 14.0, "scale_invariant": True,
                        "color": _c((1.0, 1.0, 1.0, 1.0)),
                        "text": f"{lifecycle}  rattlespace {rs * 1e3:+.1f} mm  "
                                f"force {force:+.0f} N"}]),
        _entity(stamp, "world", "spring", lines=[_line(spring, (0.6, 0.6, 0.2, 1.0), 0.01)]),
        _entity(stamp, "world", "actuator",
                lines=[_line([(0.2, 0.0, wheel_top), (0.2, 0.0, z_body)], colour, 0.06)]),
        _entity(stamp, "world", "force",
                lines=[_line([(0.0, -0.45, body_mid), (0.0, -0.45, body_mid + force_len)],
                             (0.95, 0.55, 0.1, 1.0), 0.03)]),
    ]
    return transform, {"deletions": [], "entities": entities}
