"""Denoising of path-traced frames: Intel Open Image Denoise (``pyoidn``) with albedo and
normal guides (``render --rgb pathtraced``, on by default; ``--no-rgb-denoise`` for none).

The path tracer (:mod:`.pathtrace`) renders, beside each pixel's radiance, the mean albedo
(the first surface's reflectance) and shading normal (world space, unit length) of its
samples: Mitsuba's ``aov`` integrator around the ``path`` one, so all three come from the
same samples. OIDN's ``RT`` filter (``hdr``: the radiance in cd/m², any scale; quality
``high``) denoises the radiance guided by them: the guides are smooth where a surface is and
change where its colour or orientation does, so silhouettes and texture edges stay where they
are while the noise of flat lit surfaces goes. The guides are noisy too where samples see
several surfaces (silhouettes, antialiased edges): OIDN prefilters them (``clean_aux``
false). The denoiser runs on the CPU (OIDN's CPU device) in float32; the same inputs give
the same bytes on the same machine.
"""

from __future__ import annotations

import numpy as np

from ..errors import MissingDependencyError

INSTALL_OIDN = "pip install 'sceneforge[pathtrace]' (or render with --no-rgb-denoise)"


def denoise(radiance: np.ndarray, albedo: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """(H, W, 3) float64 denoised radiance (module docs).

    radiance : (H, W, 3) float  linear radiance, non-negative
    albedo   : (H, W, 3) float  mean albedo of each pixel's samples, in [0, 1]
    normal   : (H, W, 3) float  mean shading normal of each pixel's samples, in [-1, 1]
    """
    try:
        import pyoidn
    except ModuleNotFoundError:
        raise MissingDependencyError("pyoidn", "denoised path-traced RGB", INSTALL_OIDN) from None
    f32 = [np.ascontiguousarray(np.nan_to_num(a, nan=0.0, posinf=0.0, neginf=0.0), dtype=np.float32)
           for a in (np.maximum(radiance, 0.0), np.clip(albedo, 0.0, 1.0), np.clip(normal, -1.0, 1.0))]
    out = pyoidn.denoise(f32[0], albedo=f32[1], normal=f32[2], hdr=True, quality="high")
    return np.maximum(np.asarray(out, dtype=np.float64), 0.0)
