"""The lights of a house, placed from what it has, in photometric units (pure numpy, no GL).

Units: luminous flux in lumens (lm), intensity in candela (cd = lm/sr), radiance in
cd/m²; a pixel's radiance comes out in cd/m² and the exposure step (:mod:`.tonemap`) maps
it to the image. Light falls off as 1/d² (no nearer than ``light_min_distance``).

Every room (``Instance.room_id``; None groups the instances of no room) gets:

- one **point light per lamp** (NYU40 ``lamp``, or a label naming a lamp, light or
  chandelier) of ``lamp_power`` lumens (the houses give no lamp powers; 800 lm is a
  60 W incandescent bulb), radiating ``lamp_power / 4π`` cd in every direction, outside
  its shade, where the light comes out: ``light_min_distance`` below the bottom centre of
  a hanging lamp (one whose bottom is above the middle of its room's height), as far above
  the top centre of a standing one (floor and table lamps) (inside, the shade would hide
  it from the path tracer; nearer, the shade's light would swamp the path tracer's samples);
- one **window light per window** (NYU40 ``window``, when ``sky_luminance`` > 0): the
  window is a Lambertian panel of radiance ``sky_luminance`` (the sky seen through it)
  facing into the room. The path tracer makes the window's own faces that area emitter;
  the raster mode draws the window with that radiance and lights the room with the
  panel's far field, a spot light at the window's centre along its inward normal of
  on-axis intensity ``sky_luminance × area`` falling off as cos θ out to
  :data:`WINDOW_CONE` (the window's area is that of its bounds across its normal);
- and, as the documented **fallback** for a room that has neither a lamp nor a window
  light, one point light of ``lamp_power`` ``light_below_ceiling`` under the centre of
  the top of the room's bounds (no lower than their middle height).

Indirect light (raster only; the path tracer traces it): a room's surfaces receive
``ambient × Φ / A`` lux besides their direct light, Φ the room's total flux (lamps:
``lamp_power``; windows: ``π × sky_luminance × area``) and A the surface of its bounds
(an integrating sphere of albedo ρ reflects ρ / (1 - ρ) of its flux back onto its walls:
``ambient`` 1 is a room of mean albedo ½).
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
#: half-angle of a window's cone of light in the raster mode, radians (below 84°, so that
#: its shadow map's camera has a field of view under 180°)
WINDOW_CONE = np.radians(80.0)


@dataclass(frozen=True)
class Light:
    """One light of a room.

    kind      : "point" or "spot"
    room      : the room it lights (``Instance.room_id``)
    position  : (3,) float64   world, metres
    direction : (3,) float64   unit, where a spot light points (None for point lights)
    intensity : float          candela (on the axis, for a spot light)
    source    : what placed it: "lamp", "window" or "fallback"
    flux      : float          lumens it sends into the room
    instance  : the ``Instance.id`` of its lamp or window (None for a fallback)
    radiance  : float          a window's radiance, cd/m² (0 for the others)
    """

    kind: str
    room: str | None
    position: np.ndarray
    direction: np.ndarray | None
    intensity: float
    source: str
    flux: float = 0.0
    instance: int | None = None
    radiance: float = 0.0


def room_bounds(house: "House") -> dict[str | None, np.ndarray]:
    """(2, 3) float64 bounds of each room's instances, rooms in order of first instance."""
    bounds: dict[str | None, np.ndarray] = {}
    for inst in house.instances:
        lo, hi = inst.vertices.min(0), inst.vertices.max(0)
        b = bounds.get(inst.room_id)
        bounds[inst.room_id] = np.stack([lo, hi]) if b is None else np.stack([np.minimum(b[0], lo),
                                                                             np.maximum(b[1], hi)])
    return bounds


def is_lamp(inst) -> bool:
    return inst.category == NYU40_IDS["lamp"] or bool(LAMP_LABEL.search(inst.label or ""))


def window_panel(inst, room_centre: np.ndarray) -> tuple[np.ndarray, np.ndarray, float] | None:
    """(centre, inward unit normal, area) of a window: its vertices' principal axes give its
    plane (the two widest) and normal (the thinnest, turned towards ``room_centre``); the
    area is its extent along the two widest. None for a degenerate window."""
    v = inst.vertices.astype(np.float64)
    lo, hi = v.min(0), v.max(0)
    centre = 0.5 * (lo + hi)
    _, _, axes = np.linalg.svd(v - v.mean(0), full_matrices=False)
    if len(axes) < 3:
        return None
    extents = np.ptp(v @ axes.T, axis=0)
    normal = axes[2] / np.linalg.norm(axes[2])
    towards = room_centre - centre
    if float(normal @ towards) < 0:
        normal = -normal
    area = float(extents[0] * extents[1])
    if not area > 0 or abs(float(normal @ towards)) < 1e-9:
        return None
    return centre, normal, area


def house_lights(house: "House", config: "RenderConfig") -> list[Light]:
    """Every room's lights (module docs), rooms in order of first instance, then lamps and
    windows in instance order, the fallback last."""
    out = []
    for room, bounds in room_bounds(house).items():
        members = [i for i in house.instances if i.room_id == room]
        lamps = [i for i in members if is_lamp(i) and not i.envelope]
        middle = 0.5 * (bounds[0, 1] + bounds[1, 1])
        power = float(config.lamp_power)
        for inst in lamps:
            lo, hi = inst.vertices.min(0), inst.vertices.max(0)
            position = 0.5 * (lo + hi)
            gap = config.light_min_distance
            position[1] = lo[1] - gap if lo[1] > middle else hi[1] + gap
            out.append(Light("point", room, position, None, power / (4 * np.pi), "lamp", power, inst.id))
        centre = 0.5 * (bounds[0] + bounds[1])
        windows = 0
        if config.sky_luminance > 0:
            for inst in (i for i in members if i.category == NYU40_IDS["window"]):
                panel = window_panel(inst, centre)
                if panel is None:
                    continue
                position, normal, area = panel
                luminance = float(config.sky_luminance)
                out.append(Light("spot", room, position, normal, luminance * area, "window",
                                 np.pi * luminance * area, inst.id, luminance))
                windows += 1
        if not lamps and not windows:
            out.append(fallback_light(room, bounds, config))
    return out


def fallback_light(room: str | None, bounds: np.ndarray, config: "RenderConfig") -> Light:
    """The point light of a room without lamps or windows: under the centre of the top of its bounds."""
    lo, hi = bounds
    centre = 0.5 * (lo + hi)
    position = np.array([centre[0], max(hi[1] - config.light_below_ceiling, centre[1]), centre[2]])
    power = float(config.lamp_power)
    return Light("point", room, position, None, power / (4 * np.pi), "fallback", power)


def room_lights(house: "House", config: "RenderConfig") -> dict[str | None, Light]:
    """The fallback light of every room (whether or not the room has lamps)."""
    return {room: fallback_light(room, b, config) for room, b in room_bounds(house).items()}


def room_ambient(house: "House", config: "RenderConfig", lights: list[Light] | None = None) -> dict[str | None, float]:
    """The indirect irradiance (lux) of every room in the raster mode (module docs)."""
    lights = house_lights(house, config) if lights is None else lights
    out = {}
    for room, (lo, hi) in room_bounds(house).items():
        size = np.maximum(hi - lo, 1e-3)
        area = 2.0 * (size[0] * size[1] + size[1] * size[2] + size[0] * size[2])
        flux = sum(light.flux for light in lights if light.room == room)
        out[room] = float(config.ambient) * flux / area
    return out
