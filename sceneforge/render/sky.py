"""The world outside the windows: a procedural sky over a ground plane (pure numpy, no data
files; part of sceneforge's code and under its licence).

Radiance of the outdoors seen along a world direction ``d`` (unit, +Y up), in linear sRGB
relative units (:func:`radiance`):

- **sky** (``d_y >= 0``): a clear sky without the sun's disc, its colour and brightness
  graded from the hazy horizon (:data:`HORIZON`) to the deep blue zenith (:data:`ZENITH`)
  as ``t = d_y ** 0.5`` (the sky's brightness and whiteness fall quickly above the horizon);
- **ground** (``d_y < 0``): a Lambertian ground of albedo :data:`GROUND_ALBEDO` (grass and
  paving) lit by the whole sky and the sun: radiance ``albedo × (E_sky + E_sun) / π``,
  ``E_sky`` the sky's irradiance on a horizontal plane and ``E_sun`` :data:`SUN` times it
  in luminance, of the sun's colour :data:`SUN_COLOUR` (a clear day, the sun well up). The
  sun's own beam does not enter the rooms (no disc in the sky, no sun patches on floors).

What a window lets in (:func:`window_colour`) is the cosine-weighted mean of that radiance
over the outward hemisphere of a vertical window: half sky, half ground. Its luminance sets
the unit: the environment is scaled so that a window's mean luminance is 1, and
``RenderConfig.sky_luminance`` (cd/m²) is that mean; its colour is the light every window
sends into the room (both modes) and the part of a room's indirect light the windows give
(:func:`~sceneforge.render.lights.room_ambient`). The raster mode draws the outdoors as a
dome of vertex colours (:func:`dome`) where a window's glass lets it through; the path
tracer looks it up as an environment map (:func:`latlong`).

The numbers are a plausible clear day (horizon about 8 000 K, zenith a saturated sky
blue, the ground a dull green-grey), not a measured sky: PBRS lit SUNCG with a photographed
HDR environment (a parking lot under a blue sky) that cannot be shipped.
"""

from __future__ import annotations

import functools

import numpy as np

#: linear sRGB radiance of the sky at the horizon and at the zenith (relative)
HORIZON = np.array([0.72, 0.82, 1.0])
ZENITH = np.array([0.12, 0.24, 0.62])
#: exponent of the grading from horizon to zenith in ``d_y``
GRADIENT = 0.5
#: linear albedo of the ground outside (grass and paving)
GROUND_ALBEDO = np.array([0.13, 0.16, 0.10])
#: the sun's irradiance on the ground over the sky's (luminance), and its colour (linear,
#: about 5 500 K)
SUN = 3.0
SUN_COLOUR = np.array([1.0, 0.93, 0.85])
#: Rec. 709 luminance weights of linear R, G, B
LUMINANCE = np.array([0.2126, 0.7152, 0.0722])


def _sky(dy: np.ndarray) -> np.ndarray:
    t = np.clip(dy, 0.0, 1.0)[..., None] ** GRADIENT
    return HORIZON * (1.0 - t) + ZENITH * t


@functools.cache
def _ground() -> np.ndarray:
    """(3,) the ground's radiance: albedo × (sky + sun) horizontal irradiance / π (unscaled)."""
    mu = (np.arange(4096) + 0.5) / 4096  # d_y over the upper hemisphere: E = 2π ∫ L(μ) μ dμ
    irradiance = 2.0 * np.pi * (_sky(mu) * mu[:, None]).mean(axis=0)
    sun = SUN * float(irradiance @ LUMINANCE) * SUN_COLOUR / float(SUN_COLOUR @ LUMINANCE)
    return GROUND_ALBEDO * (irradiance + sun) / np.pi


def _raw(directions: np.ndarray) -> np.ndarray:
    d = np.asarray(directions, dtype=np.float64)
    d = d / np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-12)
    return np.where(d[..., 1:2] >= 0.0, _sky(d[..., 1]), _ground())


@functools.cache
def _window_raw() -> np.ndarray:
    """(3,) cosine-weighted mean unscaled radiance through a vertical window (facing +x)."""
    n = 256
    u, v = np.meshgrid((np.arange(n) + 0.5) / n, (np.arange(n) + 0.5) / n)
    # cosine-weighted hemisphere about +x (Malley): a disc sample lifted onto the hemisphere
    r, phi = np.sqrt(u), 2.0 * np.pi * v
    a, b = r * np.cos(phi), r * np.sin(phi)
    d = np.stack([np.sqrt(np.maximum(1.0 - a * a - b * b, 0.0)), a, b], axis=-1).reshape(-1, 3)
    return _raw(d).mean(axis=0)


def scale() -> float:
    """Factor of the unscaled model that makes a window's mean luminance 1."""
    return 1.0 / float(_window_raw() @ LUMINANCE)


def radiance(directions) -> np.ndarray:
    """(..., 3) linear radiance of the outdoors along ``directions`` (..., 3), in units of
    a window's mean luminance (module docs)."""
    return _raw(directions) * scale()


def window_colour() -> np.ndarray:
    """(3,) the colour of the light a window lets in: linear sRGB of luminance 1."""
    return _window_raw() * scale()


def dome(centre, radius: float, rings: int = 24, segments: int = 48):
    """A sphere around ``centre`` drawn with the outdoors' radiance as vertex colours:
    vertices (n, 3) float64, faces (m, 3) int64, colours (n, 3) float64 (the radiance seen
    from the centre; multiply by the sky luminance). ``rings`` bands above the horizon and as
    many below, denser near the horizon, where the sky's colour changes fastest; the horizon
    ring is there twice, with the sky's colour and with the ground's, so that no band blends
    the two."""
    t = np.linspace(0.0, 1.0, rings + 1) ** 1.5 * (np.pi / 2)
    elevation = np.concatenate([-t[::-1], t])  # ground from the nadir up, then the sky
    azimuth = np.linspace(0.0, 2.0 * np.pi, segments, endpoint=False)
    el, az = np.meshgrid(elevation, azimuth, indexing="ij")
    d = np.stack([np.cos(el) * np.cos(az), np.sin(el), np.cos(el) * np.sin(az)], axis=-1).reshape(-1, 3)
    below = np.repeat(np.arange(len(elevation)) <= rings, segments)
    colours = radiance(np.where(below[:, None], d - [0.0, 1e-9, 0.0], d))
    vertices = np.asarray(centre, dtype=np.float64) + radius * d
    faces = []
    for i in range(len(elevation) - 1):
        if i == rings:
            continue  # the two horizon rings: no band between them
        for j in range(segments):
            a, b = i * segments + j, i * segments + (j + 1) % segments
            c, e = a + segments, b + segments
            faces += [[a, c, b], [b, c, e]]
    return vertices, np.asarray(faces, dtype=np.int64), colours


def latlong(width: int = 512, height: int = 256) -> np.ndarray:
    """(height, width, 3) float32 equirectangular image of :func:`radiance` (row 0 the
    zenith, +Y up), in Mitsuba's ``envmap`` convention (its +Y up, u = 0 along +x... the sky
    model has no azimuth, so only the rows matter)."""
    theta = (np.arange(height) + 0.5) / height * np.pi  # from the zenith
    dy = np.cos(theta)
    d = np.stack([np.sin(theta), dy, np.zeros_like(dy)], axis=-1)
    row = radiance(d).astype(np.float32)
    return np.repeat(row[:, None, :], width, axis=1)
