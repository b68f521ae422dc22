"""Colour encodings, stated once: colours in the house model (materials' base colours,
vertex colours) are linear RGB in [0, 1]; images (textures, PLY vertex colours as written,
the stored RGB) are sRGB-encoded bytes.

These are the float64 references of the sRGB transfer functions (IEC 61966-2-1). A module
below the loaders and the renderers alike, as both decode sRGB: a loader its sources'
colours, a renderer its textures.
"""

from __future__ import annotations

import numpy as np


def srgb_to_linear(c):
    """Linear values of sRGB-encoded values in [0, 1] (IEC 61966-2-1)."""
    c = np.asarray(c, dtype=np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(c):
    """sRGB-encoded values of linear values in [0, 1] (IEC 61966-2-1)."""
    c = np.clip(np.asarray(c, dtype=np.float64), 0.0, 1.0)
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * c ** (1 / 2.4) - 0.055)
