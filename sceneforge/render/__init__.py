"""RGB images of house views, pixel-aligned with the depth layers (docs/spec.md §8).

Two renderers behind one interface (``render(house, camera) -> (H, W, 3) uint8 sRGB``,
``close()``, a context manager), chosen by :func:`open_renderer` from the RGB mode:

- ``raster`` (:mod:`.raster`): pyrender through EGL, per-pixel lighting from the house's
  lights (:mod:`.lights`), milliseconds per frame;
- ``pathtraced`` (:mod:`.pathtrace`): Mitsuba 3 on the CPU (LLVM) or an NVIDIA GPU (CUDA),
  global illumination with soft shadows, a fixed sample count and seed.

Both compute linear radiance from the same lights (:mod:`.lights`) and turn it into the
image with the same exposure and tone curve (:mod:`.tonemap`).
"""

from __future__ import annotations

from .lights import Light, house_lights, room_lights
from .raster import (
    FAR,
    INSTALL_EGL,
    INSTALL_RENDER,
    NEAR,
    Batch,
    EGLDevice,
    RenderConfig,
    Renderer,
    egl_devices,
    house_batches,
)
from .tonemap import tonemap

#: the RGB modes of ``sceneforge render --rgb`` that render something
MODES = ("raster", "pathtraced")

__all__ = ["FAR", "INSTALL_EGL", "INSTALL_RENDER", "MODES", "NEAR", "Batch", "EGLDevice", "Light", "RenderConfig",
           "Renderer", "egl_devices", "house_batches", "house_lights", "open_renderer",
           "room_lights", "tonemap"]


def open_renderer(mode: str, width: int, height: int, *, antialias: bool = False, config: RenderConfig | None = None,
                  samples: int | None = None, seed: int = 0, gpu: int | None = None, denoise: bool = True):
    """A renderer of ``mode`` (one of :data:`MODES`) for ``width`` × ``height`` images.

    antialias : raster only: 4× multisampling
    samples   : path tracing only: samples per pixel (None: its default)
    seed      : path tracing only: the sampler's seed
    denoise   : path tracing only: denoise with Intel Open Image Denoise (:mod:`.denoise`)
    """
    if mode == "raster":
        return Renderer(width, height, gpu=gpu, antialias=antialias, config=config)
    if mode == "pathtraced":
        from .pathtrace import PathTracer

        return PathTracer(width, height, config=config, samples=samples, seed=seed, denoise=denoise)
    raise ValueError(f"unknown RGB mode {mode!r}; expected one of {', '.join(MODES)}")
