"""The lights of a house, placed from what it has (pure numpy, no GL).

Every room (``Instance.room_id``; None groups the instances of no room) gets:

- one **point light per lamp** (NYU40 ``lamp``, or a label naming a lamp, light or
  chandelier), outside its shade, where the light comes out: ``light_min_distance`` below
  the bottom centre of a hanging lamp (one whose bottom is above the middle of its room's
  height), as far above the top centre of a standing one (floor and table lamps) (inside,
  the shade would hide it from the path tracer; nearer, the shade's light would swamp the
  path tracer's samples);
- one **spot light per window** (NYU40 ``window``): at the window's centre, pointing into
  the room (from the window towards the centre of the room's bounds, kept horizontal and
  tilted 30° down), a wide cone standing in for the sky light a window lets in;
- and, as the documented **fallback** for a room that has no lamp, one point light
  ``light_below_ceiling`` under the centre of the top of the room's bounds (no lower than
  their middle height).

Intensities are set so that a surface facing a light from the farthest corner of its
room's bounds receives ``light`` (the fallback; the room's lamps share it) or
``window_light`` (each window) times its base colour: the light is as strong in a big room
as in a small one, and in a room of many lamps as in one of a single lamp.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..conventions import NYU40_IDS

if TYPE_CHECKING:
    from ..houses.model import House
    from .raster import RenderConfig

#: labels (the source's own class names) of lights that are not NYU40 ``lamp``
LAMP_LABEL = re.compile(r"lamp|light|chandelier|sconce", re.IGNORECASE)
#: half-angle of a window's cone of light, radians
WINDOW_CONE = np.radians(70.0)
#: a window's light points this far below horizontal, radians
WINDOW_TILT = np.radians(30.0)


@dataclass(frozen=True)
class Light:
    """One light of a room.

    kind      : "point" or "spot"
    room      : the room it lights (``Instance.room_id``)
    position  : (3,) float64   world, metres
    direction : (3,) float64   unit, where a spot light points (None for point lights)
    intensity : float          irradiance it gives at 1 m facing it (before the cone)
    source    : what placed it: "lamp", "window" or "fallback"
    """

    kind: str
    room: str | None
    position: np.ndarray
    direction: np.ndarray | None
    intensity: float
    source: str


def room_bounds(house: "House") -> dict[str | None, np.ndarray]:
    """(2, 3) float64 bounds of each room's instances, rooms in order of first instance."""
    bounds: dict[str | None, np.ndarray] = {}
    for inst in house.instances:
        lo, hi = inst.vertices.min(0), inst.vertices.max(0)
        b = bounds.get(inst.room_id)
        bounds[inst.room_id] = np.stack([lo, hi]) if b is None else np.stack([np.minimum(b[0], lo),
                                                                             np.maximum(b[1], hi)])
    return bounds


def _reach2(bounds: np.ndarray, position: np.ndarray, min_distance: float) -> float:
    """Squared distance from ``position`` to the farthest corner of ``bounds``."""
    corners = np.stack(np.meshgrid(*zip(*bounds), indexing="ij"), -1).reshape(-1, 3)
    return max(float(((corners - position) ** 2).sum(1).max()), min_distance ** 2)


def is_lamp(inst) -> bool:
    return inst.category == NYU40_IDS["lamp"] or bool(LAMP_LABEL.search(inst.label or ""))


def house_lights(house: "House", config: "RenderConfig") -> list[Light]:
    """Every room's lights (module docs), rooms in order of first instance, then lamps and
    windows in instance order, the fallback last."""
    out = []
    for room, bounds in room_bounds(house).items():
        members = [i for i in house.instances if i.room_id == room]
        lamps = [i for i in members if is_lamp(i) and not i.envelope]
        middle = 0.5 * (bounds[0, 1] + bounds[1, 1])
        for inst in lamps:
            lo, hi = inst.vertices.min(0), inst.vertices.max(0)
            position = 0.5 * (lo + hi)
            gap = config.light_min_distance
            position[1] = lo[1] - gap if lo[1] > middle else hi[1] + gap
            out.append(Light("point", room, position, None,
                             config.light / len(lamps) * _reach2(bounds, position, config.light_min_distance),
                             "lamp"))
        centre = 0.5 * (bounds[0] + bounds[1])
        if config.window_light > 0:
            for inst in (i for i in members if i.category == NYU40_IDS["window"]):
                position = 0.5 * (inst.vertices.min(0) + inst.vertices.max(0))
                inward = centre - position
                inward[1] = 0.0
                if np.linalg.norm(inward) < 1e-6:
                    continue
                inward /= np.linalg.norm(inward)
                direction = np.cos(WINDOW_TILT) * inward + np.array([0.0, -np.sin(WINDOW_TILT), 0.0])
                out.append(Light("spot", room, position, direction,
                                 config.window_light * _reach2(bounds, position, config.light_min_distance),
                                 "window"))
        if not lamps:
            out.append(fallback_light(room, bounds, config))
    return out


def fallback_light(room: str | None, bounds: np.ndarray, config: "RenderConfig") -> Light:
    """The point light of a room without lamps: under the centre of the top of its bounds."""
    lo, hi = bounds
    centre = 0.5 * (lo + hi)
    position = np.array([centre[0], max(hi[1] - config.light_below_ceiling, centre[1]), centre[2]])
    return Light("point", room, position, None, config.light * _reach2(bounds, position, config.light_min_distance),
                 "fallback")


def room_lights(house: "House", config: "RenderConfig") -> dict[str | None, Light]:
    """The fallback light of every room (whether or not the room has lamps)."""
    return {room: fallback_light(room, b, config) for room, b in room_bounds(house).items()}
