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
  window is a Lambertian panel of radiance ``sky_luminance`` (the outdoors seen through
  it, :mod:`.sky`: a clear sky over a sunlit ground) facing into the room, of the
  outdoors' colour (:func:`.sky.window_colour`: daylight, bluer than the lamps). The path
  tracer makes the window's own faces that area emitter (a glazed window: the outdoors
  itself, through its glass); the raster mode draws the window with that radiance (a
  glazed window: its frame, and the outdoors through its glass) and lights the room with the
  panel's far field, a spot light at the window's centre along its inward normal of
  on-axis intensity ``sky_luminance × area`` falling off as cos θ out to
  :data:`WINDOW_CONE` (the window's area is that of its bounds across its normal);
- and, as the documented **fallback** for a room that has neither a lamp nor a window
  light, one point light of ``lamp_power`` ``light_below_ceiling`` under the centre of
  the top of the room's bounds (no lower than their middle height).

A light lights its own room and every room whose bounds are mostly the same as its room's
(intersection over union at least :data:`SAME_SPACE`; :func:`light_rooms`): SUNCG has rooms
drawn over one another (a storage room over a living room, their floors coinciding), and
lit apart such a space showed one room's darkness over the other's light in stripes.
Other rooms stay apart: light does not leak into a neighbour through its walls.

Lamps and fallbacks are white (:attr:`Light.colour`; linear sRGB of luminance 1).

Indirect light (raster only; the path tracer traces it), a radiosity-style estimate per
room: its surfaces receive ``ambient × Φ / A × ρ / (1 − ρ)`` lux besides their direct light,
Φ the room's total flux (lamps: ``lamp_power``; windows: ``π × sky_luminance × area``), A
the surface of its bounds and ρ the mean albedo of the room's surfaces (area-weighted
luminance of base colour × mean texel; :func:`room_albedo`): an integrating sphere of
albedo ρ sends ρ / (1 − ρ) of the flux it receives back onto its walls after all bounces.
The light has the colour of the room's lights, flux-weighted. The rooms' own tint (ρ per
channel) is left out: against PBRS's renders of a SUNCG house (cameras 0–3) it brings the
walls and curtains within 0.05 of PBRS's chromaticity (7 of 7 regions, from 1) but takes
two of the 13 object regions out (84.6 → 69.2 %: a wood table already too red, in two views); and it
would change every store's RGB (docs/rgb.md, "Against PBRS").
"""

from __future__ import annotations

import functools
import re
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..conventions import NYU40_IDS
from .sky import LUMINANCE, window_colour

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
    colour    : (3,) linear sRGB of luminance 1 the intensity, flux and radiance are of
                (white; a window's the outdoors')
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
    colour: tuple[float, float, float] = (1.0, 1.0, 1.0)


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
            daylight = tuple(float(c) for c in window_colour())
            for inst in (i for i in members if i.category == NYU40_IDS["window"]):
                panel = window_panel(inst, centre)
                if panel is None:
                    continue
                position, normal, area = panel
                luminance = float(config.sky_luminance)
                out.append(Light("spot", room, position, normal, luminance * area, "window",
                                 np.pi * luminance * area, inst.id, luminance, daylight))
                windows += 1
        if not lamps and not windows:
            out.append(fallback_light(room, bounds, config))
    return out


def glazed_windows(house: "House") -> frozenset[int]:
    """The ids of the windows with glass: NYU40 ``window`` instances with a face group of
    opacity below 1 (SUNCG's window models: ``d 0.5`` panes in frames). The outdoors shows
    through that glass (:mod:`.sky`), as PBRS masked it out; other windows are panels."""
    window = NYU40_IDS["window"]
    return frozenset(inst.id for inst in house.instances
                     if inst.category == window and any(m.base_color[3] < 1.0 for m in inst.materials))


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


def room_ambient(house: "House", config: "RenderConfig",
                 lights: list[Light] | None = None) -> dict[str | None, np.ndarray]:
    """The indirect irradiance (lux, (3,) linear RGB) of every room in the raster mode
    (module docs)."""
    lights = house_lights(house, config) if lights is None else lights
    albedo = room_albedo(house)
    reach = light_rooms(house, lights)
    out = {}
    for room, (lo, hi) in room_bounds(house).items():
        size = np.maximum(hi - lo, 1e-3)
        area = 2.0 * (size[0] * size[1] + size[1] * size[2] + size[0] * size[2])
        flux = sum((light.flux * np.asarray(light.colour) for light, rooms in zip(lights, reach, strict=True)
                    if room in rooms), np.zeros(3))
        rho = min(albedo.get(room, 0.5), MAX_ALBEDO)
        out[room] = float(config.ambient) * flux / area * rho / (1.0 - rho)
    return out


#: rooms whose bounds' intersection over union is at least this are one space (module docs)
SAME_SPACE = 0.5


def light_rooms(house: "House", lights: list[Light]) -> list[tuple[str | None, ...]]:
    """The rooms each light lights: its own, then every other room (in room order) whose
    bounds are mostly its room's (module docs)."""
    bounds = room_bounds(house)

    def volume(lo, hi) -> float:
        return float(np.prod(np.maximum(hi - lo, 0.0)))

    def same_space(a, b) -> bool:
        if a is None or b is None or a == b:
            return False
        (alo, ahi), (blo, bhi) = bounds[a], bounds[b]
        inter = volume(np.maximum(alo, blo), np.minimum(ahi, bhi))
        union = volume(alo, ahi) + volume(blo, bhi) - inter
        return union > 0 and inter / union >= SAME_SPACE

    shared = {room: tuple(other for other in bounds if same_space(room, other)) for room in bounds}
    return [(light.room, *shared.get(light.room, ())) for light in lights]


#: the mean albedo :func:`room_ambient` takes at most (a white room would send back ~all)
MAX_ALBEDO = 0.9


def room_albedo(house: "House") -> dict[str | None, float]:
    """The mean albedo of every room: the area-weighted luminance of its surfaces' base
    colours × mean texel (sRGB texels decoded to linear; a texture without uv counts as its
    base colour alone; vertex colours are left out), over all its instances."""
    sums: dict[str | None, list[float]] = {}
    for inst in house.instances:
        tri = inst.vertices[inst.faces]
        area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        per_group = np.bincount(inst.face_materials(), weights=area, minlength=len(inst.materials))
        total = sums.setdefault(inst.room_id, [0.0, 0.0])
        for material, weight in zip(inst.materials, per_group, strict=True):
            colour = np.asarray(material.base_color[:3], dtype=np.float64)
            if material.texture is not None and inst.uv is not None:
                colour = colour * mean_texel(material.texture)
            total[0] += float(weight) * float(colour @ LUMINANCE)
            total[1] += float(weight)
    return {room: (s / w if w > 0 else 0.5) for room, (s, w) in sums.items()}


def mean_texel(texture) -> np.ndarray:
    """(3,) the mean linear colour of a ``Material.texture`` (path or PIL image); grey ½
    for one that cannot be read (the renderers say why)."""
    if isinstance(texture, (str, Path)):
        return _mean_texel_of_file(str(texture))
    return _mean_of(texture)


def _mean_texel_of_file(path: str) -> np.ndarray:
    try:
        stamp = Path(path).stat().st_mtime_ns
    except OSError:
        return np.full(3, 0.5)
    return _mean_texel_cached(path, stamp)


@functools.lru_cache(maxsize=1024)
def _mean_texel_cached(path: str, mtime_ns: int) -> np.ndarray:
    from PIL import Image

    try:
        with Image.open(path) as image:
            mean = _mean_of(image)
    except (OSError, ValueError):
        mean = np.full(3, 0.5)
    mean.setflags(write=False)
    return mean


def _mean_of(image) -> np.ndarray:
    from ..colour import srgb_to_linear

    texels = np.asarray(image.convert("RGB"), dtype=np.float64) / 255.0
    return srgb_to_linear(texels).reshape(-1, 3).mean(axis=0)
