"""Linear HDR radiance → 8-bit sRGB: the one exposure and tone-mapping step of both RGB
modes (defined in numpy, float32, so both modes and every machine apply the same
arithmetic; the raster mode evaluates it on the GL device, see "Where it runs").

Both renderers produce linear radiance in the lights' units (:mod:`.lights`: lumens,
candela, cd/m²) for every pixel, and :func:`tonemap` turns it into the stored image:

1. **Exposure** ``e``. Automatic by default (``RenderConfig.exposure`` None), chosen per
   view like a camera's auto exposure: the median luminance (Rec. 709 weights) of the
   pixels that see something lands at :data:`KEY` (18 % grey). The median ignores the
   brightest and darkest half-views alike (a lamp, a window, a black sofa), and scaling
   every light of the house by the same factor leaves the image unchanged. A number is
   a fixed exposure instead (radiance × it, the same for every view).
2. **Tone curve**, applied per channel to ``x = e × radiance`` (``RenderConfig.tone``):
   ``"soft"`` (default) is linear, ``y = x``, up to the knee :data:`SOFT_KNEE` (0.8: 4.4×
   mid-grey), and above it rolls off towards white,
   ``y = k + (x − k) / (1 + (x − k) / (1 − k))`` (slope 1 at the knee, so no kink; 1 only
   as x → ∞; the byte 255 from x ≈ 9.6, 53× mid-grey). Below the knee it is
   PBRS's response (Mitsuba's 8-bit output is a plain clamp and the sRGB encoding): dark
   surfaces and mid-tones keep their ratios and their colour (the chromaticity of a region
   unchanged); above it a lamp's surroundings or a window are graded instead of clipped.
   ``"aces"`` is Narkowicz's fit of the ACES filmic curve: a toe that darkens dark
   surfaces (a surface at a tenth of mid-grey comes out at a thirtieth, about 1.5 stops
   under PBRS's), mid-grey 0.18 → 0.27, and a soft shoulder that reaches white at about
   40× mid-grey (x ≈ 7.2). ``"clip"`` is no curve (``x`` clipped to [0, 1]): with
   ``exposure=1`` a surface of radiance equal to its base colour shows exactly that colour
   (for checking materials and textures). The default was chosen against PBRS's images
   (docs/rgb.md, "Against PBRS").
3. **sRGB encoding** (IEC 61966-2-1) and rounding to bytes; pixels that see nothing get
   ``RenderConfig.background`` exactly.

The curve maps 0 to 0, so a channel a surface does not reflect stays exactly 0.

Where it runs. :func:`tonemap` (numpy, float32) is the definition, and what the path tracer
applies (:class:`ToneMapped`). The raster renderer applies the same arithmetic on the GPU
where it draws (:mod:`.raster`, ``Renderer(gpu_tonemap=True)``, the default): a shader
pass writes each pixel's luminance, of which only the median is taken here
(:func:`exposure_of_luminance`), and a second pass writes the bytes, which are all that is
read back. Its bytes are those of :func:`tonemap`: float32 step for step, the sRGB
encoding exact through :func:`encoding_thresholds` whatever the device's ``pow``, the
luminance with numpy's (OpenBLAS's) fused multiply-adds; identical on Mesa's llvmpipe
(tests/test_render.py). A device whose float32 division is not correctly rounded may put
a channel one level off where the curve's value lies within a rounding of a threshold.
"""

from __future__ import annotations

import functools

import numpy as np

#: the luminance the median seen pixel is exposed to (scene-referred 18 % grey)
KEY = 0.18
#: Rec. 709 / sRGB luminance weights of linear R, G, B
LUMINANCE = np.array([0.2126, 0.7152, 0.0722])
#: Narkowicz's ACES fit: (x (a x + b)) / (x (c x + d) + e)
ACES = (2.51, 0.03, 2.43, 0.59, 0.14)
#: the knee of the ``soft`` curve: linear (y = x) up to it, a shoulder above it
SOFT_KNEE = 0.8
#: tone curves of ``RenderConfig.tone``
TONES = ("soft", "aces", "clip")


def aces(x):
    """Narkowicz's ACES filmic fit of exposed linear values, clipped to [0, 1]."""
    a, b, c, d, e = ACES
    x = np.maximum(np.asarray(x, dtype=np.float64), 0.0)
    return np.clip(x * (a * x + b) / (x * (c * x + d) + e), 0.0, 1.0)


def soft(x, knee: float = SOFT_KNEE):
    """The ``soft`` curve of exposed linear values: y = x up to ``knee``, above it
    ``knee + (x - knee) / (1 + (x - knee) / (1 - knee))`` (slope 1 at the knee, 1 only as x → ∞)."""
    x = np.maximum(np.asarray(x, dtype=np.float64), 0.0)
    over = np.maximum(x - knee, 0.0)
    return np.where(x <= knee, x, knee + over / (1.0 + over / (1.0 - knee)))


def auto_exposure(radiance: np.ndarray, seen: np.ndarray) -> float:
    """The exposure that puts the median luminance of the ``seen`` pixels at :data:`KEY`;
    1 when nothing is seen or the median is black (then the mean is used if it is not)."""
    return exposure_of_luminance((radiance @ LUMINANCE.astype(radiance.dtype))[seen])


def exposure_of_luminance(luminance: np.ndarray) -> float:
    """:func:`auto_exposure` of the (n,) luminances of the seen pixels, in image order (the
    order matters only to the mean, used when the median is black)."""
    if luminance.size == 0:
        return 1.0
    middle = float(np.median(luminance))
    if not middle > 0:
        middle = float(luminance.mean())
    return KEY / middle if middle > 0 else 1.0


def tonemap(radiance: np.ndarray, seen: np.ndarray, *, exposure: float | None = None, tone: str = "soft",
            background=(0.0, 0.0, 0.0)) -> np.ndarray:
    """(H, W, 3) uint8 sRGB image of (H, W, 3) linear ``radiance`` (module docs).

    seen       : (H, W) bool, the pixels that see a surface (the others get ``background``)
    exposure   : None: automatic; else the fixed factor
    tone       : one of :data:`TONES`
    background : sRGB colour in [0, 1] of the pixels that see nothing

    The curve and the encoding are evaluated in float32 (:func:`soft`, :func:`aces` and
    :func:`sceneforge.colour.linear_to_srgb` are the float64 references; the two agree to a level of 8-bit
    rounding), which takes a fifth of the time.
    """
    if tone not in TONES:
        raise ValueError(f"unknown tone curve {tone!r}; expected one of {', '.join(TONES)}")
    f = np.float32
    x = np.nan_to_num(np.asarray(radiance, dtype=f), nan=0.0, posinf=0.0, neginf=0.0)
    e = auto_exposure(x, seen) if exposure is None else float(exposure)
    x *= f(e)
    np.maximum(x, f(0.0), out=x)
    if tone == "aces":
        a, b, c, d, k = (f(v) for v in ACES)
        y = x * (a * x + b)
        y /= x * (c * x + d) + k
    elif tone == "soft":
        k = f(SOFT_KNEE)
        over = np.maximum(x - k, f(0.0))  # 0 below the knee, where y = x
        y = np.where(x <= k, x, k + over / (f(1.0) + over / (f(1.0) - k)))
    else:
        y = x
    np.minimum(y, f(1.0), out=y)
    out = encode(y)
    out[~seen] = background_bytes(background)
    return out


def encode(y: np.ndarray) -> np.ndarray:
    """uint8 sRGB bytes of float32 tone-mapped values ``y`` in [0, 1] (IEC 61966-2-1, rounded
    to nearest, in float32 as :func:`tonemap` evaluates it)."""
    f = np.float32
    srgb = f(1.055) * np.power(y, f(1 / 2.4)) - f(0.055)
    dark = y <= f(0.0031308)
    srgb[dark] = f(12.92) * y[dark]
    return np.rint(srgb * f(255.0)).astype(np.uint8)


def background_bytes(background) -> np.ndarray:
    """(3,) uint8: the bytes of an sRGB ``background`` colour in [0, 1]."""
    return np.round(255.0 * np.asarray(background, dtype=np.float64)).astype(np.uint8)


@functools.cache
def encoding_thresholds() -> np.ndarray:
    """(255,) float32: entry ``j`` is the least float32 ``y`` that :func:`encode` turns into
    ``j + 1`` or more, so that ``encode(y)`` is the number of entries ≤ ``y``: the sRGB
    encoding as 255 comparisons, exact whatever a GPU's ``pow`` rounds to. (Found by
    bisection on the bits of ``y``; that the count equals :func:`encode` for every float32 in
    [0, 1] was checked exhaustively on numpy 2 / x86-64, and tests/test_render.py checks it
    around every entry.)"""
    f = np.float32
    lo = np.zeros(255, np.uint32)  # encode(lo) <= j, encode(hi) >= j + 1
    hi = np.full(255, f(1.0).view(np.uint32), np.uint32)
    level = np.arange(1, 256)
    while np.any(hi - lo > 1):
        mid = lo + (hi - lo) // 2
        above = encode(mid.view(f)) >= level
        hi, lo = np.where(above, mid, hi), np.where(above, lo, mid)
    return hi.view(f)


class ToneMapped:
    """What a renderer of linear radiance gets for free: :meth:`render`, its image through
    :func:`tonemap` with the exposure, curve and background of its ``config`` (a
    :class:`~.raster.RenderConfig`). Both modes end in this one step: the path tracer with
    numpy, the raster renderer on the GL device (its own ``render``, the same bytes; this one
    with ``gpu_tonemap=False``)."""

    def render(self, house, camera) -> np.ndarray:
        """(H, W, 3) uint8 sRGB image of ``house`` seen from ``camera`` (:func:`tonemap` of
        ``render_linear``)."""
        radiance, seen = self.render_linear(house, camera)
        c = self.config
        return tonemap(radiance, seen, exposure=c.exposure, tone=c.tone, background=c.background)
