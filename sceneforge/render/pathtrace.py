"""Path-traced RGB of house views with Mitsuba 3 (``sceneforge render --rgb pathtraced``).

Same interface as :class:`~sceneforge.render.raster.Renderer`: ``render(house, camera)``
gives an (H, W, 3) uint8 sRGB image, pixel-aligned with the depth layers.

Camera. :func:`mitsuba_sensor` turns the layers' camera (OpenCV axes, ``K`` in pixels,
pixel ``(i, j)`` centred at ``(j + 0.5, i + 0.5)``) into Mitsuba's ``perspective`` sensor:
Mitsuba's camera looks along its +z with +y up and +x to the *left* of the image, so its
pose is ``cam_to_world · diag(-1, -1, 1)``; the horizontal field of view is
``2 atan(W / 2 fx)`` and the principal point offset ``((W/2 - cx) / W, (H/2 - cy) / H)``
(Mitsuba moves the image, not the principal point: the signs are OpenCV's negated).
Mitsuba's sensor has square pixels and no skew: a camera whose fx and fy differ, or with
a skew, by more than ``tol.square_pixels`` (1e-5 of fx: what a PBRS file's 6-decimal
half-FOVs leave) is refused with a one-line error; within it, fx sets the field of view. Each pixel integrates its own square (a box filter of
radius ½ pixel), so the image is antialiased: a silhouette pixel blends its two sides,
while the pixels on either side of it show what the layers' centre ray sees.

Scene. The house's draw batches (:func:`~sceneforge.render.raster.house_batches`: every
face group with its own material) become two-sided diffuse meshes: reflectance = linear
base colour × the sRGB texture decoded to linear (with the material's wrapping), or ×
the vertex colours. The lights are the raster mode's (:mod:`sceneforge.render.lights`,
the same lumens and candela): point lights for lamps and fallbacks, and every window an
area emitter of the sky's radiance (its faces wound into the room, reflecting nothing)
in place of the raster mode's spot light; no ambient term (the path tracer traces the
indirect light). Behind a glazed window's glass the outdoors' dome emits the sky's full
radiance, which lights the rooms, while the camera sees it at ``outdoors_seen`` × that: the
``aov`` integrator also gives the shape each sample's camera ray meets first, and a sample
that meets the dome (which reflects nothing, so it brings back only the dome's emission) is
scaled before the samples are averaged. The radiance goes through the same exposure and tone-mapping step as
the raster mode's (:func:`sceneforge.render.tonemap.tonemap`). The integrator is
Mitsuba's ``path`` with :data:`MAX_DEPTH` bounces, inside an ``aov`` integrator that also
averages each pixel's albedo and shading normal; with ``denoise`` (the default) Intel Open
Image Denoise removes the noise guided by them (:mod:`.denoise`) before the tone mapping,
keeping ``RenderConfig.grain`` (5 %) of it: PBRS's renders, the paper's, show their grain.

Determinism. A fixed sample count and seed give the same image on the same machine and
variant: the view's seed is the renderer's seed mixed with a CRC of the camera (so views
do not share one noise pattern, and the same view always gets the same one), each render
pass takes one sample per pixel (the view's seed + ``k`` in pass ``k``) and
the passes are averaged in numpy in pass order, so no two samples ever race to add into
one pixel. Across CPUs (LLVM) and GPUs (CUDA) results differ by floating-point rounding.

Variant: ``cuda_ad_rgb`` when it runs (an NVIDIA driver and GPU), else ``llvm_ad_rgb``
(Dr.Jit's LLVM backend on the CPU, which needs a libLLVM shared library, 16 or newer;
``scripts/system-deps.sh`` installs one). "Runs" is tested by setting the variant and
evaluating one tiny kernel: a CUDA variant whose driver fails to initialise falls back to
LLVM, and when neither runs the error gives both reasons. ``SCENEFORGE_MITSUBA_VARIANT``
names the variant instead (no fallback). The seeds above do not depend on the variant.
``sceneforge doctor`` prints the variant and why (:func:`mitsuba_variant`).
"""

from __future__ import annotations

import functools
import glob
import os
import re
import zlib
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..colour import srgb_to_linear
from ..conventions import tol
from ..errors import MissingDependencyError, SceneforgeError
from .lights import glazed_windows, house_lights
from .raster import RenderConfig, _texels, _texture_key, check_camera_size, house_batches
from .sky import dome as sky_dome
from .tonemap import ToneMapped

if TYPE_CHECKING:
    from ..cameras import Camera
    from ..houses.model import House

INSTALL_MITSUBA = "pip install 'sceneforge[pathtrace]'"
INSTALL_LLVM = "sudo apt-get install libllvm19 (LLVM 16 or newer), or set DRJIT_LIBLLVM_PATH"
#: the oldest LLVM whose library Dr.Jit's kernels compile with (LLVM 14 and 15 abort the
#: process: "Cannot select: fminimum")
MIN_LLVM = 16
#: the Mitsuba variants path tracing runs on, in the order they are tried (module docs)
VARIANTS = ("cuda_ad_rgb", "llvm_ad_rgb")
#: environment variable naming the one of :data:`VARIANTS` to run on, e.g. ``llvm_ad_rgb``
#: to path-trace on the CPU where a GPU is present
VARIANT_ENV = "SCENEFORGE_MITSUBA_VARIANT"
#: light bounces of the path tracer
MAX_DEPTH = 6
#: samples per pixel when none is given
DEFAULT_SAMPLES = 64


def newest_llvm() -> tuple[int, str] | None:
    """(major version, path) of the newest libLLVM shared library in the places Dr.Jit
    searches (``/usr/lib/<arch>/``), or None."""
    found = []
    for path in glob.glob("/usr/lib/*/libLLVM*.so*") + glob.glob("/usr/lib/llvm-*/lib/libLLVM*.so*"):
        match = re.search(r"libLLVM(?:-|\.so\.)(\d+)", os.path.basename(path))
        if match:
            found.append((int(match.group(1)), path))
    return max(found, default=None)


@dataclass(frozen=True)
class Variant:
    """The Mitsuba variant path tracing runs on (:func:`mitsuba_variant`) and why that one."""

    name: str
    #: e.g. ``"on NVIDIA H200"`` or ``"(no CUDA driver)"``
    why: str

    def __str__(self) -> str:
        return f"{self.name} {self.why}".strip()


@functools.cache
def _select() -> tuple[object, Variant]:
    """Mitsuba with its variant set (module docs: the first of :data:`VARIANTS` that runs, or
    the one ``SCENEFORGE_MITSUBA_VARIANT`` names) and that variant. Points Dr.Jit at the
    newest libLLVM (it takes the first it finds, and an old one aborts the process, so the
    LLVM variant is not even tried with one)."""
    forced = os.environ.get(VARIANT_ENV, "").strip()
    if forced and forced not in VARIANTS:
        raise SceneforgeError(f"{VARIANT_ENV}={forced!r} names no variant sceneforge path-traces with; "
                              f"choose {' or '.join(VARIANTS)}, or unset it")
    no_llvm = None  # why the LLVM variant cannot run, known before trying it
    if not os.environ.get("DRJIT_LIBLLVM_PATH"):
        llvm = newest_llvm()
        if llvm is not None and llvm[0] >= MIN_LLVM:
            os.environ["DRJIT_LIBLLVM_PATH"] = llvm[1]
        else:
            no_llvm = f"LLVM {llvm[0]} is too old" if llvm else "no libLLVM found"
    try:
        import mitsuba as mi
    except ModuleNotFoundError as e:
        raise MissingDependencyError(e.name or "mitsuba", "path-traced RGB", INSTALL_MITSUBA) from None
    failed: list[tuple[str, str]] = []  # (variant, why it does not run)
    for variant in [forced] if forced else VARIANTS:
        if variant == "llvm_ad_rgb" and no_llvm:
            failed.append((variant, f"{no_llvm}, needs LLVM {MIN_LLVM}+"))
            continue
        if variant not in mi.variants():
            failed.append((variant, "not in this Mitsuba build"))
            continue
        try:
            mi.set_variant(variant)
            import drjit as dr

            dr.eval(mi.Float(0.0) + 1.0)  # a backend without its library fails only when used
        except (ImportError, RuntimeError, AttributeError) as e:
            cuda_missing = variant.startswith("cuda") and not _has_cuda()
            failed.append((variant, "no CUDA driver" if cuda_missing else _first_line(e)))
            continue
        if forced:
            why = f"({VARIANT_ENV})"
        else:  # the CUDA variant failed before
            why = "; ".join(r if r == "no CUDA driver" else f"{v}: {r}" for v, r in failed)
            why = f"({why})" if why else ""
        if variant.startswith("cuda"):
            why = f"on {_cuda_device_name() or 'a CUDA GPU'}" + (f" {why}" if why else "")
        return mi, Variant(variant, why)
    reasons = "; ".join(f"{v}: {r}" for v, r in failed)
    if forced:
        raise SceneforgeError(f"path-traced RGB: {VARIANT_ENV}={forced}, which does not run here "
                              f"({failed[0][1]}); unset it to take the first Mitsuba variant that runs")
    raise MissingDependencyError(f"libLLVM {MIN_LLVM}+ (or a CUDA GPU)",
                                 f"path-traced RGB (no Mitsuba variant runs: {reasons})", INSTALL_LLVM)


def _first_line(e: BaseException) -> str:
    return (str(e).strip().splitlines() or [type(e).__name__])[0]


def _mitsuba():
    """Mitsuba with its variant set (:func:`_select`), imported on first use."""
    return _select()[0]


def mitsuba_variant() -> Variant:
    """The Mitsuba variant ``--rgb pathtraced`` runs on here, and why (module docs); sets it
    up as path tracing would, running one tiny kernel, and renders nothing. Raises
    :class:`MissingDependencyError` where Mitsuba is not installed or no variant runs."""
    return _select()[1]


def _has_cuda() -> bool:
    """Whether an NVIDIA driver is loadable (Mitsuba's CUDA variant needs nothing else)."""
    import ctypes.util

    return ctypes.util.find_library("cuda") is not None


def _cuda_device_name() -> str | None:
    """The name of CUDA device 0 (Dr.Jit's default device), from the driver, or None."""
    import ctypes
    import ctypes.util

    try:
        cuda = ctypes.CDLL(ctypes.util.find_library("cuda") or "libcuda.so.1")
        device, name = ctypes.c_int(), ctypes.create_string_buffer(256)
        if cuda.cuInit(0) or cuda.cuDeviceGet(ctypes.byref(device), 0) or \
                cuda.cuDeviceGetName(name, 256, device):
            return None
    except (OSError, AttributeError):
        return None
    return name.value.decode(errors="replace") or None


def mitsuba_sensor(camera: "Camera") -> dict:
    """The Mitsuba ``perspective`` sensor of ``camera`` (module docs) as plain data, without
    film and sampler; ``to_world`` is a (4, 4) float64 array. Raises
    :class:`SceneforgeError` for non-square pixels or a skew."""
    K, W, H = camera.K, camera.width, camera.height
    fx, fy, skew = K[0, 0], K[1, 1], K[0, 1]
    if abs(fx - fy) > tol.square_pixels * fx or abs(skew) > tol.square_pixels * fx:
        raise SceneforgeError(f"path tracing needs square pixels and no skew (Mitsuba's camera has neither); "
                              f"K has fx {fx:g}, fy {fy:g}, skew {skew:g}: use --rgb raster")
    pose = camera.cam_to_world @ np.diag([-1.0, -1.0, 1.0, 1.0])
    return {
        "type": "perspective",
        "fov_axis": "x",
        "fov": float(np.degrees(2.0 * np.arctan(W / (2.0 * fx)))),
        "principal_point_offset_x": float((W / 2.0 - K[0, 2]) / W),
        "principal_point_offset_y": float((H / 2.0 - K[1, 2]) / H),
        "near_clip": 0.01,
        "far_clip": 1000.0,
        "to_world": pose,
    }


class PathTracer(ToneMapped):
    """Path-traced RGB of house views (module docs).

    width, height : image size in pixels; every camera must have it
    config        : lights (as the raster mode's) and background
    samples       : samples per pixel (None: :data:`DEFAULT_SAMPLES`)
    seed          : the renderer's seed (module docs)
    denoise       : denoise the radiance with its albedo and normal (:mod:`.denoise`)

    Keeps the Mitsuba scene of the last house it rendered (compared by identity).
    """

    def __init__(self, width: int, height: int, config: RenderConfig | None = None, samples: int | None = None,
                 seed: int = 0, denoise: bool = True):
        if int(width) < 1 or int(height) < 1:
            raise ValueError(f"image size must be positive, got {width}×{height}")
        self.mi = _mitsuba()
        self.width, self.height = int(width), int(height)
        self.config = config or RenderConfig()
        self.samples = int(samples or DEFAULT_SAMPLES)
        if self.samples < 1:
            raise ValueError(f"samples must be at least 1, got {self.samples}")
        self.seed = int(seed)
        self.denoise = bool(denoise)
        if self.denoise:
            from .denoise import denoise as check  # a missing pyoidn fails here, not at the first view

            check(np.zeros((1, 1, 3)), np.zeros((1, 1, 3)), np.zeros((1, 1, 3)))
        self._house = self._scene = self._sky_id = None

    @property
    def variant(self) -> str:
        return self.mi.variant()

    def render_linear(self, house: "House", camera: "Camera") -> tuple[np.ndarray, np.ndarray]:
        """(H, W, 3) float64 linear radiance (cd/m²) of the view and the (H, W) bool mask of
        the pixels that see a surface (any of their samples)."""
        if self.mi is None:
            raise SceneforgeError("the renderer is closed")
        check_camera_size(camera, self.width, self.height)
        mi = self.mi
        if house is not self._house:
            self._scene, self._sky_id = self._build_scene(house)
            self._house = house
        spec = mitsuba_sensor(camera)
        sensor = mi.load_dict({
            **spec,
            "to_world": mi.ScalarTransform4f(spec["to_world"].tolist()),
            "film": {"type": "hdrfilm", "width": self.width, "height": self.height, "pixel_format": "rgba",
                     "rfilter": {"type": "box"}},
            "sampler": {"type": "independent", "sample_count": 1},
        })
        view_seed = (self.seed * 1_000_003 + zlib.crc32(camera.K.tobytes() + camera.cam_to_world.tobytes())) % 2 ** 31
        # channels: radiance RGB, alpha, then the aov integrator's albedo RGB and normal XYZ
        # (and, with an outdoors to dim, the registry id of the shape each sample first hits)
        total = np.zeros((self.height, self.width, 10))
        for k in range(self.samples):
            image = mi.render(self._scene, sensor=sensor, spp=1, seed=view_seed + k)
            sample = np.nan_to_num(np.asarray(image, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
            if self._sky_id is not None:
                # one sample per pixel and pass (a box filter of ½ pixel): a sample whose camera
                # ray meets the outdoors' dome first sees only its emission (it reflects nothing)
                sample[..., :3] *= np.where(sample[..., 10:11] == self._sky_id, self.config.outdoors_seen, 1.0)
            total += sample[..., :10]
        out = total / self.samples
        radiance = out[..., :3]
        if self.denoise:
            from .denoise import denoise

            clean = denoise(radiance, out[..., 4:7], out[..., 7:10])
            # a little of the samples' own noise kept (RenderConfig.grain): PBRS's grain
            radiance = clean + self.config.grain * (radiance - clean) if self.config.grain else clean
        # the film's alpha is the fraction of a pixel's samples that hit a surface
        return radiance, out[..., 3] > 0

    def close(self) -> None:
        """Forget the scene. Idempotent."""
        self._house = self._scene = self._sky_id = None
        self.mi = None

    def __enter__(self) -> "PathTracer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- internals ----------------------------------------------------------------------

    def _build_scene(self, house: "House"):
        """The Mitsuba scene of ``house`` and the registry id of its outdoors' dome when the
        camera sees the dome dimmed (``outdoors_seen`` below 1), else None."""
        mi = self.mi
        lights = house_lights(house, self.config)
        # a glazed window is drawn without its glass, and the outdoors (a dome emitting the
        # sky's radiance) lights the room through it; any other window is an area emitter of
        # the outdoors' mean radiance, its faces turned into the room
        glazed = glazed_windows(house) if self.config.sky_luminance > 0 else frozenset()
        dim = bool(glazed) and self.config.outdoors_seen != 1.0
        # a pixel sees nothing beyond the house (the background is applied after tone mapping)
        # the aov integrator adds each sample's albedo and shading normal (the denoiser's
        # guides) and, to dim the outdoors where the camera sees it, the shape it first hits
        aovs = "albedo:albedo,normal:sh_normal" + (",shape:shape_index" if dim else "")
        scene: dict = {"type": "scene", "integrator": {
            "type": "aov", "aovs": aovs, "integrator": {"type": "path", "max_depth": MAX_DEPTH}}}
        windows = {light.instance: light for light in lights
                   if light.source == "window" and light.instance not in glazed}
        textures: dict[tuple, object] = {}
        for k, batch in enumerate(house_batches(house, exclude=frozenset(windows), see_through=glazed)):
            scene[f"mesh{k:06d}"] = self._mesh(house, f"mesh{k:06d}", batch, textures)
        for k, inst in enumerate(i for i in house.instances if i.id in windows):
            scene[f"window{k:06d}"] = self._window(inst, windows[inst.id])
        if glazed:
            scene["sky"] = self._sky(house)
        for k, light in enumerate(light for light in lights if light.kind == "point"):
            scene[f"light{k:06d}"] = {"type": "point", "position": light.position.tolist(),
                                      "intensity": {"type": "rgb", "value": [light.intensity] * 3}}
        loaded = mi.load_dict(scene)
        if not dim:
            return loaded, None
        # the aov integrator's shape_index is a shape's Dr.Jit registry id, not its position
        import drjit as dr

        ids = np.asarray(dr.reinterpret_array(mi.UInt32, loaded.shapes_dr()), dtype=np.float64)
        (sky_id,) = (i for i, shape in zip(ids, loaded.shapes(), strict=True) if shape.id() == "sky")
        return loaded, float(sky_id)

    def _sky(self, house: "House"):
        """The outdoors: the raster mode's dome (:func:`.sky.dome`), an area emitter whose
        radiance is its vertex colours × ``sky_luminance``, facing inwards, reflecting nothing
        (what the camera sees of it is scaled in :meth:`render_linear`)."""
        mi = self.mi
        bounds = house.bounds()
        centre = bounds.mean(axis=0)
        radius = min(max(4.0 * float(np.ptp(bounds, axis=0).max()), 50.0), 500.0)
        v, f, colours = sky_dome(centre, radius)
        tri = v[f]
        inward = np.einsum("ij,ij->i", np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]),
                           centre - tri.mean(axis=1)) >= 0
        f = np.where(inward[:, None], f, f[:, ::-1])
        props = mi.Properties()
        props["bsdf"] = mi.load_dict({"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0, 0.0, 0.0]}})
        props["emitter"] = mi.load_dict({"type": "area", "radiance": {"type": "mesh_attribute",
                                                                      "name": "vertex_color"}})
        mesh = mi.Mesh("sky", len(v), len(f), props=props, has_vertex_normals=False)
        mesh.add_attribute("vertex_color", 3, (colours * float(self.config.sky_luminance)).astype(np.float32).ravel())
        params = mi.traverse(mesh)
        params["vertex_positions"] = v.astype(np.float32).ravel()
        params["faces"] = f.astype(np.uint32).ravel()
        params.update()
        return mesh

    def _window(self, inst, light):
        """A Mitsuba mesh of a window's faces, each wound to face ``light.direction`` (into
        the room), emitting ``light.radiance`` from that side and reflecting nothing."""
        mi = self.mi
        tri = inst.vertices[inst.faces].astype(np.float64)
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        inward = normal @ light.direction >= 0
        faces = np.where(inward[:, None], inst.faces, inst.faces[:, ::-1])
        props = mi.Properties()
        props["bsdf"] = mi.load_dict({"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0, 0.0, 0.0]}})
        radiance = [light.radiance * c for c in light.colour]  # the outdoors' colour
        props["emitter"] = mi.load_dict({"type": "area", "radiance": {"type": "rgb", "value": radiance}})
        mesh = mi.Mesh(f"window{inst.id}", len(inst.vertices), len(faces), props=props, has_vertex_normals=False)
        params = mi.traverse(mesh)
        params["vertex_positions"] = inst.vertices.astype(np.float32).ravel()
        params["faces"] = faces.astype(np.uint32).ravel()
        params.update()
        return mesh

    def _mesh(self, house: "House", name: str, batch, textures: dict):
        """A Mitsuba mesh of one draw batch with its two-sided diffuse BSDF."""
        mi = self.mi
        material = batch.material
        base = np.clip(np.asarray(material.base_color[:3], dtype=np.float64), 0.0, 1.0)
        if material.texture is not None:
            key = (_texture_key(material.texture), tuple(base))
            if key not in textures:
                linear = srgb_to_linear(_texels(house, material.texture) / 255.0) * base
                # the image's top row is v = 1 (OpenGL); Mitsuba's bitmap has its first row at v = 0
                textures[key] = mi.Bitmap(np.ascontiguousarray(linear[::-1], dtype=np.float32))
            wrap = {"repeat": "repeat", "clamp": "clamp", "mirror": "mirror"}[material.wrap[0]]
            reflectance = {"type": "bitmap", "bitmap": textures[key], "raw": True, "wrap_mode": wrap,
                           "filter_type": "bilinear"}
        elif batch.colors is not None:
            reflectance = {"type": "mesh_attribute", "name": "vertex_color"}
        else:
            reflectance = {"type": "rgb", "value": base.tolist()}
        props = mi.Properties()
        props["bsdf"] = mi.load_dict({"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": reflectance}})
        n = len(batch.positions)
        mesh = mi.Mesh(name, n, n // 3, props=props, has_vertex_normals=False,
                       has_vertex_texcoords=batch.uv is not None)
        if batch.colors is not None and material.texture is None:
            mesh.add_attribute("vertex_color", 3, (batch.colors[:, :3] * base).astype(np.float32).ravel())
        params = mi.traverse(mesh)
        params["vertex_positions"] = (batch.positions.astype(np.float64) + batch.origin).astype(np.float32).ravel()
        params["faces"] = np.arange(n, dtype=np.uint32)
        if batch.uv is not None:
            params["vertex_texcoords"] = batch.uv.astype(np.float32).ravel()
        params.update()
        return mesh

