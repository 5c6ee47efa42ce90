"""``/scene``: each tick as a ``foxglove.SceneUpdate``, for Foxglove's 3-D panel.

Per tick: every agent (a sphere, red static / green mobile as in the report's
figures, gray when not live, with its id), the links of the tick (a line
list), the target's truth (a black sphere and its last ``TRAIL`` ticks), and
each agent's estimate of the target: a small sphere in the agent's colour
and its 2-sigma covariance ellipse (a flat sphere along P's eigenvectors).
The schema (``SCHEMA``) describes the part of Foxglove's SceneUpdate these
messages use, under Foxglove's schema name, so the panel renders it without
plugins. Coordinates are the scenario's, z = 0, frame "world". The recorder writes
``/scene`` when the run ends (a run killed before has every other channel).
"""
from __future__ import annotations

import math

import numpy as np

TOPIC = "/scene"
FRAME = "world"
TRAIL = 20
NAME = "foxglove.SceneUpdate"

_N = {"type": "number"}
_XYZ = {"type": "object", "properties": {"x": _N, "y": _N, "z": _N}, "required": ["x", "y", "z"]}
_QUAT = {"type": "object", "properties": {"x": _N, "y": _N, "z": _N, "w": _N}, "required": ["x", "y", "z", "w"]}
_POSE = {"type": "object", "properties": {"position": _XYZ, "orientation": _QUAT}, "required": ["position", "orientation"]}
_RGBA = {"type": "object", "properties": {"r": _N, "g": _N, "b": _N, "a": _N}, "required": ["r", "g", "b", "a"]}
_TIME = {"type": "object", "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}}
_SPHERE = {"type": "object", "properties": {"pose": _POSE, "size": _XYZ, "color": _RGBA}}
_LINE = {"type": "object", "properties": {
    "type": {"type": "integer", "description": "0 line strip, 1 line loop, 2 line list"}, "pose": _POSE,
    "thickness": _N, "scale_invariant": {"type": "boolean"}, "points": {"type": "array", "items": _XYZ},
    "color": _RGBA, "colors": {"type": "array", "items": _RGBA},
    "indices": {"type": "array", "items": {"type": "integer"}}}}
_TEXT = {"type": "object", "properties": {"pose": _POSE, "billboard": {"type": "boolean"}, "font_size": _N,
                                          "scale_invariant": {"type": "boolean"}, "color": _RGBA,
                                          "text": {"type": "string"}}}
_EMPTY = {"type": "array", "items": {"type": "object"}}
SCHEMA = {
    "title": NAME, "description": "An update to the entities displayed in a 3D scene (the fields diskf-mesh uses)",
    "type": "object", "properties": {
        "deletions": _EMPTY,
        "entities": {"type": "array", "items": {"type": "object", "properties": {
            "timestamp": _TIME, "frame_id": {"type": "string"}, "id": {"type": "string"}, "lifetime": _TIME,
            "frame_locked": {"type": "boolean"}, "metadata": _EMPTY, "arrows": _EMPTY, "cubes": _EMPTY,
            "spheres": {"type": "array", "items": _SPHERE}, "cylinders": _EMPTY,
            "lines": {"type": "array", "items": _LINE}, "triangles": _EMPTY,
            "texts": {"type": "array", "items": _TEXT}, "models": _EMPTY}}}}}

_IDENTITY = {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}
_BLACK = {"r": 0.0, "g": 0.0, "b": 0.0, "a": 1.0}
_BLUE = {"r": 0.12, "g": 0.47, "b": 0.71, "a": 0.8}
_STATIC = {"r": 0.84, "g": 0.15, "b": 0.16, "a": 1.0}
_MOBILE = {"r": 0.17, "g": 0.63, "b": 0.17, "a": 1.0}
_GONE = {"r": 0.6, "g": 0.6, "b": 0.6, "a": 0.6}


# matplotlib's tab10 without its gray (the truth is black): the agents' colours here and in the figures
AGENT_COLORS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#bcbd22", "#17becf")


def agent_color(j: int) -> tuple:
    """(r, g, b) in 0..1 of the j-th agent (colours repeat after nine)."""
    h = AGENT_COLORS[j % len(AGENT_COLORS)]
    return tuple(int(h[i:i + 2], 16) / 255 for i in (1, 3, 5))


def _xyz(p) -> dict:
    return {"x": float(p[0]), "y": float(p[1]), "z": 0.0}


def _pose(p, q=_IDENTITY) -> dict:
    return {"position": _xyz(p), "orientation": q}


def _entity(id_: str, stamp: dict, **prims) -> dict:
    e = {"timestamp": stamp, "frame_id": FRAME, "id": id_, "lifetime": {"sec": 0, "nsec": 0}, "frame_locked": False,
         "metadata": [], "arrows": [], "cubes": [], "spheres": [], "cylinders": [], "lines": [], "triangles": [],
         "texts": [], "models": []}
    e.update(prims)
    return e


def ellipse(P2: np.ndarray, sigmas: float = 2.0) -> tuple:
    """(size {x, y, z}, orientation quaternion) of the ``sigmas`` ellipse of a 2 x 2 covariance."""
    (a, b0), (b1, c) = P2
    b = 0.5 * (b0 + b1)
    mid, rad = 0.5 * (a + c), math.hypot(0.5 * (a - c), b)
    l1, l2 = max(mid + rad, 0.0), max(mid - rad, 0.0)
    theta = 0.5 * math.atan2(2.0 * b, a - c)
    size = {"x": 2 * sigmas * math.sqrt(l1), "y": 2 * sigmas * math.sqrt(l2), "z": 0.1}
    return size, {"x": 0.0, "y": 0.0, "z": math.sin(theta / 2), "w": math.cos(theta / 2)}


def scene_update(k: int, stamp_ns: int, ids, positions, mobile, live, edges, truth_trail, estimates,
                 colors, radius: float) -> dict:
    """The SceneUpdate of tick k. ``truth_trail``: (T, 2) target positions up
    to tick k; ``estimates``: [(agent id, position (2,), P of the position (2, 2))];
    ``colors``: agent id -> (r, g, b); ``radius``: the agents' sphere radius."""
    stamp = {"sec": stamp_ns // 1_000_000_000, "nsec": stamp_ns % 1_000_000_000}
    where = {i: j for j, i in enumerate(ids)}
    size = {"x": 2 * radius, "y": 2 * radius, "z": 2 * radius}
    agents = _entity("agents", stamp, spheres=[
        {"pose": _pose(positions[j]), "size": size,
         "color": (_MOBILE if mobile[j] else _STATIC) if i in live else _GONE} for j, i in enumerate(ids)],
        texts=[{"pose": _pose(positions[j] + radius), "billboard": True, "font_size": 14.0, "scale_invariant": True,
                "color": _BLACK, "text": str(i)} for j, i in enumerate(ids)])
    links = _entity("links", stamp, lines=[{
        "type": 2, "pose": _pose((0.0, 0.0)), "thickness": 2.0, "scale_invariant": True,
        "points": [_xyz(positions[where[i]]) for e in edges for i in e], "color": _BLUE, "colors": [],
        "indices": []}])
    truth = _entity("truth", stamp, spheres=[{"pose": _pose(truth_trail[-1]), "size": size, "color": _BLACK}],
                    lines=[{"type": 0, "pose": _pose((0.0, 0.0)), "thickness": 1.0, "scale_invariant": True,
                            "points": [_xyz(p) for p in truth_trail[-TRAIL:]], "color": _BLACK, "colors": [],
                            "indices": []}])
    spheres = []
    for i, p, P2 in estimates:
        r, g, b = colors[i]
        spheres.append({"pose": _pose(p), "size": {k: 0.6 * v for k, v in size.items()},
                        "color": {"r": r, "g": g, "b": b, "a": 1.0}})
        esize, q = ellipse(P2)
        spheres.append({"pose": _pose(p, q), "size": esize, "color": {"r": r, "g": g, "b": b, "a": 0.15}})
    est = _entity("estimates", stamp, spheres=spheres)
    return {"deletions": [], "entities": [agents, links, truth, est]}
