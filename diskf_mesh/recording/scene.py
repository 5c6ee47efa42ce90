"""``/scene``: each tick as a ``foxglove.SceneUpdate``, for Foxglove's 3-D panel.

Per tick: every agent (a sphere, red static / green mobile as in the report's
figures, gray when not live, with its id), the links of the tick (a line
list), the target's truth (a black sphere and its last ``TRAIL`` ticks), and
each agent's estimate of the target: a small sphere in the agent's colour
and its 2-sigma covariance ellipse (a flat sphere along P's eigenvectors).
The messages are foxglove-sdk's typed ``foxglove.SceneUpdate``, encoded as
protobuf with the SDK's schema (``schema``), so the panel renders them
without plugins, in a recording and on the live server alike. Coordinates are the scenario's, z = 0, frame "world". The recorder writes
``/scene`` when the run ends (a run killed before has every other channel).
"""
from __future__ import annotations

import math

import numpy as np

TOPIC = "/scene"
FRAME = "world"
TRAIL = 20
ENCODING = "protobuf"


def schema():
    """(name, encoding, data) of ``/scene``'s schema: foxglove-sdk's SceneUpdate."""
    from foxglove.messages import SceneUpdate  # foxglove-sdk only where a scene is made (not in the world)

    sch = SceneUpdate.get_schema()
    return sch.name, sch.encoding, bytes(sch.data)


# (r, g, b, a)
_BLACK = (0.0, 0.0, 0.0, 1.0)
_BLUE = (0.12, 0.47, 0.71, 0.8)
_STATIC = (0.84, 0.15, 0.16, 1.0)
_MOBILE = (0.17, 0.63, 0.17, 1.0)
_GONE = (0.6, 0.6, 0.6, 0.6)


# matplotlib's tab10 without its gray (the truth is black): the agents' colours here and in the figures
AGENT_COLORS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#bcbd22", "#17becf")


def agent_color(j: int) -> tuple:
    """(r, g, b) in 0..1 of the j-th agent (colours repeat after nine)."""
    h = AGENT_COLORS[j % len(AGENT_COLORS)]
    return tuple(int(h[i:i + 2], 16) / 255 for i in (1, 3, 5))


def ellipse(P2: np.ndarray, sigmas: float = 2.0) -> tuple:
    """(size (x, y, z), orientation quaternion (x, y, z, w)) of the ``sigmas`` ellipse of a 2 x 2 covariance."""
    (a, b0), (b1, c) = P2
    b = 0.5 * (b0 + b1)
    mid, rad = 0.5 * (a + c), math.hypot(0.5 * (a - c), b)
    l1, l2 = max(mid + rad, 0.0), max(mid - rad, 0.0)
    theta = 0.5 * math.atan2(2.0 * b, a - c)
    return (2 * sigmas * math.sqrt(l1), 2 * sigmas * math.sqrt(l2), 0.1), (0.0, 0.0, math.sin(theta / 2),
                                                                           math.cos(theta / 2))


def scene_update(k: int, stamp_ns: int, ids, positions, mobile, live, edges, truth_trail, estimates,
                 colors, radius: float):
    """The SceneUpdate of tick k. ``truth_trail``: (T, 2) target positions up
    to tick k; ``estimates``: [(agent id, position (2,), P of the position (2, 2))];
    ``colors``: agent id -> (r, g, b); ``radius``: the agents' sphere radius.
    Returns a ``foxglove.messages.SceneUpdate``."""
    from foxglove.messages import (Color, LinePrimitive, LinePrimitiveLineType, Point3, Pose, Quaternion,
                                   SceneEntity, SceneUpdate, SpherePrimitive, TextPrimitive, Timestamp, Vector3)

    xyz = lambda p: Point3(x=float(p[0]), y=float(p[1]), z=0.0)  # noqa: E731
    rgba = lambda c, a=None: Color(r=c[0], g=c[1], b=c[2], a=c[3] if a is None else a)  # noqa: E731

    def pose(p, q=(0.0, 0.0, 0.0, 1.0)):
        return Pose(position=Vector3(x=float(p[0]), y=float(p[1]), z=0.0),
                    orientation=Quaternion(x=q[0], y=q[1], z=q[2], w=q[3]))

    stamp = Timestamp(stamp_ns // 1_000_000_000, stamp_ns % 1_000_000_000)
    where = {i: j for j, i in enumerate(ids)}
    size = Vector3(x=2 * radius, y=2 * radius, z=2 * radius)
    small = Vector3(x=1.2 * radius, y=1.2 * radius, z=1.2 * radius)
    entity = lambda id_, **prims: SceneEntity(timestamp=stamp, frame_id=FRAME, id=id_, **prims)  # noqa: E731
    agents = entity("agents", spheres=[
        SpherePrimitive(pose=pose(positions[j]), size=size,
                        color=rgba((_MOBILE if mobile[j] else _STATIC) if i in live else _GONE))
        for j, i in enumerate(ids)],
        texts=[TextPrimitive(pose=pose(positions[j] + radius), billboard=True, font_size=14.0, scale_invariant=True,
                             color=rgba(_BLACK), text=str(i)) for j, i in enumerate(ids)])
    links = entity("links", lines=[LinePrimitive(
        type=LinePrimitiveLineType.LineList, pose=pose((0.0, 0.0)), thickness=2.0, scale_invariant=True,
        points=[xyz(positions[where[i]]) for e in edges for i in e], color=rgba(_BLUE))])
    truth = entity("truth", spheres=[SpherePrimitive(pose=pose(truth_trail[-1]), size=size, color=rgba(_BLACK))],
                   lines=[LinePrimitive(type=LinePrimitiveLineType.LineStrip, pose=pose((0.0, 0.0)), thickness=1.0,
                                        scale_invariant=True, points=[xyz(p) for p in truth_trail[-TRAIL:]],
                                        color=rgba(_BLACK))])
    spheres = []
    for i, p, P2 in estimates:
        spheres.append(SpherePrimitive(pose=pose(p), size=small, color=rgba(colors[i], 1.0)))
        esize, q = ellipse(P2)
        spheres.append(SpherePrimitive(pose=pose(p, q), size=Vector3(x=esize[0], y=esize[1], z=esize[2]),
                                       color=rgba(colors[i], 0.15)))
    return SceneUpdate(entities=[agents, links, truth, entity("estimates", spheres=spheres)])
