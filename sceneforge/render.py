"""Offscreen RGB (and z-buffer depth) of house views with pyrender through EGL (SPEC §8).

The only module that touches OpenGL. One :class:`Renderer` per worker process renders
every view of every house: it keeps the GL scene of the current house and rebuilds it,
freeing the previous one's GL buffers and textures, when another house comes.

Alignment with the depth layers. The camera is the layers' camera: pyrender's
``IntrinsicsCamera`` with fx, fy, cx, cy (and the skew) of ``K``, posed with
:func:`sceneforge.cameras.opencv_to_opengl`. OpenGL rasterises at pixel centres and maps
window x ∈ [0, W] onto continuous u ∈ [0, W], which is exactly the convention of
``K`` (pixel ``(i, j)`` has its centre at ``(j + 0.5, i + 0.5)``), so no half-pixel shift
is needed. pyrender always renders into a 4× multisampled framebuffer, whose samples are
not at pixel centres and whose colours blend across depth edges; by default this module
renders single-sampled instead, so every RGB pixel shows the surface that the ray through
its centre hits first (``antialias=True`` restores pyrender's 4× multisampling).
Every face is drawn from both sides, like the ray tracer sees it.

Look. Materials (``Instance.material``: linear RGBA base colour, optional texture sampled
with ``Instance.uv``) from every loader, opaque: alpha is ignored, as the depth layers see
glass too. Lighting is deterministic and baked into vertex colours once per house
(:func:`shade_house`): an ambient term plus one point light under the ceiling centre of
each room (its extent from its instances), lighting only that room's instances, with the
Lambert term of either side of a face (so back faces are lit too) and ``1/d²`` falloff.
The same view always gives the same pixels on the same machine; different GL drivers can
differ by rounding.

Devices. ``gpu=None`` picks ``$EGL_DEVICE_ID`` when set, else the first EGL device backed
by a DRM device (a GPU), else the first one (Mesa's software llvmpipe device). A missing
libEGL or EGL driver is reported as a :class:`~sceneforge.errors.MissingDependencyError`
naming what to install.
"""

from __future__ import annotations

import functools
import os
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import TYPE_CHECKING

import numpy as np

from .cameras import opencv_to_opengl
from .errors import HouseError, MissingDependencyError, SceneforgeError

if TYPE_CHECKING:
    from .cameras import Camera
    from .houses.model import House

#: near and far clipping planes, metres. With a 24-bit depth buffer the depth resolution
#: is about z² / (NEAR · 2²⁴): 0.1 mm at 10 m. Surfaces nearer than NEAR to the camera are
#: clipped; FAR is beyond any house.
NEAR, FAR = 0.05, 1000.0
#: display gamma of the rendered images (vertex colours are gamma-encoded: the flat shader
#: multiplies them with sRGB texels, and (a·b)^(1/γ) = a^(1/γ) · b^(1/γ))
GAMMA = 2.2

INSTALL_RENDER = "pip install 'sceneforge[render]'"
#: Debian/Ubuntu packages of libEGL and Mesa's EGL driver with its software rasteriser
#: (a GPU driver with EGL, e.g. NVIDIA's, works as well)
INSTALL_EGL = "sudo apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri"


@dataclass(frozen=True)
class RenderConfig:
    """How rendered views look. Field docs become the config schema's descriptions."""

    #: ambient light: the fraction of its base colour that every surface shows unlit
    ambient: float = 0.3
    #: strength of each room's light: a surface facing it at the room's farthest corner
    #: receives this much (1/d² falloff, so nearer surfaces receive more)
    light: float = 0.25
    #: the room light hangs this far below the top of its room's bounds, metres
    light_below_ceiling: float = 0.3
    #: nearer than this, a surface receives the light of this distance, metres
    light_min_distance: float = 0.3
    #: sRGB colour (0..1) of pixels that see nothing
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self):
        for name in ("ambient", "light", "light_below_ceiling"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if not self.light_min_distance > 0:
            raise ValueError(f"light_min_distance must be > 0, got {self.light_min_distance}")
        if len(self.background) != 3 or not all(0 <= c <= 1 for c in self.background):
            raise ValueError(f"background must be 3 numbers in [0, 1], got {self.background}")
        # a list read back from a saved config would make the config unhashable
        object.__setattr__(self, "background", tuple(float(c) for c in self.background))


# ---------------------------------------------------------------------------------------
# Baked lighting: pure numpy, no GL


@dataclass(frozen=True)
class RoomLight:
    """The point light of one room.

    position  : (3,) float64  world, metres
    intensity : float         irradiance at 1 m facing the light
    """

    position: np.ndarray
    intensity: float


@dataclass(frozen=True, eq=False)
class Batch:
    """Triangles of a house that share one texture (or none), lighting baked in.

    positions : (3m, 3) float32  world, three unshared corners per triangle
    colors    : (3m, 4) float32  gamma-encoded RGBA multiplier (alpha 1): base colour × light
    uv        : (3m, 2) float32  texture coordinates (OpenGL convention), or None
    texture   : the ``Material.texture`` (path or PIL image) these triangles sample, or None
    """

    positions: np.ndarray
    colors: np.ndarray
    uv: np.ndarray | None
    texture: object | None


def room_lights(house: "House", config: RenderConfig | None = None) -> dict[str | None, RoomLight]:
    """One light per room (per ``Instance.room_id``; None groups the instances of no room).

    The light hangs ``light_below_ceiling`` under the centre of the top of the bounds of the
    room's instances (no lower than their middle height). Its intensity makes a surface that
    faces it at the farthest corner of those bounds receive ``config.light``.
    """
    config = config or RenderConfig()
    bounds: dict[str | None, np.ndarray] = {}
    for inst in house.instances:
        lo, hi = inst.vertices.min(0), inst.vertices.max(0)
        b = bounds.get(inst.room_id)
        bounds[inst.room_id] = np.stack([lo, hi]) if b is None else np.stack([np.minimum(b[0], lo),
                                                                             np.maximum(b[1], hi)])
    lights = {}
    for room, (lo, hi) in bounds.items():
        centre = 0.5 * (lo + hi)
        position = np.array([centre[0], max(hi[1] - config.light_below_ceiling, centre[1]), centre[2]])
        corners = np.stack(np.meshgrid(*zip(lo, hi), indexing="ij"), -1).reshape(-1, 3)
        reach2 = max(float(((corners - position) ** 2).sum(1).max()), config.light_min_distance ** 2)
        lights[room] = RoomLight(position, config.light * reach2)
    return lights


def _irradiance(points, normals, light: RoomLight, min_distance: float) -> np.ndarray:
    """(n,) float64 light that (n, 3) points with unit (n, 3) normals receive, either side."""
    to_light = light.position - points
    d2 = np.einsum("ij,ij->i", to_light, to_light)
    cos = np.abs(np.einsum("ij,ij->i", normals, to_light)) / np.sqrt(np.maximum(d2, 1e-300))
    return light.intensity * cos / np.maximum(d2, min_distance ** 2)


def _texture_key(texture) -> object:
    """What identifies a texture across instances: its resolved path, or the image object."""
    if texture is None:
        return None
    if isinstance(texture, (str, Path)):
        return str(Path(texture).resolve())
    return id(texture)


def shade_house(house: "House", config: RenderConfig | None = None) -> list[Batch]:
    """The house's triangles with lighting baked into vertex colours, one batch per texture.

    Each triangle gets its own three corners (flat shading). A corner's colour is
    ``(base_rgb · (ambient + light)) ** (1 / GAMMA)`` clipped to [0, 1], where ``light`` is
    :func:`_irradiance` from its room's :class:`RoomLight` with the face normal. Batches come
    in the order their texture first appears in ``house.instances`` (untextured: None);
    an instance with a texture but no ``uv`` is drawn with its base colour only.
    """
    config = config or RenderConfig()
    lights = room_lights(house, config)
    parts: dict[object, tuple[object, list, list, list]] = {}
    for inst in house.instances:
        tri = inst.vertices[inst.faces]
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
        points = tri.reshape(-1, 3)
        light = config.ambient + _irradiance(points, np.repeat(normal, 3, axis=0), lights[inst.room_id],
                                             config.light_min_distance)
        base = np.clip(np.asarray(inst.material.base_color[:3], dtype=np.float64), 0.0, 1.0)
        colors = np.ones((len(points), 4), dtype=np.float32)
        colors[:, :3] = np.clip(light[:, None] * base, 0.0, 1.0) ** (1.0 / GAMMA)
        texture = inst.material.texture if inst.uv is not None else None
        key = _texture_key(texture)
        entry = parts.setdefault(key, (texture, [], [], []))
        entry[1].append(points.astype(np.float32))
        entry[2].append(colors)
        if texture is not None:
            entry[3].append(inst.uv[inst.faces].reshape(-1, 2).astype(np.float32))
    return [
        Batch(np.concatenate(p), np.concatenate(c), np.concatenate(uv) if tex is not None else None, tex)
        for tex, p, c, uv in parts.values()
    ]


def _texels(house: "House", texture) -> np.ndarray:
    """(h, w, 3) uint8 sRGB texels of a ``Material.texture`` (path or PIL image)."""
    from PIL import Image

    if isinstance(texture, (str, Path)):
        try:
            with Image.open(texture) as image:
                return np.asarray(image.convert("RGB"))
        except (OSError, ValueError) as e:
            raise HouseError(house.id, str(texture), f"cannot read texture ({e})") from None
    return np.asarray(texture.convert("RGB"))


# ---------------------------------------------------------------------------------------
# pyrender and EGL


@functools.cache
def _gl() -> SimpleNamespace:
    """pyrender, PyOpenGL's GL and EGL, and the pyrender subclasses below.

    Imported on first use, as pyrender is optional. PyOpenGL picks its platform from
    ``PYOPENGL_PLATFORM`` when first imported, and pyrender's EGL module switches it to EGL.
    """
    platform = os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    if platform != "egl":
        raise SceneforgeError(
            f"PYOPENGL_PLATFORM is {platform!r}, but sceneforge renders through EGL: unset it or set it to 'egl'"
        )
    try:
        import pyrender
        from pyrender.platforms import egl  # installs PyOpenGL's EGL platform, even over an earlier one
    except ModuleNotFoundError as e:
        raise MissingDependencyError(e.name or "pyrender", "RGB rendering", INSTALL_RENDER) from None
    except (ImportError, OSError):  # PyOpenGL cannot load libEGL
        raise MissingDependencyError("libEGL", "RGB rendering", INSTALL_EGL) from None
    from OpenGL import EGL, GL
    from OpenGL.error import Error as GLError

    class FramebufferRenderer(pyrender.Renderer):
        """pyrender's renderer with a choice of samples per pixel for the offscreen framebuffer.

        pyrender 0.1.45 hard-codes ``glRenderbufferStorageMultisample(..., 4, ...)`` for the
        framebuffer it draws into, then blits it into a single-sample one to read it back.
        With ``samples=0`` the storage of the drawn-into renderbuffers is re-specified
        single-sampled right after pyrender creates them (their framebuffer attachments stay
        valid); the blit is then an exact copy.
        """

        def __init__(self, width: int, height: int, samples: int):
            super().__init__(width, height)
            self.samples = samples

        def _configure_main_framebuffer(self):
            fresh = self._main_fb_dims != (self.viewport_width, self.viewport_height)
            super()._configure_main_framebuffer()
            if fresh and self.samples != 4:
                for buffer, fmt in ((self._main_cb_ms, GL.GL_RGBA), (self._main_db_ms, GL.GL_DEPTH_COMPONENT24)):
                    GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, buffer)
                    GL.glRenderbufferStorageMultisample(
                        GL.GL_RENDERBUFFER, self.samples, fmt, self.viewport_width, self.viewport_height
                    )

    class IntrinsicsCamera(pyrender.IntrinsicsCamera):
        """pyrender's intrinsics camera plus the skew of ``K``."""

        skew = 0.0

        def get_projection_matrix(self, width=None, height=None):
            P = super().get_projection_matrix(width, height)
            # OpenCV y points down and OpenGL y up: the skew term changes sign
            P[0, 1] = -2.0 * self.skew / width
            return P

    class Platform(egl.EGLPlatform):
        """pyrender's EGL context, released without ``eglTerminate``: the display of a device
        is one per process, and terminating it would kill every other renderer's context."""

        def delete_context(self):
            if self._egl_display is not None and self._egl_context is not None:
                EGL.eglMakeCurrent(self._egl_display, EGL.EGL_NO_SURFACE, EGL.EGL_NO_SURFACE, EGL.EGL_NO_CONTEXT)
                EGL.eglDestroyContext(self._egl_display, self._egl_context)
            self._egl_context = None

    return SimpleNamespace(pyrender=pyrender, egl=egl, GL=GL, GLError=GLError, Renderer=FramebufferRenderer,
                           IntrinsicsCamera=IntrinsicsCamera, Platform=Platform)


@dataclass(frozen=True)
class EGLDevice:
    """An EGL device: its index (``gpu=``/``EGL_DEVICE_ID``) and DRM device file (None for
    Mesa's software device)."""

    index: int
    drm_file: str | None

    @property
    def kind(self) -> str:
        return "software" if self.drm_file is None else "gpu"


def _devices() -> list[tuple[EGLDevice, object]]:
    """This machine's EGL devices, each with pyrender's handle of it."""
    egl = _gl().egl
    try:
        found = egl.query_devices()
    except RuntimeError:  # no EGL_EXT_device_enumeration: only the default display
        return [(EGLDevice(0, None), egl.EGLDevice(None))]
    return [(EGLDevice(i, d.name), d) for i, d in enumerate(found)]


def egl_devices() -> list[EGLDevice]:
    """The EGL devices of this machine (raises :class:`MissingDependencyError` without libEGL)."""
    return [device for device, _ in _devices()]


def _pick_device(gpu: int | None) -> tuple[EGLDevice, object]:
    """The device to render on (see the module docstring) and pyrender's handle of it."""
    devices = _devices()
    if not devices:
        raise MissingDependencyError("an EGL driver", "RGB rendering (EGL lists no device)", INSTALL_EGL)
    if gpu is None and os.environ.get("EGL_DEVICE_ID", "").strip():
        try:
            gpu = int(os.environ["EGL_DEVICE_ID"])
        except ValueError:
            raise SceneforgeError(
                f"EGL_DEVICE_ID must be a device index, got {os.environ['EGL_DEVICE_ID']!r}"
            ) from None
    if gpu is None:
        return next((d for d in devices if d[0].drm_file is not None), devices[0])
    if not 0 <= gpu < len(devices):
        listed = ", ".join(f"{d.index} ({d.kind})" for d, _ in devices)
        raise SceneforgeError(f"EGL device {gpu} does not exist; this machine has {listed}")
    return devices[gpu]


class Renderer:
    """Offscreen renderer of house views: RGB and z-buffer depth, pixel-aligned with the layers.

    width, height : image size in pixels; every camera must have it
    gpu           : EGL device index; None = ``$EGL_DEVICE_ID``, else the first GPU, else
                    Mesa's software device
    antialias     : 4× multisampling (pyrender's default); off by default so that pixels
                    sample their centres like the ray tracer (see the module docstring)
    config        : lighting and background

    Keeps the GL scene of the last house it rendered (compared by identity: do not modify a
    house between renders) and rebuilds it, freeing the old one, when the house changes.
    One OpenGL context per renderer; use it from one thread. Call :meth:`close` (or use it as
    a context manager) to free the context.
    """

    def __init__(self, width: int, height: int, gpu: int | None = None, antialias: bool = False,
                 config: RenderConfig | None = None):
        if int(width) < 1 or int(height) < 1:
            raise ValueError(f"image size must be positive, got {width}×{height}")
        gl = _gl()
        self.width, self.height = int(width), int(height)
        self.antialias = bool(antialias)
        self.config = config or RenderConfig()
        self.device, handle = _pick_device(gpu)
        self._platform = gl.Platform(self.width, self.height, device=handle)
        try:
            self._platform.init_context()
        except (AssertionError, RuntimeError, OSError, gl.GLError):  # pyrender asserts EGL calls
            raise MissingDependencyError(
                "a working EGL driver",
                f"RGB rendering (no OpenGL 4.1 context on EGL device {self.device.index}, {self.device.kind})",
                INSTALL_EGL,
            ) from None
        # pyrender uploads tightly packed RGB textures and reads back RGB rows of any width
        gl.GL.glPixelStorei(gl.GL.GL_UNPACK_ALIGNMENT, 1)
        gl.GL.glPixelStorei(gl.GL.GL_PACK_ALIGNMENT, 1)
        self._gl = gl.Renderer(self.width, self.height, samples=4 if self.antialias else 0)
        self._house: House | None = None
        self._scene = None
        self._camera_node = None

    # -- public API ---------------------------------------------------------------------

    def render(self, house: "House", camera: "Camera") -> np.ndarray:
        """(H, W, 3) uint8 sRGB image of ``house`` seen from ``camera``."""
        flags = self._prepare(house, camera)
        color, _ = self._gl.render(self._scene, flags | _gl().pyrender.RenderFlags.FLAT)
        return np.array(color, dtype=np.uint8)

    def depth(self, house: "House", camera: "Camera") -> np.ndarray:
        """(H, W) float32 planar depth (camera z, metres) of the z-buffer; NaN where nothing.

        Single-sampled, this is the first hit of the ray through each pixel centre (the
        layers' ``traditional_depth`` up to the depth buffer's resolution, see :data:`NEAR`);
        with ``antialias`` it comes from one of the four samples of each pixel.
        """
        flags = self._prepare(house, camera)
        depth = np.array(self._gl.render(self._scene, flags | _gl().pyrender.RenderFlags.DEPTH_ONLY),
                         dtype=np.float32)
        depth[depth <= 0] = np.nan  # pyrender writes 0 where the depth buffer stayed clear
        return depth

    def gl_info(self) -> dict[str, str]:
        """The OpenGL vendor, renderer and version strings of this renderer's context."""
        GL = _gl().GL
        self._platform.make_current()
        return {name.lower(): GL.glGetString(getattr(GL, f"GL_{name}")).decode(errors="replace")
                for name in ("VENDOR", "RENDERER", "VERSION")}

    def close(self) -> None:
        """Free the GL scene, shaders, framebuffers and the context. Idempotent."""
        if self._platform is None:
            return
        self._platform.make_current()
        self._gl.delete()
        self._platform.delete_context()
        self._platform = self._gl = self._scene = self._house = self._camera_node = None

    def __enter__(self) -> "Renderer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- internals ----------------------------------------------------------------------

    def _prepare(self, house: "House", camera: "Camera") -> int:
        """Make the context current, the scene that of ``house`` and the camera ``camera``;
        return the render flags every pass uses."""
        if self._platform is None:
            raise SceneforgeError("the renderer is closed")
        if camera.shape != (self.height, self.width):
            raise ValueError(
                f"camera is {camera.width}×{camera.height} but the renderer renders {self.width}×{self.height}; "
                "use camera.resized()"
            )
        self._platform.make_current()
        if house is not self._house:
            self._build_scene(house)
        cam = self._camera_node.camera
        K = camera.K
        cam.fx, cam.fy, cam.cx, cam.cy, cam.skew = K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1]
        self._scene.set_pose(self._camera_node, opencv_to_opengl(camera.cam_to_world))
        RenderFlags = _gl().pyrender.RenderFlags
        return RenderFlags.OFFSCREEN | RenderFlags.SKIP_CULL_FACES

    def _build_scene(self, house: "House") -> None:
        """Replace the GL scene by one of ``house``, freeing the previous one's GL objects first."""
        gl = _gl()
        pyrender = gl.pyrender
        if self._scene is not None:
            # pyrender frees the GL objects of whatever its context holds that a scene lacks
            self._gl._update_context(pyrender.Scene(), pyrender.RenderFlags.NONE)
        self._scene = self._house = None
        primitives = []
        for batch in shade_house(house, self.config):  # one batch per texture
            texture = None
            if batch.texture is not None:
                texture = pyrender.Texture(source=_texels(house, batch.texture), source_channels="RGB")
            material = pyrender.MetallicRoughnessMaterial(
                baseColorFactor=(1.0, 1.0, 1.0, 1.0), baseColorTexture=texture, doubleSided=True
            )
            primitives.append(pyrender.Primitive(positions=batch.positions, color_0=batch.colors,
                                                 texcoord_0=batch.uv, material=material))
        scene = pyrender.Scene(bg_color=(*self.config.background, 1.0), ambient_light=(0.0, 0.0, 0.0))
        if primitives:
            scene.add(pyrender.Mesh(primitives=primitives))
        self._camera_node = scene.add(gl.IntrinsicsCamera(1.0, 1.0, 0.0, 0.0, znear=NEAR, zfar=FAR))
        self._scene, self._house = scene, house
