"""Rasterised RGB (and z-buffer depth) of house views with pyrender through EGL (docs/spec.md §8).

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

Look. Every face group of every instance is drawn with its own material
(``Instance.materials``): linear base colour × the sRGB texture decoded to linear (with
the material's wrapping, bilinear and mipmapped) × the vertex colours, opaque (alpha is
ignored, as the depth layers see glass too; only a glazed window's glass is left out, below).
Shading is per pixel, by pyrender's shader with the
house's lights (:mod:`sceneforge.render.lights`: lamps, windows, a fallback per room, in
lumens and candela, 1/d² falloff; windows daylight-coloured) plus each room's indirect light
(``ambient`` × its flux over its surface × ρ / (1 − ρ), ρ its mean albedo).
The shader is pyrender's own with seven changes made when it is loaded
(:func:`_mesh_shader`): Lambertian (the houses' materials are diffuse colours, and the
path tracer shades them so too), a face seen from behind is shaded with its normal turned to the
viewer (faces have no consistent winding in real houses), no light is nearer than
``light_min_distance``, a spot light (a window) falls off as cos θ inside its cone (a
Lambertian panel's far field), emission is added once (pyrender squares the factor), and
the output is the linear radiance itself, into a float framebuffer; and its light loops
are not unrolled (:data:`_LOOP_PATCHES`). Every view's radiance then goes through the
exposure and tone-mapping step both modes share (:func:`sceneforge.render.tonemap.tonemap`),
applied where it was drawn (see "Tone mapping" below). A window with glass (a face group
of opacity below 1) is drawn without its glass (in the RGB; the z-buffer of
:meth:`Renderer.depth` has it, and not the dome, as the layers do), its frame lit like any
surface, and through it the outdoors shows: a dome around the house with the radiance of
:mod:`sceneforge.render.sky` × ``outdoors_seen`` as vertex colours (unlit); other windows are drawn emitting
the outdoors' mean radiance.
A room's geometry is one pyrender mesh lit by that room's lights only (and those of a room
drawn over the same space, :func:`~sceneforge.render.lights.light_rooms`; up to
:data:`MAX_LIGHTS` of each kind, nearest its centre first): light does not leak through
walls, and every fragment evaluates only its room's few lights. Its faces without a
texture or emission are one draw (their base colours in the vertex colours).
Shadows (``RenderConfig.shadows``, off by default) come from shadow maps of the spot
lights (windows); point lights (lamps, fallbacks) cast none: pyrender 0.1.45 raises
"Point light shadows not implemented" (``Renderer._bind_lighting``).

Tone mapping. :meth:`Renderer.render` applies the exposure, tone curve and sRGB encoding
of :func:`~sceneforge.render.tonemap.tonemap` on the GL device, in two full-screen passes
over the resolved radiance (:class:`_TonePass`): one writes each pixel's luminance, whose
median (the automatic exposure) numpy takes from a single float channel; the other writes
the bytes into an RGBA8 target, and only those (3 bytes a pixel) are read back, instead of
16 bytes of float RGBA and numpy's float32 passes over them. The arithmetic is numpy's,
float32 step for step (``precise``: no fused multiply-adds), the luminance's two fused
multiply-adds (OpenBLAS's) emulated in double and the sRGB encoding made exact by 255
thresholds (:func:`~sceneforge.render.tonemap.encoding_thresholds`), so the bytes are
``tonemap(render_linear(...))``'s: identical on Mesa's llvmpipe (the toy houses in
tests/test_render.py; the breakfast room too, at 1280×960); a device whose division is not
correctly rounded (the curves' divisions) may put a value one level off where
it falls within a float32 rounding of one of the thresholds. ``gpu_tonemap=False`` reads
the float radiance back and applies numpy's :func:`~sceneforge.render.tonemap.tonemap`.
On llvmpipe the passes run on the CPU like the rest, in about numpy's CPU time but on every
core (docs/benchmarks.md, "Raster per-pixel work").

Depth pre-pass. pyrender draws the farthest meshes first, so a pixel's shader runs once
for every surface that is nearer than what was drawn before it (1.5–4 times per pixel on
the toy houses). A colour render therefore draws the z-buffer first (pyrender's depth-only
shader, every face from both sides) and then shades with depth writes off, a fragment
passing only at its pixel's depth and only the first such one (a stencil), which is the
fragment pyrender's single ``GL_LESS`` pass keeps: the same bytes (tests/test_render.py,
coincident surfaces included), each pixel shaded once. It costs a second draw of every
triangle, so it is used where the scene has at most a quarter as many triangles as the
frame has pixels (``FramebufferRenderer.depth_prepass``: ``"auto"``, True or False).

The same view always gives the same bytes on the same machine (GL and driver); across
GPUs and drivers, shading and texture filtering may differ by a few levels of 8-bit
rounding, while which surface each pixel shows (depth, silhouettes) does not.

Devices. ``gpu=None`` picks ``$EGL_DEVICE_ID`` when set, else the first EGL device backed
by a DRM device (a GPU), else the first one (Mesa's software llvmpipe device). A missing
libEGL or EGL driver is reported as a :class:`~sceneforge.errors.MissingDependencyError`
naming what to install.
"""

from __future__ import annotations

import atexit
import ctypes
import functools
import os
import shutil
import tempfile
import typing
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import TYPE_CHECKING

import numpy as np

from ..cameras import opencv_to_opengl
from ..errors import HouseError, MissingDependencyError, SceneforgeError
from .lights import WINDOW_CONE, Light, glazed_windows, house_lights, light_rooms, room_ambient, room_bounds
from .sky import dome as sky_dome
from .tonemap import TONES, ToneMapped

if TYPE_CHECKING:
    from ..cameras import Camera
    from ..houses.model import House

#: near and far clipping planes, metres. With a 24-bit depth buffer the depth resolution
#: is about z² / (NEAR · 2²⁴): 0.1 mm at 10 m. Surfaces nearer than NEAR to the camera are
#: clipped; FAR is beyond any house.
NEAR, FAR = 0.05, 1000.0
#: lights of each kind (point, spot) that light one room's geometry
MAX_LIGHTS = 8
#: pyrender's diffuse term is the base colour × (1 - 0.04) / π per unit of light; the
#: lights are scaled by 1 / (1 - 0.04) so that it is the Lambertian base colour / π
_DIFFUSE = 1.0 - 0.04

INSTALL_RENDER = "pip install 'sceneforge[render]'"
#: Debian/Ubuntu packages of libEGL and Mesa's EGL driver with its software rasteriser
#: (a GPU driver with EGL, e.g. NVIDIA's, works as well)
INSTALL_EGL = "sudo apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri"


@dataclass(frozen=True)
class RenderConfig:
    """How rendered views look (lights: :mod:`.lights`; exposure and tone: :mod:`.tonemap`).
    Field docs become the config schema's descriptions."""

    #: raster only: indirect light, as a multiple of a room's integrating-sphere estimate
    #: (its lights' flux over the surface of its bounds × ρ / (1 - ρ), ρ the mean albedo of its
    #: surfaces; the path tracer traces it)
    ambient: float = 1.0
    #: luminous flux of each lamp and of each room's fallback light, lumens (800: a 60 W
    #: incandescent bulb); light falls off as 1/d²
    lamp_power: float = 800.0
    #: mean radiance of the outdoors seen through a window, cd/m² (a clear sky over a sunlit
    #: ground, daylight-coloured); every window lights its room as a panel of this radiance,
    #: and glazed windows show the outdoors through their glass (0: windows give no light)
    sky_luminance: float = 1000.0
    #: the outdoors as the camera sees it through a window's glass, as a fraction of the
    #: radiance with which it lights the rooms (it changes no light): 0.1 shows it about as
    #: bright beside the room as PBRS's photographed outdoors (a window's median luminance
    #: 2-3× the frame's), 1 as bright as it lights them (5-50× the frame's: mostly white
    #: after the tone curve)
    outdoors_seen: float = 0.1
    #: the fallback light of a room without lamps or windows hangs this far below the top
    #: of its room's bounds, metres
    light_below_ceiling: float = 0.3
    #: nearer than this, a surface receives the light of this distance, metres
    light_min_distance: float = 0.3
    #: raster only: shadows of the window lights (shadow maps; point lights cast none)
    shadows: bool = False
    #: exposure (radiance × it before the tone curve); None: automatic per view, the
    #: median luminance of the pixels that see something lands at 18 % grey
    exposure: float | None = None
    #: tone curve after the exposure: ``soft`` (linear, as PBRS's images, up to 0.8 = 4.4×
    #: mid-grey, then a shoulder that rolls highlights off towards white instead of clipping
    #: them), ``aces`` (filmic: a toe that darkens dark surfaces, white at about 40× mid-grey)
    #: or ``clip`` (none: exposed values clipped to [0, 1])
    tone: typing.Literal["soft", "aces", "clip"] = "soft"
    #: raster only, for checking materials: no lights, every surface shows ``ambient`` × its
    #: base colour as radiance (with ``exposure`` 1 and ``tone`` clip: exactly its colour)
    flat: bool = False
    #: sRGB colour (0..1) of pixels that see nothing
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    #: pathtraced with denoising only: the fraction of the path tracer's own noise kept
    #: (denoised + grain × (raw − denoised)); 0.05 at 64 spp leaves walls about as grainy as
    #: PBRS's renders (0: the denoised frame)
    grain: float = 0.05

    def __post_init__(self):
        for name in ("ambient", "lamp_power", "sky_luminance", "outdoors_seen", "light_below_ceiling"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if not 0 <= self.grain <= 1:
            raise ValueError(f"grain must be in [0, 1], got {self.grain}")
        if not self.light_min_distance > 0:
            raise ValueError(f"light_min_distance must be > 0, got {self.light_min_distance}")
        if self.exposure is not None and not self.exposure > 0:
            raise ValueError(f"exposure must be > 0 (or None: automatic), got {self.exposure}")
        if self.tone not in TONES:
            raise ValueError(f"tone must be one of {', '.join(TONES)}, got {self.tone!r}")
        if len(self.background) != 3 or not all(0 <= c <= 1 for c in self.background):
            raise ValueError(f"background must be 3 numbers in [0, 1], got {self.background}")
        # a list read back from a saved config would make the config unhashable
        object.__setattr__(self, "background", tuple(float(c) for c in self.background))


def check_camera_size(camera: "Camera", width: int, height: int) -> None:
    """Raise ValueError unless ``camera`` has the ``width``×``height`` a renderer was made for."""
    if camera.shape != (height, width):
        raise ValueError(f"camera is {camera.width}×{camera.height} but the renderer renders {width}×{height}; "
                         "use camera.resized()")


# ---------------------------------------------------------------------------------------
# The house as draw batches: pure numpy, no GL


@dataclass(frozen=True, eq=False)
class Batch:
    """The triangles of one room that share one material (texture, wrapping and colour).

    room      : the ``Instance.room_id`` of its instances
    origin    : (3,) float64   world position of the batch's mesh node (its room's centre)
    positions : (3m, 3) float32  relative to ``origin``, three unshared corners per triangle
    normals   : (3m, 3) float32  the face normal at each corner (flat shading)
    colors    : (3m, 4) float32  linear vertex colours, or None
    uv        : (3m, 2) float32  texture coordinates (OpenGL convention), or None
    material  : the :class:`~sceneforge.houses.model.Material` (its texture None when the
                batch has no uv)
    emission  : radiance its faces emit, cd/m² (a window's sky; 0 for every other batch)
    """

    room: str | None
    origin: np.ndarray
    positions: np.ndarray
    normals: np.ndarray
    colors: np.ndarray | None
    uv: np.ndarray | None
    material: object
    emission: float = 0.0


def _texture_key(texture) -> object:
    """What identifies a texture across instances: its resolved path, or the image object."""
    if texture is None:
        return None
    if isinstance(texture, (str, Path)):
        return str(Path(texture).resolve())
    return id(texture)


def house_batches(house: "House", emission: dict[int, float] | None = None,
                  exclude: frozenset[int] = frozenset(), see_through: frozenset[int] = frozenset()) -> list["Batch"]:
    """The house's face groups as draw batches: per room (in order of first instance), one
    per distinct material (in order of first use); instances without vertex colours and
    with them are apart, and so are emitting ones (``emission``: ``Instance.id`` → radiance,
    the windows of :func:`~sceneforge.render.lights.house_lights`); the instances of
    ``exclude`` (ids) are left out, and so are the translucent face groups (opacity < 1: the
    glass) of the instances of ``see_through``. An instance with a texture but no ``uv`` is
    drawn with its base colour only."""
    from dataclasses import replace

    centres = {room: 0.5 * (b[0] + b[1]) for room, b in room_bounds(house).items()}
    parts: dict[tuple, tuple[object, list, list, list, list]] = {}
    for inst in house.instances:
        if inst.id in exclude:
            continue
        tri = inst.vertices[inst.faces]
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
        group = inst.face_materials()
        for g, material in enumerate(inst.materials):
            if inst.id in see_through and material.base_color[3] < 1.0:
                continue
            faces = np.flatnonzero(group == g) if len(inst.materials) > 1 else slice(None)
            if inst.uv is None and material.texture is not None:
                material = replace(material, texture=None)
            key = (inst.room_id, tuple(float(c) for c in material.base_color), _texture_key(material.texture),
                   tuple(material.wrap) if material.texture is not None else None, inst.colors is not None,
                   float((emission or {}).get(inst.id, 0.0)))
            entry = parts.setdefault(key, (material, [], [], [], []))
            entry[1].append((tri[faces] - centres[inst.room_id]).reshape(-1, 3).astype(np.float32))
            entry[2].append(np.repeat(normal[faces], 3, axis=0).astype(np.float32))
            if inst.colors is not None:
                entry[3].append(inst.colors[inst.faces[faces]].reshape(-1, 4))
            if material.texture is not None:
                entry[4].append(inst.uv[inst.faces[faces]].reshape(-1, 2).astype(np.float32))
    return [
        Batch(key[0], centres[key[0]], np.concatenate(p), np.concatenate(n),
              np.concatenate(c).astype(np.float32) if c else None, np.concatenate(uv) if uv else None, material,
              key[5])
        for key, (material, p, n, c, uv) in parts.items()
    ]


def _glass_triangles(house: "House", glazed: frozenset[int]) -> np.ndarray:
    """(n, 3, 3) float64 world corners of the glass (face groups of opacity below 1) of the
    windows ``glazed``: what :func:`house_batches` leaves out of them."""
    out = [np.zeros((0, 3, 3))]
    for inst in house.instances:
        if inst.id not in glazed:
            continue
        group = inst.face_materials()
        clear = [g for g, m in enumerate(inst.materials) if m.base_color[3] < 1.0]
        out.append(inst.vertices[inst.faces[np.isin(group, clear)]])
    return np.concatenate(out)


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
# The shader

#: pyrender's mesh.frag text → sceneforge's (see the module docstring); each must occur once
_SHADER_PATCHES = (
    ("        vec3 diffuse_contrib = (1.0 - F) * c_diff / PI;\n        vec3 spec_contrib = F * G * D / (4.0 * nl * nv + 0.001);\n",
     "        vec3 diffuse_contrib = c_diff / PI;\n        vec3 spec_contrib = vec3(0.0);\n"),
    ("    vec3 n = normalize(get_normal());\n",
     "    vec3 n = normalize(get_normal());\n    if (!gl_FrontFacing) n = -n;\n"),
    ("        float dist = length(position - frag_position);\n",
     "        float dist = max(length(position - frag_position), LIGHT_MIN_DISTANCE);\n"),
    ("        attenuation = attenuation * attenuation * spot_lights[i].intensity;\n",
     "        attenuation = cd * step(0.0, cd * las + lao) * spot_lights[i].intensity;\n"),
    ("    color.xyz += emissive * material.emissive_factor;\n",
     "    color.xyz += emissive;\n"),
    ("    frag_color = clamp(vec4(pow(color.xyz, vec3(1.0/2.2)), color.a * base_color.a), 0.0, 1.0);\n",
     "    frag_color = vec4(max(color.xyz, vec3(0.0)), 1.0);\n"),
)
#: and the light loops' arrays indexed through min(): Mesa bounds a loop by the length of an
#: array its counter indexes and unrolls it, and llvmpipe then evaluates all MAX_LIGHTS
#: bodies of each kind for every fragment under a mask, lights or not (a 1280×960 toy-house
#: frame with no light at all, ``flat``: 177 ms, against 37 ms with the loops taken out).
#: Indexed so, the loops stay loops; the radiance is the same to the bit
_LOOP_PATCHES = tuple(
    (f"    for (int i = 0; i < n_{kind}_lights; i++) {{\n",
     f"    for (int k = 0; k < n_{kind}_lights; k++) {{\n        int i = min(k, MAX_{kind.upper()}_LIGHTS - 1);\n")
    for kind in ("directional", "point", "spot"))


@functools.cache
def _shader_dir() -> Path:
    """A folder of this process for the patched shaders (removed at exit)."""
    path = Path(tempfile.mkdtemp(prefix="sceneforge-shaders-"))
    atexit.register(shutil.rmtree, path, ignore_errors=True)
    return path


@functools.cache
def _mesh_shader(min_distance: float) -> str:
    """Path of pyrender's mesh.frag with :data:`_SHADER_PATCHES` and :data:`_LOOP_PATCHES` applied."""
    pyrender = _gl().pyrender

    text = (Path(pyrender.__file__).parent / "shaders" / "mesh.frag").read_text()
    for old, new in _SHADER_PATCHES + _LOOP_PATCHES:
        if text.count(old) != (2 if "dist" in old else 1):
            raise SceneforgeError(f"pyrender {pyrender.__version__}'s mesh.frag is not the one sceneforge "
                                  f"patches (install pyrender 0.1.45): no {old.strip()!r}")
        text = text.replace(old, new)
    text = text.replace("#version 330 core\n", f"#version 330 core\n#define LIGHT_MIN_DISTANCE {min_distance!r}\n", 1)
    path = _shader_dir() / f"mesh_{len(list(_shader_dir().iterdir()))}.frag"
    path.write_text(text)
    return str(path)


# ---------------------------------------------------------------------------------------
# Exposure, tone curve and sRGB encoding on the GPU

#: a triangle that covers the viewport: (-1, -1), (3, -1), (-1, 3), from gl_VertexID alone
_FULL_SCREEN_VERT = """#version 410 core
void main() {
    gl_Position = vec4(float((gl_VertexID & 1) << 2) - 1.0, float((gl_VertexID & 2) << 1) - 1.0, 0.0, 1.0);
}
"""

#: what both passes start with: this fragment's radiance, rows in image order
_PIXEL = """#version 410 core
uniform sampler2D radiance;  // the resolved float framebuffer: linear RGB, alpha > 0 where a surface was drawn

// the pixel of this fragment in image order (row 0 at the top: the rows read back need no
// flip), NaN and infinite radiance replaced by 0 (tonemap's nan_to_num)
vec4 pixel() {
    ivec2 p = ivec2(gl_FragCoord.xy);
    vec4 c = texelFetch(radiance, ivec2(p.x, textureSize(radiance, 0).y - 1 - p.y), 0);
    c.rgb = mix(c.rgb, vec3(0.0), isnan(c.rgb));
    c.rgb = mix(c.rgb, vec3(0.0), isinf(c.rgb));
    return c;
}
"""

#: pass 1 (automatic exposure only): the Rec. 709 luminance of every seen pixel, -inf elsewhere
_LUMINANCE_FRAG = _PIXEL + """
uniform vec3 weights;  // tonemap.LUMINANCE in float32
out float luminance;

void main() {
    vec4 c = pixel();
    // numpy's float32 (H, W, 3) @ (3,) (OpenBLAS's sgemv on x86-64): r w0, then two fused
    // multiply-adds, g w1 and b w2. GLSL's fma() need not be fused (llvmpipe's is not): in
    // double, the product of two floats is exact and the sum is rounded to float after
    // double (off from a fused float32 one only where that double rounding meets a tie,
    // about once in 2^29). `precise`: no other contraction or reordering.
    precise float l = c.r * weights.r;
    precise double t = double(c.g) * double(weights.g) + double(l);
    l = float(t);
    t = double(c.b) * double(weights.b) + double(l);
    l = float(t);
    luminance = c.a > 0.0 ? l : uintBitsToFloat(0xff800000u);
}
"""

#: pass 2: the bytes of tonemap.tonemap
_TONE_FRAG = _PIXEL + """
uniform float exposure;      // float32(e), as tonemap multiplies
uniform int tone;            // 0: clip, 1: the ACES fit, 2: soft
uniform vec4 curve;          // a, b, c, d of tonemap.ACES in float32
uniform float curve_e;       // e
uniform float knee;          // soft: tonemap.SOFT_KNEE in float32
uniform float knee_span;     // soft: 1 - knee, in float32 as tonemap subtracts
uniform float bounds[257];   // [0] -1, [j] tonemap.encoding_thresholds()[j - 1], [256] 2
uniform vec3 background;     // the bytes of pixels that see nothing
out vec4 srgb;               // bytes / 255 into an RGBA8 target: exactly the bytes

void main() {
    vec4 c = pixel();
    // tonemap's float32 steps in its order; `precise`: no fused multiply-adds
    precise vec3 x = max(c.rgb * exposure, vec3(0.0));
    precise vec3 y = x;
    if (tone == 1) {
        y = (x * (curve.x * x + curve.y)) / (x * (curve.z * x + curve.w) + curve_e);
    } else if (tone == 2) {
        precise vec3 over = max(x - knee, vec3(0.0));
        precise vec3 shoulder = knee + over / (1.0 + over / knee_span);
        y = mix(shoulder, x, lessThanEqual(x, vec3(knee)));
    }
    y = min(y, vec3(1.0));
    // sRGB byte: pow's estimate, within a level, then made exact by the thresholds (the
    // byte is the number of thresholds at or below y)
    vec3 s = mix(12.92 * y, 1.055 * pow(y, vec3(1.0 / 2.4)) - 0.055, greaterThan(y, vec3(0.0031308)));
    ivec3 q = clamp(ivec3(roundEven(255.0 * s)), 0, 255);
    for (int k = 0; k < 3; k++) {
        q[k] += int(y[k] >= bounds[q[k] + 1]) - int(y[k] < bounds[q[k]]);
    }
    srgb = c.a > 0.0 ? vec4(vec3(q) / 255.0, 1.0) : vec4(background / 255.0, 1.0);
}
"""


class _TonePass:
    """:func:`sceneforge.render.tonemap.tonemap` as two full-screen GL passes over the
    resolved radiance texture, for one renderer's context and size (see :meth:`apply`).

    The luminance pass (automatic exposure only) writes each pixel's float32 luminance, or
    -inf where nothing is seen, into an R32F target; it is read back (4 bytes per pixel, a
    quarter of the RGBA float image) and its median taken with numpy
    (:func:`~sceneforge.render.tonemap.exposure_of_luminance`: the same values and
    arithmetic as :func:`~sceneforge.render.tonemap.auto_exposure`). The tone pass writes
    the bytes into an RGBA8 target, read back as RGB bytes: the image.
    """

    def __init__(self, width: int, height: int, config: RenderConfig):
        from .tonemap import ACES, LUMINANCE, SOFT_KNEE, background_bytes, encoding_thresholds

        GL = _gl().GL
        self.width, self.height = width, height
        self.exposure: float | None = None  # of the last view
        self._programs, self._fbs, self._rbs = [], [], []
        self._luminance = self._program(_LUMINANCE_FRAG)
        self._tone = self._program(_TONE_FRAG)
        self._vao = GL.glGenVertexArrays(1)  # core profile: drawing needs one, even empty
        self._luminance_fb = self._target(GL.GL_R32F)
        self._tone_fb = self._target(GL.GL_RGBA8)
        f32 = np.float32
        GL.glUseProgram(self._luminance)
        GL.glUniform3f(self._uniform(self._luminance, "weights"), *(float(w) for w in LUMINANCE.astype(f32)))
        GL.glUseProgram(self._tone)
        GL.glUniform1i(self._uniform(self._tone, "tone"), {"clip": 0, "aces": 1, "soft": 2}[config.tone])
        GL.glUniform1f(self._uniform(self._tone, "knee"), float(f32(SOFT_KNEE)))
        GL.glUniform1f(self._uniform(self._tone, "knee_span"), float(f32(1.0) - f32(SOFT_KNEE)))
        a, b, c, d, e = (float(f32(v)) for v in ACES)
        GL.glUniform4f(self._uniform(self._tone, "curve"), a, b, c, d)
        GL.glUniform1f(self._uniform(self._tone, "curve_e"), e)
        bounds = np.concatenate([[-1.0], encoding_thresholds(), [2.0]]).astype(f32)
        GL.glUniform1fv(self._uniform(self._tone, "bounds"), 257, bounds)
        GL.glUniform3f(self._uniform(self._tone, "background"), *(float(v) for v in background_bytes(config.background)))
        GL.glUseProgram(0)
        self._exposure_loc = self._uniform(self._tone, "exposure")

    def apply(self, radiance_texture, exposure: float | None) -> np.ndarray:
        """(H, W, 3) uint8: :func:`~sceneforge.render.tonemap.tonemap` of the radiance in
        ``radiance_texture`` (RGBA32F, OpenGL's bottom-up rows, alpha > 0 where seen) with
        ``exposure`` (None: automatic) and this pass's tone curve and background."""
        from .tonemap import exposure_of_luminance

        GL = _gl().GL
        W, H = self.width, self.height
        GL.glViewport(0, 0, W, H)
        for cap in (GL.GL_DEPTH_TEST, GL.GL_BLEND, GL.GL_CULL_FACE):
            GL.glDisable(cap)
        GL.glActiveTexture(GL.GL_TEXTURE0)
        GL.glBindTexture(GL.GL_TEXTURE_2D, radiance_texture)
        GL.glBindVertexArray(self._vao)
        if exposure is None:
            luminance = np.empty((H, W), np.float32)
            self._draw(self._luminance, self._luminance_fb)
            GL.glReadPixels(0, 0, W, H, GL.GL_RED, GL.GL_FLOAT, luminance.ctypes.data)
            exposure = exposure_of_luminance(luminance[luminance > -np.inf])
        self.exposure = float(exposure)
        GL.glUseProgram(self._tone)
        GL.glUniform1f(self._exposure_loc, float(np.float32(exposure)))
        rgb = np.empty((H, W, 3), np.uint8)
        self._draw(self._tone, self._tone_fb)
        GL.glReadPixels(0, 0, W, H, GL.GL_RGB, GL.GL_UNSIGNED_BYTE, rgb.ctypes.data)
        GL.glBindVertexArray(0)
        GL.glBindTexture(GL.GL_TEXTURE_2D, 0)
        GL.glUseProgram(0)
        return rgb

    def delete(self) -> None:
        """Free the programs, targets and vertex array (the context must be current)."""
        GL = _gl().GL
        for program in self._programs:
            GL.glDeleteProgram(program)
        if self._fbs:
            GL.glDeleteFramebuffers(len(self._fbs), self._fbs)
            GL.glDeleteRenderbuffers(len(self._rbs), self._rbs)
        GL.glDeleteVertexArrays(1, [self._vao])
        self._programs, self._fbs, self._rbs = [], [], []

    def _draw(self, program, framebuffer) -> None:
        GL = _gl().GL
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, framebuffer)
        GL.glUseProgram(program)
        GL.glDrawArrays(GL.GL_TRIANGLES, 0, 3)
        GL.glBindFramebuffer(GL.GL_READ_FRAMEBUFFER, framebuffer)

    def _program(self, fragment: str):
        GL = _gl().GL
        shaders = []
        for kind, text in ((GL.GL_VERTEX_SHADER, _FULL_SCREEN_VERT), (GL.GL_FRAGMENT_SHADER, fragment)):
            shader = GL.glCreateShader(kind)
            GL.glShaderSource(shader, text)
            GL.glCompileShader(shader)
            if not GL.glGetShaderiv(shader, GL.GL_COMPILE_STATUS):
                raise SceneforgeError(f"the tone-mapping shader does not compile: {GL.glGetShaderInfoLog(shader)!r}")
            shaders.append(shader)
        program = GL.glCreateProgram()
        for shader in shaders:
            GL.glAttachShader(program, shader)
        GL.glLinkProgram(program)
        for shader in shaders:
            GL.glDeleteShader(shader)
        if not GL.glGetProgramiv(program, GL.GL_LINK_STATUS):
            raise SceneforgeError(f"the tone-mapping shader does not link: {GL.glGetProgramInfoLog(program)!r}")
        self._programs.append(program)
        GL.glUseProgram(program)
        GL.glUniform1i(self._uniform(program, "radiance"), 0)
        return program

    def _uniform(self, program, name: str) -> int:
        location = _gl().GL.glGetUniformLocation(program, name)
        if location < 0:
            raise SceneforgeError(f"the tone-mapping shader has no uniform {name!r}")
        return location

    def _target(self, fmt):
        """A framebuffer of one colour renderbuffer of ``fmt``, the renderer's size."""
        GL = _gl().GL
        rb = GL.glGenRenderbuffers(1)
        GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, rb)
        GL.glRenderbufferStorage(GL.GL_RENDERBUFFER, fmt, self.width, self.height)
        fb = GL.glGenFramebuffers(1)
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, fb)
        GL.glFramebufferRenderbuffer(GL.GL_FRAMEBUFFER, GL.GL_COLOR_ATTACHMENT0, GL.GL_RENDERBUFFER, rb)
        if GL.glCheckFramebufferStatus(GL.GL_FRAMEBUFFER) != GL.GL_FRAMEBUFFER_COMPLETE:
            raise SceneforgeError("the tone-mapping framebuffer is incomplete")
        self._rbs.append(rb)
        self._fbs.append(fb)
        return fb


# ---------------------------------------------------------------------------------------
# pyrender and EGL


def import_pyrender():
    """pyrender, imported headless: the one place sceneforge imports it.

    pyrender imports its viewer, and with it pyglet, which loads Xlib (and fails without
    X11's libraries, as on a GPU server: "'NoneType' object has no attribute
    'XRenderFindVisualFormat'") unless told it is headless before. sceneforge never opens a
    window: it renders offscreen through EGL, so PyOpenGL (imported with pyrender) is told
    to use EGL too unless ``PYOPENGL_PLATFORM`` says otherwise (its default would be GLX,
    which loads X11's libGLX). Raises what the import raises.
    """
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    try:
        import pyglet
    except ModuleNotFoundError:  # a pyrender without its viewer's dependency: nothing to tell
        pass
    else:
        pyglet.options["headless"] = True
    import pyrender

    return pyrender


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
    from ..compressors import load_compressors

    load_compressors()  # before Mesa's libraries: see there
    try:
        pyrender = import_pyrender()
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

        def __init__(self, width: int, height: int, samples: int, mesh_shader: str):
            super().__init__(width, height)
            self.samples = samples
            self._program_cache = ShaderCache(mesh_shader)
            self._lit: dict = {}  # program → (scene, mesh node) whose lights it has
            #: the RGBA32F texture that holds the last frame's resolved radiance
            self.radiance_texture = None
            #: False: a colour render leaves the radiance in :attr:`radiance_texture` and
            #: returns None instead of reading it back
            self.read_radiance = True
            #: colour renders draw depth first, then shade each pixel once (:meth:`_forward_pass`):
            #: True, False, or "auto": when the scene has at most a quarter as many triangles
            #: as the frame has pixels (the pass draws every triangle again)
            self.depth_prepass = "auto"
            self._triangles: tuple = (None, 0)  # (scene, its triangle count)
            self._shading = False  # in the shading pass that follows a depth pre-pass

        def _bind_lighting(self, scene, program, node, flags):
            # Light uniforms depend on the scene and the mesh node only, and stay set in a
            # program: pyrender sets them again for every primitive of every frame, which is
            # most of a frame's time in Python. Shadow maps take texture units per primitive.
            shadows = flags & (pyrender.RenderFlags.SHADOWS_SPOT | pyrender.RenderFlags.SHADOWS_DIRECTIONAL)
            key = (scene, node)
            if not shadows and self._lit.get(program) == key:
                return
            super()._bind_lighting(RoomLights(scene, node), program, node, flags)
            self._lit[program] = None if shadows else key

        def _compute_max_n_lights(self, flags):
            # pyrender's 4 lights per kind are a texture-unit budget for shadow maps only
            counts = super()._compute_max_n_lights(flags)
            spot_shadows = flags & pyrender.RenderFlags.SHADOWS_SPOT
            return [counts[0], counts[1] if spot_shadows else MAX_LIGHTS, MAX_LIGHTS]

        def _configure_main_framebuffer(self):
            # linear HDR radiance needs a float colour buffer (pyrender's is 8-bit RGBA)
            fresh = self._main_fb_dims != (self.viewport_width, self.viewport_height)
            super()._configure_main_framebuffer()
            if fresh:
                W, H = self.viewport_width, self.viewport_height
                GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, self._main_cb)
                GL.glRenderbufferStorage(GL.GL_RENDERBUFFER, GL.GL_RGBA32F, W, H)
                for buffer, fmt in ((self._main_cb_ms, GL.GL_RGBA32F), (self._main_db_ms, GL.GL_DEPTH24_STENCIL8)):
                    GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, buffer)
                    GL.glRenderbufferStorageMultisample(GL.GL_RENDERBUFFER, self.samples, fmt, W, H)
                # the depth buffers carry a stencil (the shading pass's "first fragment wins");
                # the read-back one has the same format, as a depth blit needs
                GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, self._main_db)
                GL.glRenderbufferStorage(GL.GL_RENDERBUFFER, GL.GL_DEPTH24_STENCIL8, W, H)
                for fb, buffer in ((self._main_fb_ms, self._main_db_ms), (self._main_fb, self._main_db)):
                    GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, fb)
                    GL.glFramebufferRenderbuffer(GL.GL_FRAMEBUFFER, GL.GL_DEPTH_STENCIL_ATTACHMENT,
                                                 GL.GL_RENDERBUFFER, buffer)
                # the resolved colour is a texture, which the tone-mapping passes sample
                # (pyrender's renderbuffer, detached, keeps one texel)
                GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, self._main_cb)
                GL.glRenderbufferStorage(GL.GL_RENDERBUFFER, GL.GL_RGBA32F, 1, 1)
                self.radiance_texture = GL.glGenTextures(1)
                GL.glBindTexture(GL.GL_TEXTURE_2D, self.radiance_texture)
                GL.glTexImage2D(GL.GL_TEXTURE_2D, 0, GL.GL_RGBA32F, W, H, 0, GL.GL_RGBA, GL.GL_FLOAT, None)
                for name in (GL.GL_TEXTURE_MIN_FILTER, GL.GL_TEXTURE_MAG_FILTER):  # one level: complete
                    GL.glTexParameteri(GL.GL_TEXTURE_2D, name, GL.GL_NEAREST)
                GL.glBindTexture(GL.GL_TEXTURE_2D, 0)
                GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, self._main_fb)
                GL.glFramebufferTexture2D(GL.GL_FRAMEBUFFER, GL.GL_COLOR_ATTACHMENT0, GL.GL_TEXTURE_2D,
                                          self.radiance_texture, 0)

        def _forward_pass(self, scene, flags, seg_node_map=None):
            # A colour render in two passes: the z-buffer first (a depth-only shader: no
            # lights, no textures), then the shading pass, whose fragments pass only at the
            # z-buffer's depth, the first of them drawn (a stencil) winning as under
            # pyrender's GL_LESS: the same pixels, each shaded once. pyrender draws the
            # farthest meshes first, so without it a pixel is shaded 1.5-4 times (llvmpipe
            # runs the shader on the CPU). Not for translucent meshes (blending needs every
            # layer) or segmentation renders; a depth-only render is the first pass alone.
            RenderFlags = pyrender.RenderFlags
            if flags & RenderFlags.DEPTH_ONLY:
                # the z-buffer alone, both sides of every face: pyrender's depth-only pass
                # culls back faces whatever the flags, where the layers see both sides (a
                # window's glass seen from inside, its winding facing out)
                self._depth_pass(scene, flags)
                return self._read_main_framebuffer(scene, flags)
            if (not self._prepass_pays(scene) or flags & RenderFlags.SEG
                    or any(node.mesh.is_transparent for node in scene.mesh_nodes)):
                return super()._forward_pass(scene, flags, seg_node_map)
            self._depth_pass(scene, flags)
            self._shading = True
            try:
                return super()._forward_pass(scene, flags, seg_node_map)
            finally:
                self._shading = False
                GL.glDisable(GL.GL_STENCIL_TEST)
                GL.glDepthMask(GL.GL_TRUE)
                GL.glDepthFunc(GL.GL_LESS)

        def _prepass_pays(self, scene) -> bool:
            # it saves shading where surfaces overlap (pixels) and costs a second draw of
            # every triangle: on llvmpipe at 1280×960 a toy house (3,480 triangles) takes
            # 2.4× less with it, a 1 M-triangle room about the same, and at 320×240 the
            # room 40 % more (benchmarks/bench_render.py --per-pixel)
            if self.depth_prepass != "auto":
                return bool(self.depth_prepass)
            if self._triangles[0] is not scene:
                count = sum((p.indices.size // 3 if p.indices is not None else len(p.positions) // 3)
                            * (1 if p.poses is None else len(p.poses))
                            for node in scene.mesh_nodes for p in node.mesh.primitives)
                self._triangles = (scene, count)
            return 4 * self._triangles[1] <= self.viewport_width * self.viewport_height

        def _depth_pass(self, scene, flags):
            """The z-buffer of every mesh, both sides of every face, colour writes off."""
            self._configure_forward_pass_viewport(flags)  # depth test GL_LESS, depth writes on
            GL.glStencilMask(0xFF)
            GL.glClear(GL.GL_DEPTH_BUFFER_BIT | GL.GL_STENCIL_BUFFER_BIT)
            GL.glColorMask(GL.GL_FALSE, GL.GL_FALSE, GL.GL_FALSE, GL.GL_FALSE)
            GL.glDisable(GL.GL_CULL_FACE)
            GL.glPolygonMode(GL.GL_FRONT_AND_BACK, GL.GL_FILL)
            V, P = self._get_camera_matrices(scene)
            program = None
            try:
                for node in self._sorted_mesh_nodes(scene):  # pyrender's order
                    if not node.mesh.is_visible:
                        continue
                    pose = scene.get_pose(node)
                    for primitive in node.mesh.primitives:
                        program = self._get_primitive_program(primitive, flags | pyrender.RenderFlags.DEPTH_ONLY,
                                                              pyrender.constants.ProgramFlags.USE_MATERIAL)
                        program._bind()
                        program.set_uniform("V", V)
                        program.set_uniform("P", P)
                        program.set_uniform("M", pose)
                        primitive._bind()
                        instances = 1 if primitive.poses is None else len(primitive.poses)
                        if primitive.indices is not None:
                            GL.glDrawElementsInstanced(primitive.mode, primitive.indices.size, GL.GL_UNSIGNED_INT,
                                                       ctypes.c_void_p(0), instances)
                        else:
                            GL.glDrawArraysInstanced(primitive.mode, 0, len(primitive.positions), instances)
                        primitive._unbind()
            finally:
                if program is not None:
                    program._unbind()
                GL.glColorMask(GL.GL_TRUE, GL.GL_TRUE, GL.GL_TRUE, GL.GL_TRUE)

        def _configure_forward_pass_viewport(self, flags):
            super()._configure_forward_pass_viewport(flags)
            if self._shading:
                # the z-buffer stays (its clear is masked off); a fragment passes at its
                # pixel's depth while the pixel's stencil is 0, and sets it
                GL.glDepthMask(GL.GL_FALSE)
                GL.glDepthFunc(GL.GL_LEQUAL)
                GL.glEnable(GL.GL_STENCIL_TEST)
                GL.glStencilMask(0xFF)
                GL.glStencilFunc(GL.GL_EQUAL, 0, 0xFF)
                GL.glStencilOp(GL.GL_KEEP, GL.GL_KEEP, GL.GL_INCR)

        def _delete_main_framebuffer(self):
            super()._delete_main_framebuffer()
            if self.radiance_texture is not None:
                GL.glDeleteTextures([self.radiance_texture])
                self.radiance_texture = None

        def _read_main_framebuffer(self, scene, flags):
            # colour only (pyrender also reads and converts the depth buffer every frame):
            # (H, W, 4) float32, linear radiance and alpha 1 where a surface was drawn
            if flags & pyrender.RenderFlags.DEPTH_ONLY:
                return super()._read_main_framebuffer(scene, flags)
            W, H = self._main_fb_dims
            GL.glBindFramebuffer(GL.GL_READ_FRAMEBUFFER, self._main_fb_ms)
            GL.glBindFramebuffer(GL.GL_DRAW_FRAMEBUFFER, self._main_fb)
            GL.glBlitFramebuffer(0, 0, W, H, 0, 0, W, H, GL.GL_COLOR_BUFFER_BIT, GL.GL_NEAREST)
            if not self.read_radiance:
                return None, None
            GL.glBindFramebuffer(GL.GL_READ_FRAMEBUFFER, self._main_fb)
            data = GL.glReadPixels(0, 0, W, H, GL.GL_RGBA, GL.GL_FLOAT)
            return np.frombuffer(data, dtype=np.float32).reshape(H, W, 4)[::-1], None

    class ShaderCache(pyrender.shader_program.ShaderProgramCache):
        """pyrender's shader cache, with sceneforge's mesh.frag (an absolute path) for pyrender's."""

        def __init__(self, mesh_shader: str):
            super().__init__()
            self.mesh_shader = mesh_shader

        def get_program(self, vertex_shader, fragment_shader, geometry_shader=None, defines=None):
            if fragment_shader == "mesh.frag":
                fragment_shader = self.mesh_shader
            return super().get_program(vertex_shader, fragment_shader, geometry_shader, defines)

    class Scene(pyrender.Scene):
        """pyrender's scene with its mesh and light nodes in name order, not set order: pyrender
        draws meshes and sums lights in the order it gets them, and a set's order changes
        from one scene to the next (pixels would change by a level of rounding)."""

        @property
        def mesh_nodes(self):
            return sorted(super().mesh_nodes, key=lambda n: n.name)

        @property
        def light_nodes(self):
            return sorted(super().light_nodes, key=lambda n: n.name)

        #: the light nodes of each room's mesh node (by node name), in name order
        room_lights: dict
        #: the ambient light (radiance per unit of base colour) of each room's mesh node
        room_ambient: dict

    class RoomLights:
        """The scene as pyrender's lighting code sees it for one room's mesh node: only the
        lights of that room (``Scene.room_lights``), in name order. Every fragment then
        evaluates its own room's few lights, not every light up to :data:`MAX_LIGHTS`."""

        def __init__(self, scene, node):
            self._scene = scene
            self.light_nodes = scene.room_lights.get(node.name, [])
            self.point_light_nodes = [n for n in self.light_nodes if isinstance(n.light, pyrender.PointLight)]
            self.spot_light_nodes = [n for n in self.light_nodes if isinstance(n.light, pyrender.SpotLight)]
            self.directional_light_nodes = []
            self.ambient_light = scene.room_ambient.get(node.name, scene.ambient_light)

        def __getattr__(self, name):  # get_pose, main_camera_node, centroid, scale
            return getattr(self._scene, name)

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
                           ShaderCache=ShaderCache, Scene=Scene,
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


class Renderer(ToneMapped):
    """Offscreen renderer of house views: RGB and z-buffer depth, pixel-aligned with the layers.

    width, height : image size in pixels; every camera must have it
    gpu           : EGL device index; None = ``$EGL_DEVICE_ID``, else the first GPU, else
                    Mesa's software device
    antialias     : 4× multisampling (pyrender's default); off by default so that pixels
                    sample their centres like the ray tracer (see the module docstring)
    config        : lights, shadows and background
    gpu_tonemap   : :meth:`render` applies the exposure, tone curve and sRGB encoding on the
                    GL device and reads back bytes (the default); False: it reads back the
                    float radiance and applies :func:`~sceneforge.render.tonemap.tonemap`
                    with numpy (the reference, slower per pixel; the same bytes up to a level
                    where the device rounds differently, see the module docstring)

    Keeps the GL scene of the last house it rendered (compared by identity: do not modify a
    house between renders) and rebuilds it, freeing the old one, when the house changes.
    One OpenGL context per renderer; use it from one thread. Call :meth:`close` (or use it as
    a context manager) to free the context.
    """

    def __init__(self, width: int, height: int, gpu: int | None = None, antialias: bool = False,
                 config: RenderConfig | None = None, gpu_tonemap: bool = True):
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
        self._gl = gl.Renderer(self.width, self.height, samples=4 if self.antialias else 0,
                               mesh_shader=_mesh_shader(float(self.config.light_min_distance)))
        self.gpu_tonemap = bool(gpu_tonemap)
        self._tone = _TonePass(self.width, self.height, self.config)
        self._house: House | None = None
        self._scene = None
        self._camera_node = None
        self._see_through = None  # (the outdoors' dome, the glazed windows' glass) mesh nodes

    # -- public API ---------------------------------------------------------------------

    def render(self, house: "House", camera: "Camera") -> np.ndarray:
        """(H, W, 3) uint8 sRGB image of ``house`` seen from ``camera``: the radiance of
        :meth:`render_linear` through :func:`~sceneforge.render.tonemap.tonemap`'s exposure,
        tone curve and encoding, on the GL device unless ``gpu_tonemap`` is False."""
        if not self.gpu_tonemap:
            return super().render(house, camera)
        flags = self._colour_flags(house, camera)
        self._gl.read_radiance = False
        try:
            self._gl.render(self._scene, flags)
        finally:
            self._gl.read_radiance = True
        return self._tone.apply(self._gl.radiance_texture, self.config.exposure)

    def render_linear(self, house: "House", camera: "Camera") -> tuple[np.ndarray, np.ndarray]:
        """(H, W, 3) float32 linear radiance (cd/m²) of the view and the (H, W) bool mask of
        the pixels that see a surface."""
        flags = self._colour_flags(house, camera)  # before reading self._scene: it may build it
        rgba, _ = self._gl.render(self._scene, flags)
        return rgba[..., :3], rgba[..., 3] > 0

    def depth(self, house: "House", camera: "Camera") -> np.ndarray:
        """(H, W) float32 planar depth (camera z, metres) of the z-buffer; NaN where nothing.

        Single-sampled, this is the first hit of the ray through each pixel centre (the
        layers' ``traditional_depth`` up to the depth buffer's resolution, see :data:`NEAR`);
        with ``antialias`` it comes from one of the four samples of each pixel. A glazed
        window's glass is a surface here, as in the layers, though the RGB sees the outdoors
        through it; the outdoors' dome is not.
        """
        flags = self._prepare(house, camera)
        self._show_glass(True)
        try:
            depth = np.array(self._gl.render(self._scene, flags | _gl().pyrender.RenderFlags.DEPTH_ONLY),
                             dtype=np.float32)
        finally:
            self._show_glass(False)
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
        self._tone.delete()
        self._gl.delete()
        self._platform.delete_context()
        self._platform = self._gl = self._tone = self._scene = self._house = self._camera_node = None

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
        check_camera_size(camera, self.width, self.height)
        self._platform.make_current()
        if house is not self._house:
            self._build_scene(house)
        cam = self._camera_node.camera
        K = camera.K
        cam.fx, cam.fy, cam.cx, cam.cy, cam.skew = K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1]
        self._scene.set_pose(self._camera_node, opencv_to_opengl(camera.cam_to_world))
        RenderFlags = _gl().pyrender.RenderFlags
        return RenderFlags.OFFSCREEN | RenderFlags.SKIP_CULL_FACES

    def _show_glass(self, depth: bool) -> None:
        """Show the glazed windows' glass and hide the outdoors' dome (``depth``), or the
        other way round (colour, the default)."""
        if self._see_through is not None:
            sky_node, glass_node = self._see_through
            sky_node.mesh.is_visible = not depth
            if glass_node is not None:
                glass_node.mesh.is_visible = depth

    def _colour_flags(self, house: "House", camera: "Camera") -> int:
        """:meth:`_prepare`, with the shadow maps' flag when ``config.shadows``."""
        flags = self._prepare(house, camera)
        if self.config.shadows:
            flags |= _gl().pyrender.RenderFlags.SHADOWS_SPOT
        return flags

    def _build_scene(self, house: "House") -> None:
        """Replace the GL scene by one of ``house``, freeing the previous one's GL objects first."""
        gl = _gl()
        pyrender = gl.pyrender
        if self._scene is not None:
            # pyrender frees the GL objects of whatever its context holds that a scene lacks
            self._gl._update_context(pyrender.Scene(), pyrender.RenderFlags.NONE)
        self._scene = self._house = None
        self._see_through = None
        self._gl._lit.clear()
        config = self.config
        lights = [] if config.flat else house_lights(house, config)
        # glazed windows show the outdoors through their glass (a dome around the house);
        # the others are drawn as panels of the outdoors' mean radiance and colour
        glazed = glazed_windows(house) if lights and config.sky_luminance > 0 else frozenset()
        emission = {light.instance: light.radiance for light in lights
                    if light.source == "window" and light.instance not in glazed}
        daylight = next((np.asarray(light.colour) for light in lights if light.source == "window"), np.ones(3))
        scene = gl.Scene(bg_color=(0.0, 0.0, 0.0, 0.0), ambient_light=(float(config.ambient),) * 3)
        textures: dict[tuple, object] = {}
        rooms: dict[str | None, tuple[np.ndarray, list]] = {}
        for batch in _merge_plain(house_batches(house, emission, see_through=glazed)):
            material = batch.material
            texture = None
            if material.texture is not None:
                key = (_texture_key(material.texture), tuple(material.wrap))
                if key not in textures:
                    wrap = [_WRAP_CODES[w] for w in material.wrap]
                    sampler = pyrender.Sampler(magFilter=gl.GL.GL_LINEAR, minFilter=gl.GL.GL_LINEAR_MIPMAP_LINEAR,
                                               wrapS=wrap[0], wrapT=wrap[1])
                    textures[key] = pyrender.Texture(source=_texels(house, material.texture), source_channels="RGB",
                                                     sampler=sampler)
                texture = textures[key]
            look = pyrender.MetallicRoughnessMaterial(
                baseColorFactor=(*(float(c) for c in material.base_color[:3]), 1.0), baseColorTexture=texture,
                metallicFactor=0.0, roughnessFactor=1.0, doubleSided=True,
                emissiveFactor=tuple(float(c) for c in batch.emission * daylight))
            primitive = pyrender.Primitive(positions=batch.positions, normals=batch.normals, color_0=batch.colors,
                                           texcoord_0=batch.uv, material=look)
            rooms.setdefault(batch.room, (batch.origin, []))[1].append(primitive)
        mesh_of_room = {}
        for k, (room, (origin, primitives)) in enumerate(rooms.items()):
            mesh_of_room[room] = f"room{k:06d}"
            scene.add(pyrender.Mesh(primitives=primitives), name=mesh_of_room[room], pose=_translation(origin))
        scene.room_lights = {name: [] for name in mesh_of_room.values()}
        for k, (light, reached) in enumerate(zip(lights, light_rooms(house, lights), strict=True)):
            meshes = [mesh_of_room[room] for room in reached if room in mesh_of_room]
            if meshes:  # one node, lighting its own room and the rooms of the same space
                node, pose = _pyrender_light(pyrender, light)
                node = scene.add(node, name=f"light{k:06d}", pose=pose)
                for name in meshes:
                    scene.room_lights[name].append(node)
        # pyrender's ambient term is base colour × ambient_light, a Lambertian surface's
        # radiance under irradiance E is base colour × E / π
        scene.room_ambient = {} if config.flat else {
            mesh_of_room[room]: np.asarray(e) / np.pi for room, e in room_ambient(house, config, lights).items()
            if room in mesh_of_room}
        if glazed:
            # the outdoors as seen through the glass: a dome of the sky's radiance ×
            # outdoors_seen (vertex colours × an ambient light of 1 and no light: exactly that
            # radiance), lit by nothing else; the windows' lights carry its whole radiance
            centre = house.bounds().mean(axis=0)
            radius = min(max(4.0 * float(np.ptp(house.bounds(), axis=0).max()), 50.0), 0.5 * FAR)
            v, f, colours = sky_dome(centre, radius)
            dome = pyrender.Primitive(
                positions=(v[f] - centre).reshape(-1, 3).astype(np.float32),
                normals=np.repeat(-np.asarray(v[f].mean(axis=1) - centre, np.float64)
                                  / radius, 3, axis=0).astype(np.float32),
                color_0=np.concatenate([(colours[f] * float(config.sky_luminance * config.outdoors_seen))
                                        .reshape(-1, 3), np.ones((3 * len(f), 1))], axis=1).astype(np.float32),
                material=pyrender.MetallicRoughnessMaterial(baseColorFactor=(1.0, 1.0, 1.0, 1.0), metallicFactor=0.0,
                                                            roughnessFactor=1.0, doubleSided=True))
            sky_node = scene.add(pyrender.Mesh(primitives=[dome]), name="sky", pose=_translation(centre))
            scene.room_lights["sky"] = []
            scene.room_ambient["sky"] = np.ones(3)
            # the glass, for depth() only: the z-buffer sees it, as the layers do, and not
            # the dome behind it (hidden from every colour pass)
            glass = _glass_triangles(house, glazed)
            glass_node = None
            if len(glass):
                origin = glass.reshape(-1, 3).mean(axis=0)
                pane = pyrender.Primitive(
                    positions=(glass - origin).reshape(-1, 3).astype(np.float32),
                    material=pyrender.MetallicRoughnessMaterial(baseColorFactor=(1.0, 1.0, 1.0, 1.0),
                                                                doubleSided=True))
                glass_node = scene.add(pyrender.Mesh(primitives=[pane], is_visible=False), name="glass",
                                       pose=_translation(origin))
            self._see_through = (sky_node, glass_node)
        self._camera_node = scene.add(gl.IntrinsicsCamera(1.0, 1.0, 0.0, 0.0, znear=NEAR, zfar=FAR))
        # shadow maps frame the scene's bounds; pyrender's own computation uses np.infty,
        # which NumPy 2 removed
        scene._bounds = house.bounds()
        self._scene, self._house = scene, house


def _merge_plain(batches: list[Batch]) -> list[Batch]:
    """The batches to draw: per room, every batch without a texture or emission merged into
    one, its base colours moved into the vertex colours (the shader multiplies the two in
    float32, as this does); the others as they are. Each draw costs pyrender a few dozen
    Python calls per frame, and a room of one material per object has dozens of batches."""
    from dataclasses import replace

    out, plain = [], {}
    for batch in batches:
        if batch.material.texture is None and batch.emission == 0:
            plain.setdefault(batch.room, []).append(batch)
        else:
            out.append(batch)
    merged = []
    for room, group in plain.items():
        colours = []
        for b in group:
            base = np.asarray(b.material.base_color, dtype=np.float32)
            rgba = b.colors if b.colors is not None else np.ones((len(b.positions), 4), np.float32)
            colours.append(rgba * np.array([*base[:3], 1.0], np.float32))
        white = replace(group[0].material, base_color=(1.0, 1.0, 1.0, 1.0))
        merged.append(Batch(room, group[0].origin, np.concatenate([b.positions for b in group]),
                            np.concatenate([b.normals for b in group]), np.concatenate(colours), None, white))
    return merged + out


#: OpenGL's wrap modes of :data:`sceneforge.houses.model.WRAPS`
_WRAP_CODES = {"repeat": 10497, "clamp": 33071, "mirror": 33648}


def _translation(t) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = t
    return m


def _pyrender_light(pyrender, light: Light):
    """(pyrender light, pose) of a :class:`Light`: pyrender's light falls off as
    ``intensity / d²`` and its diffuse term is ``base × (1 - 0.04) / π`` of it, hence the
    scale; a spot light points along its pose's -z (the patched shader: cos θ inside its cone)."""
    intensity = light.intensity / _DIFFUSE
    if light.kind == "point":
        return pyrender.PointLight(color=np.asarray(light.colour, dtype=np.float64), intensity=intensity), \
            _translation(light.position)
    z = -np.asarray(light.direction, dtype=np.float64)
    x = np.cross([0.0, 1.0, 0.0], z)
    x = x / np.linalg.norm(x) if np.linalg.norm(x) > 1e-9 else np.array([1.0, 0.0, 0.0])
    pose = _translation(light.position)
    pose[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    return pyrender.SpotLight(color=np.asarray(light.colour, dtype=np.float64), intensity=intensity, innerConeAngle=0.0,
                              outerConeAngle=float(WINDOW_CONE)), pose
