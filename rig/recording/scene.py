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

import json
from typing import Any, Final

__all__ = [
    "FORCE_SCALE_M_PER_N",
    "FRAME_TRANSFORM_SCHEMA",
    "NOMINAL_GAP_M",
    "SCENE_PERIOD_NS",
    "SCENE_UPDATE_SCHEMA",
    "body_height_m",
    "next_scene_ns",
    "scene_json",
    "scene_messages",
]

#: one picture per 50 ms of loop time (20 Hz): smooth enough to watch, ~1 % of the
#: recording's bytes
SCENE_PERIOD_NS: Final = 50_000_000
#: body bottom to wheel top at zero rattlespace [m] (drawing only)
NOMINAL_GAP_M: Final = 0.30
WHEEL_CENTRE_M: Final = 0.25
WHEEL_SIZE_M: Final = (0.5, 0.25, 0.5)     # side view: diameter along x
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
_POSE_COLOR: Final[dict[str, Any]] = {
    "type": "object", "properties": {"pose": _POSE, "color": _COLOR},
}


def _empty(items: dict[str, Any]) -> dict[str, Any]:
    """A primitive list this picture never fills: always empty, yet with its ``items``
    (the Foxglove apps' schema converter needs a type for every array)."""
    return {"type": "array", "items": items, "maxItems": 0}


#: the items of the always-empty lists, as in the well-known schemas (the fields that
#: place and colour them; the lists stay empty)
_DELETION: Final[dict[str, Any]] = {
    "title": "foxglove.SceneEntityDeletion", "type": "object",
    "properties": {"timestamp": _TIME,
                   "type": {"oneOf": [{"title": "MATCHING_ID", "const": 0},
                                      {"title": "ALL", "const": 1}]},
                   "id": {"type": "string"}},
}
_KEY_VALUE: Final[dict[str, Any]] = {
    "title": "foxglove.KeyValuePair", "type": "object",
    "properties": {"key": {"type": "string"}, "value": {"type": "string"}},
}
_ARROW: Final[dict[str, Any]] = {
    **_POSE_COLOR, "title": "foxglove.ArrowPrimitive",
    "properties": {**_POSE_COLOR["properties"],
                   **{k: {"type": "number", "minimum": 0} for k in (
                       "shaft_length", "shaft_diameter", "head_length", "head_diameter")}},
}
_SPHERE: Final[dict[str, Any]] = {
    **_POSE_COLOR, "title": "foxglove.SpherePrimitive",
    "properties": {**_POSE_COLOR["properties"], "size": _VEC3},
}
_CYLINDER: Final[dict[str, Any]] = {
    **_POSE_COLOR, "title": "foxglove.CylinderPrimitive",
    "properties": {**_POSE_COLOR["properties"], "size": _VEC3,
                   "bottom_scale": {"type": "number"}, "top_scale": {"type": "number"}},
}
_TRIANGLES: Final[dict[str, Any]] = {
    **_POSE_COLOR, "title": "foxglove.TriangleListPrimitive",
    "properties": {**_POSE_COLOR["properties"],
                   "points": {"type": "array", "items": _VEC3},
                   "colors": {"type": "array", "items": _COLOR},
                   "indices": {"type": "array", "items": {"type": "integer", "minimum": 0}}},
}
_MODEL: Final[dict[str, Any]] = {
    **_POSE_COLOR, "title": "foxglove.ModelPrimitive",
    "properties": {**_POSE_COLOR["properties"], "scale": _VEC3,
                   "override_color": {"type": "boolean"}, "url": {"type": "string"},
                   "media_type": {"type": "string"},
                   "data": {"type": "string", "contentEncoding": "base64"}},
}

#: ``foxglove.SceneUpdate`` (the fields this picture uses; the other primitive lists are
#: always empty)
SCENE_UPDATE_SCHEMA: Final[dict[str, Any]] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "foxglove.SceneUpdate",
    "description": "the quarter car: road, wheel, body, spring, actuator, measured force",
    "type": "object",
    "properties": {
        "deletions": _empty(_DELETION),
        "entities": {"type": "array", "items": {
            "title": "foxglove.SceneEntity",
            "type": "object",
            "properties": {
                "timestamp": _TIME, "frame_id": {"type": "string"}, "id": {"type": "string"},
                "lifetime": _TIME, "frame_locked": {"type": "boolean"},
                "metadata": _empty(_KEY_VALUE), "arrows": _empty(_ARROW),
                "cubes": {"type": "array", "items": _CUBE}, "spheres": _empty(_SPHERE),
                "cylinders": _empty(_CYLINDER), "lines": {"type": "array", "items": _LINE},
                "triangles": _empty(_TRIANGLES),
                "texts": {"type": "array", "items": _TEXT}, "models": _empty(_MODEL),
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


def next_scene_ns(deadline_ns: int | None, t_ns: int) -> int:
    """The loop time of the next picture after one drawn at the tick of ``t_ns`` that was
    due at ``deadline_ns`` (None: the first): absolute deadlines, every
    :data:`SCENE_PERIOD_NS`, so the lateness of the tick that draws one does not stretch
    the period (counted from the tick, 20 Hz became ~18 Hz live); after a gap of more
    than a period the grid starts again from ``t_ns``."""
    if deadline_ns is None or t_ns - deadline_ns >= SCENE_PERIOD_NS:
        return t_ns + SCENE_PERIOD_NS
    return deadline_ns + SCENE_PERIOD_NS


def body_height_m(rattlespace_m: float) -> float:
    """Height of the body frame's origin (its bottom face) above the road [m]."""
    return WHEEL_CENTRE_M + WHEEL_SIZE_M[2] / 2 + NOMINAL_GAP_M - rattlespace_m


def _finite(x: Any) -> float:
    try:
        v = float(x)
    except (TypeError, ValueError):
        return 0.0
    return v if v == v and abs(v) < 1e9 else 0.0


# The picture is written as JSON text from fragments made once (a few tens of
# microseconds per picture instead of ~0.3 ms of dict building and json.dumps, which
# held the GIL against the control loop).  :func:`scene_messages` parses it back.

def _num(v: float) -> str:
    return f"{v:.6g}"


def _vec(x: float, y: float, z: float) -> str:
    return f'{{"x":{_num(x)},"y":{_num(y)},"z":{_num(z)}}}'


def _colour(rgba: tuple[float, float, float, float]) -> str:
    r, g, b, a = rgba
    return f'{{"r":{_num(r)},"g":{_num(g)},"b":{_num(b)},"a":{_num(a)}}}'


_IDENTITY_JSON: Final = '{"x":0,"y":0,"z":0,"w":1}'


def _pose_json(x: float, y: float, z: float) -> str:
    return f'{{"position":{_vec(x, y, z)},"orientation":{_IDENTITY_JSON}}}'


_ORIGIN_POSE: Final = _pose_json(0.0, 0.0, 0.0)


def _line_json(points: str, colour: str, thickness: float) -> str:
    return (f'{{"type":0,"pose":{_ORIGIN_POSE},"thickness":{_num(thickness)},'
            f'"scale_invariant":false,"points":[{points}],"color":{colour},"colors":[],'
            '"indices":[]}')


def _cube_json(x: float, y: float, z: float, size: tuple[float, float, float],
               rgba: tuple[float, float, float, float]) -> str:
    return f'{{"pose":{_pose_json(x, y, z)},"size":{_vec(*size)},"color":{_colour(rgba)}}}'


def _entity_json(stamp: str, frame: str, ident: str, cubes: str = "", lines: str = "",
                 texts: str = "") -> str:
    return (f'{{"timestamp":{stamp},"frame_id":"{frame}","id":"{ident}",'
            '"lifetime":{"sec":0,"nsec":0},"frame_locked":true,"metadata":[],"arrows":[],'
            f'"cubes":[{cubes}],"spheres":[],"cylinders":[],"lines":[{lines}],'
            f'"triangles":[],"texts":[{texts}],"models":[]}}')


_WHEEL_TOP: Final = WHEEL_CENTRE_M + WHEEL_SIZE_M[2] / 2
_ROAD_LINE: Final = _line_json(f"{_vec(-1.0, 0.0, 0.0)},{_vec(1.0, 0.0, 0.0)}",
                               _colour((0.2, 0.2, 0.2, 1.0)), 0.02)
_WHEEL_CUBE: Final = _cube_json(0.0, 0.0, WHEEL_CENTRE_M, WHEEL_SIZE_M, (0.1, 0.1, 0.1, 1.0))
_BODY_CUBE: Final = _cube_json(0.0, 0.0, BODY_SIZE_M[2] / 2, BODY_SIZE_M,
                               (0.25, 0.45, 0.75, 0.8))
_TEXT_HEAD: Final = (f'{{"pose":{_pose_json(0.0, 0.0, BODY_SIZE_M[2] + 0.1)},'
                     '"billboard":true,"font_size":14,"scale_invariant":true,'
                     f'"color":{_colour((1.0, 1.0, 1.0, 1.0))},"text":')
_SPRING_COLOUR: Final = _colour((0.6, 0.6, 0.2, 1.0))
_FORCE_COLOUR: Final = _colour((0.95, 0.55, 0.1, 1.0))
_ACTUATOR_COLOURS: Final = {k: _colour(v) for k, v in _LIFECYCLE_COLOUR.items()}
_PASSIVE_JSON: Final = _colour(_PASSIVE_COLOUR)
_N_COILS: Final = 8
#: the spring's zig-zag: (x, fraction of the wheel-to-body height)
_SPRING_SHAPE: Final = tuple(
    (-0.25 + (0.06 if i % 2 else -0.06) * (0 < i < 2 * _N_COILS), i / (2 * _N_COILS))
    for i in range(2 * _N_COILS + 1))


def scene_json(wall_ns: int, rattlespace_m: Any, force_meas_n: Any, lifecycle: str
               ) -> tuple[bytes, bytes]:
    """(``foxglove.FrameTransform`` world -> body, ``foxglove.SceneUpdate``) for one
    moment, as JSON (UTF-8).  Non-finite or missing readings are drawn as zero."""
    rs = _finite(rattlespace_m)
    force = _finite(force_meas_n)
    sec, nsec = divmod(max(int(wall_ns), 0), 1_000_000_000)
    stamp = f'{{"sec":{sec},"nsec":{nsec}}}'
    z_body = body_height_m(rs)
    transform = (f'{{"timestamp":{stamp},"parent_frame_id":"world","child_frame_id":"body",'
                 f'"translation":{_vec(0.0, 0.0, z_body)},"rotation":{_IDENTITY_JSON}}}')
    span = z_body - _WHEEL_TOP
    spring = ",".join(_vec(x, 0.0, _WHEEL_TOP + span * f) for x, f in _SPRING_SHAPE)
    body_mid = z_body + BODY_SIZE_M[2] / 2
    force_top = body_mid + force * FORCE_SCALE_M_PER_N
    label = json.dumps(f"{lifecycle}  rattlespace {rs * 1e3:+.1f} mm  force {force:+.0f} N")
    entities = ",".join((
        _entity_json(stamp, "world", "road", lines=_ROAD_LINE),
        _entity_json(stamp, "world", "wheel", cubes=_WHEEL_CUBE),
        _entity_json(stamp, "body", "body", cubes=_BODY_CUBE,
                     texts=f"{_TEXT_HEAD}{label}}}"),
        _entity_json(stamp, "world", "spring",
                     lines=_line_json(spring, _SPRING_COLOUR, 0.01)),
        _entity_json(stamp, "world", "actuator", lines=_line_json(
            f"{_vec(0.2, 0.0, _WHEEL_TOP)},{_vec(0.2, 0.0, z_body)}",
            _ACTUATOR_COLOURS.get(lifecycle, _PASSIVE_JSON), 0.06)),
        _entity_json(stamp, "world", "force", lines=_line_json(
            f"{_vec(0.0, -0.45, body_mid)},{_vec(0.0, -0.45, force_top)}",
            _FORCE_COLOUR, 0.03)),
    ))
    return transform.encode(), f'{{"deletions":[],"entities":[{entities}]}}'.encode()


def scene_messages(wall_ns: int, rattlespace_m: Any, force_meas_n: Any, lifecycle: str
                   ) -> tuple[dict[str, Any], dict[str, Any]]:
    """:func:`scene_json` as Python objects."""
    tf, scene = scene_json(wall_ns, rattlespace_m, force_meas_n, lifecycle)
    return json.loads(tf), json.loads(scene)
