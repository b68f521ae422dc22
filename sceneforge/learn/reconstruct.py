"""From RGB photos to 3D: a trained overhead run on images that are not in any store (the
paper's NYUv2 and ScanNet figures).

Every photo is taken by a pinhole camera of known intrinsics (:class:`PhotoCamera`: the
paper's camera by default, docs/spec.md §1) at a known height above the floor and pitch (roll 0),
set at the origin of its **gravity-aligned frame** (right-handed, metres): +Y up, +Z the
view direction flattened onto the floor, so the camera's right is -X; the floor is at
``y = -height``. The
run's frozen frontal nets predict D1..D5 and the classes of layers 1 and 3; the overhead
camera is placed from the predicted layers by the store's heuristics (docs/spec.md §6: depth
statistics and frustum; no rooms are known), or by a camera proposal run; the EFT and the
overhead nets predict the heights, the floor removed by the overhead segmentation (as
``predict``) and the pixels outside the photo's view frustum dropped (the EFT carries
nothing there).

Per photo ``NAME``, :func:`reconstruct` writes into ``out``:

- ``NAME.npz``: ``depth`` (5, H, W) float32 (NaN = none), ``category`` (2, H, W) uint8
  NYU40, ``overhead_height`` (R, R) float32 (NaN = floor or none), ``overhead_category``
  (R, R) uint8, ``K`` (3, 3), ``cam_to_world`` (4, 4) (the camera in the gravity frame),
  ``overhead_cam_to_world`` (4, 4), ``overhead_extent`` (), ``overhead_params`` (5,);
- ``NAME.exr``: the same layers through :func:`sceneforge.store.export_exr`;
- ``NAME.png``: a panel of the photo, D1, D3, D5, the classes and the overhead heights;
- ``NAME.ply``: one mesh of the frontal layers D1..D5 and of the overhead heights
  (:mod:`sceneforge.evaluate.depth_mesh`), vertices in the gravity-aligned frame, metres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from ..cameras import DEFAULT_HALF_FOV_X, DEFAULT_PITCH, pose_from_view
from ..errors import SceneforgeError, listed
from .dataset import CLASS_TO_NYU40, SEG_CLASSES, normalize_rgb
from .eft import EpipolarFeatureTransformer
from .networks import SEG_LAYERS
from .predict import overhead_heights, proposed_overhead_cameras
from .stages import get_stage, overhead_input
from .train import load_run, resolve_device

#: image suffixes read from a folder
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
#: the camera height above the floor, metres (the toy and PBRS cameras' eye height)
DEFAULT_HEIGHT = 1.5
#: the files written per photo NAME: NAME.npz, NAME.exr, NAME.png, NAME.ply
OUTPUT_SUFFIXES = (".npz", ".exr", ".png", ".ply")


@dataclass(frozen=True)
class PhotoCamera:
    """How the photos were taken (all of them, at their own size).

    K      : (3, 3) intrinsics in pixels of the photo as read; None = the paper's camera
             (horizontal half-FOV ``half_fov_x``, principal point at the centre)
    half_fov_x : horizontal half field of view, radians (used when K is None)
    height : camera height above the floor, metres
    pitch  : downward pitch, radians (paper: atan 0.2 = 11.31°)
    """

    K: tuple | None = None
    half_fov_x: float = DEFAULT_HALF_FOV_X
    height: float = DEFAULT_HEIGHT
    pitch: float = DEFAULT_PITCH

    def __post_init__(self):
        if not 0 < self.half_fov_x < math.pi / 2:
            raise SceneforgeError(f"the field of view must be in (0°, 180°), got {2 * math.degrees(self.half_fov_x):g}°")
        if not self.height > 0:
            raise SceneforgeError(f"the camera height must be > 0 m, got {self.height}")
        if not -math.pi / 2 < self.pitch < math.pi / 2:
            raise SceneforgeError(f"the pitch must be within ±90°, got {math.degrees(self.pitch):g}°")

    def intrinsics(self, width: int, height: int) -> np.ndarray:
        """(3, 3) float64 K of a ``width × height`` photo."""
        if self.K is not None:
            return np.asarray(self.K, dtype=np.float64).reshape(3, 3)
        f = 0.5 * width / math.tan(self.half_fov_x)
        return np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], dtype=np.float64)

    def pose(self) -> np.ndarray:
        """(4, 4) cam_to_world (OpenCV axes) in the gravity-aligned frame: at the origin,
        looking along +Z pitched down by :attr:`pitch`, no roll."""
        return pose_from_view(np.zeros(3), np.array([0.0, -math.sin(self.pitch), math.cos(self.pitch)]))


def photo_paths(inputs: Sequence[str | Path]) -> list[Path]:
    """The images named, folders expanded to their PNG/JPEG files (sorted); a missing path
    or a folder without images is a :class:`SceneforgeError`."""
    paths: list[Path] = []
    for item in map(Path, inputs):
        if item.is_dir():
            found = sorted(p for p in item.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
            if not found:
                raise SceneforgeError(f"{item}: no PNG or JPEG image in the folder")
            paths += found
        elif item.is_file():
            paths.append(item)
        else:
            raise SceneforgeError(f"{item}: no such image or folder")
    if not paths:
        raise SceneforgeError("no image given")
    return paths


def check_outputs(out: str | Path, names: Sequence[str], *, run, camera_run, images: Sequence[Path],
                  overwrite: bool) -> None:
    """Raise :class:`SceneforgeError` unless writing the files of photos ``names`` into the
    folder ``out`` loses nothing it did not make (see :func:`reconstruct`)."""
    from ..store.guard import check_apart, check_not_in_store

    check_apart(out, "output folder", [("run", run), ("camera run", camera_run), *(("image", p) for p in images)])
    check_not_in_store(out, "output folder")
    there = [Path(out) / f"{name}{suffix}" for name in names for suffix in OUTPUT_SUFFIXES]
    there = [p for p in there if p.exists()]
    if there and not overwrite:
        raise SceneforgeError(f"{out}: already holds {listed([p.name for p in there], 1)}; pass --overwrite to replace the "
                              "files of these photos, or choose another folder")


def read_photo(path: Path) -> np.ndarray:
    """(H, W, 3) uint8 RGB of an image file."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            return np.asarray(im.convert("RGB"))
    except (OSError, UnidentifiedImageError) as e:
        raise SceneforgeError(f"{path}: not a readable image ({e})") from None


@dataclass(frozen=True)
class Reconstruction:
    """One photo's predictions (the arrays of ``NAME.npz``) and its mesh."""

    name: str
    rgb: np.ndarray
    arrays: dict
    vertices: np.ndarray
    faces: np.ndarray


def _frustum_mask(points: np.ndarray, K: np.ndarray, pose: np.ndarray, width: int, height: int) -> np.ndarray:
    """(n,) bool: world points (n, 3) in front of the camera and inside its image."""
    cam = (points - pose[:3, 3]) @ pose[:3, :3]
    with np.errstate(invalid="ignore", divide="ignore"):
        uv = cam @ K.T
        u, v = uv[:, 0] / uv[:, 2], uv[:, 1] / uv[:, 2]
        return (cam[:, 2] > 0) & (u >= 0) & (u <= width) & (v >= 0) & (v <= height)


def _overhead_camera(depth: np.ndarray, K: np.ndarray, pose: np.ndarray, camera: PhotoCamera, resolution: int):
    """The overhead camera (docs/spec.md §6) of one photo's predicted layers (5, H, W)."""
    from sceneforge.cameras import Camera
    from sceneforge.overhead import FrontalPoints, OverheadConfig, gravity_frame, place_overhead_camera

    H, W = depth.shape[1:]
    frame = gravity_frame(Camera(K, pose, W, H))
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    rays = np.stack([u, v, np.ones_like(u)], axis=-1) @ np.linalg.inv(K).T

    def points(layer):
        d = depth[layer]
        ok = np.isfinite(d)
        return frame.to_frame((rays[ok] * d[ok, None]) @ pose[:3, :3].T + pose[:3, 3])

    objects = np.concatenate([points(k) for k in range(4)])
    top = max((float(p[:, 1].max()) for p in (points(0), points(1), points(4)) if len(p)), default=0.0)
    env = depth[4][np.isfinite(depth[4])].astype(np.float64)
    n = len(objects)
    fp = FrontalPoints(objects, np.full(n, -1), np.zeros(n, bool), env, np.zeros(0, np.int64), (), top)
    config = OverheadConfig(resolution=resolution)
    return place_overhead_camera(frame, fp, W / 2 / K[0, 0], -camera.height, config)


def reconstruct(run: str | Path, images: Sequence[str | Path], out: str | Path, *,
                camera: PhotoCamera | None = None, camera_run: str | Path | None = None,
                resolution: int = 300, batch_size: int = 4, device: str = "auto",
                floor_removal: str = "segmentation", min_object_probability: float | None = None,
                min_overhead_object_probability: float | None = None, overwrite: bool = False,
                progress=None) -> list[Path]:
    """Reconstruct every photo of ``images`` (files or folders) with the overhead ``run``
    into the folder ``out`` (files: module docstring); the PLY paths written.

    camera     : intrinsics, height and pitch of the photos (default: the paper's)
    camera_run : a camera proposal run placing the overhead camera (default: the heuristics)
    resolution : overhead image size, pixels
    min_object_probability, min_overhead_object_probability : as for
                 :func:`~sceneforge.learn.predict.predict` (None: the arg-max, the paper's)
    overwrite  : replace the files of these photos that ``out`` already holds (else refused)
    Raises :class:`SceneforgeError` for a run that is not an overhead run, unreadable images,
    or an ``out`` that would lose data: one of the inputs (or inside or holding one), inside a
    store, or holding a file of these photos' names without ``overwrite``.
    """
    camera = camera or PhotoCamera()
    paths = photo_paths(images)
    check_outputs(out, [p.stem for p in paths], run=run, camera_run=camera_run, images=paths, overwrite=overwrite)
    dev = resolve_device(device)
    config, nets = load_run(run, dev)
    if not get_stage(config.stage).uses_eft:
        raise SceneforgeError(f"{run} is a {config.stage} run: reconstruct needs an overhead run (it predicts the "
                              "frontal layers with its frozen depth and seg runs, and the overhead heights)")
    cam_nets = None
    if camera_run is not None:
        cam_config, cam_nets = load_run(camera_run, dev)
        if cam_config.stage != "camera":
            raise SceneforgeError(f"{camera_run} is a {cam_config.stage} run, not a camera run")
    eft = EpipolarFeatureTransformer(config.eft, resolution=resolution)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    if progress:
        progress.start("reconstructing photos", len(paths), "photos")
    photos = [(p, read_photo(p)) for p in paths]
    # a batch holds photos of one size: the nets run on whole tensors
    by_size: dict[tuple, list] = {}
    for p, rgb in photos:
        by_size.setdefault(rgb.shape, []).append((p, rgb))
    for group in by_size.values():
        for start in range(0, len(group), batch_size):
            chunk = group[start:start + batch_size]
            for rec in _reconstruct_batch(nets, cam_nets, eft, chunk, camera, resolution, floor_removal, dev,
                                          (min_object_probability, min_overhead_object_probability)):
                written.append(_write(rec, out))
            if progress:
                progress.advance(len(chunk))
    return written


@torch.no_grad()
def _reconstruct_batch(nets, cam_nets, eft, chunk, camera: PhotoCamera, resolution: int, floor_removal: str,
                       dev, thresholds: tuple[float | None, float | None] = (None, None)) -> list[Reconstruction]:
    H, W = chunk[0][1].shape[:2]
    K = camera.intrinsics(W, H)
    pose = camera.pose()
    rgb = torch.from_numpy(np.stack([normalize_rgb(im) for _, im in chunk])).to(dev)
    B = len(chunk)
    depth_out, seg_out = nets["depth"](rgb), nets["seg"](rgb)
    from .networks import masked_layers

    masked = masked_layers(depth_out.prediction, seg_out.prediction)
    layers = masked.float().cpu().numpy()
    # the overhead camera and the EFT read the arg-max layers the nets were trained with;
    # a least object probability only thins the layers reconstructed
    cams = [_overhead_camera(layers[k], K, pose, camera, resolution) for k in range(B)]
    if thresholds[0] is not None:
        layers = masked_layers(masked, seg_out.prediction, thresholds[0]).float().cpu().numpy()
    To = np.stack([c.cam_to_world for c in cams])
    extent = np.array([c.half_extent for c in cams])
    params = np.stack([c.params for c in cams])
    Ks, poses = np.repeat(K[None], B, 0), np.repeat(pose[None], B, 0)
    if cam_nets is not None:
        feats = cam_nets["depth"](rgb)
        proposal = cam_nets["camera"](feats.features, feats.encoding).cpu().numpy()
        To, extent, params = proposed_overhead_cameras(Ks, poses, (H, W), To, params, proposal)
    batch = {"rgb": rgb, "K": torch.from_numpy(Ks).to(dev), "cam_to_world": torch.from_numpy(poses).to(dev),
             "overhead_cam_to_world": torch.from_numpy(To).to(dev),
             "overhead_extent": torch.from_numpy(extent).to(dev), "overhead_params": torch.from_numpy(params).to(dev)}
    x, _, logits = overhead_input(nets, eft, batch)
    top = nets["overhead_seg"](x)
    heights = overhead_heights(nets["height"](x)[:, 0], top, floor_removal, thresholds[1]).float().cpu().numpy()
    top_classes = CLASS_TO_NYU40[top.argmax(dim=1).cpu().numpy()].astype(np.uint8)
    classes = logits.reshape(B, SEG_LAYERS, SEG_CLASSES, H, W).argmax(dim=2).cpu().numpy()
    category = np.where(np.isfinite(layers[:, [0, 2]]), CLASS_TO_NYU40[classes], 0).astype(np.uint8)
    return [_one(name.stem, im, layers[k], category[k], heights[k], top_classes[k], K, pose, To[k], float(extent[k]),
                 params[k]) for k, (name, im) in enumerate(chunk)]


def _one(name, rgb, depth, category, height, top_classes, K, pose, To, extent, params) -> Reconstruction:
    """One photo's arrays and mesh: overhead heights outside the frustum removed."""
    from sceneforge.conventions import overhead_pixel_centre
    from sceneforge.evaluate.depth_mesh import concatenate, height_map_mesh, perspective_mesh

    H, W = depth.shape[1:]
    R = height.shape[0]
    c = overhead_pixel_centre(np.arange(R), extent, R)
    y, x = np.meshgrid(c, c, indexing="ij")
    below = params[2] - np.nan_to_num(height)
    centres = np.stack([x, y, below], axis=-1).reshape(-1, 3) @ To[:3, :3].T + To[:3, 3]
    inside = _frustum_mask(centres, K, pose, W, H).reshape(R, R)
    height = np.where(inside, height, np.nan).astype(np.float32)
    meshes = [perspective_mesh(depth[k], K, pose) for k in range(5)]
    meshes.append(height_map_mesh(height, To, extent, float(params[2])))
    mesh = concatenate(meshes)
    arrays = {"depth": depth, "category": category, "overhead_height": height, "overhead_category": top_classes,
              "K": K, "cam_to_world": pose, "overhead_cam_to_world": To, "overhead_extent": np.float64(extent),
              "overhead_params": params}
    return Reconstruction(name, rgb, arrays, mesh.vertices, mesh.faces)


class _OneView:
    """A reconstruction as the one-view store :func:`sceneforge.store.export_exr` reads."""

    def __init__(self, rec: Reconstruction):
        self.rec = rec

    def __len__(self) -> int:
        return 1

    def view(self, index: int) -> dict:
        a = self.rec.arrays
        R = a["overhead_height"].shape[0]
        return {**a, "rgb": self.rec.rgb, "house_id": self.rec.name, "camera_id": 0,
                "overhead_depth": np.full((5, R, R), np.nan, np.float32)}


def _write(rec: Reconstruction, out: Path) -> Path:
    import trimesh

    from sceneforge.store import export_exr

    np.savez_compressed(out / f"{rec.name}.npz", **rec.arrays)
    try:
        export_exr(_OneView(rec), 0, out / f"{rec.name}.exr")
    except SceneforgeError:
        pass  # OpenEXR is an optional extra: the npz holds the same arrays
    panel(rec).savefig(out / f"{rec.name}.png", dpi=100, bbox_inches="tight")
    ply = out / f"{rec.name}.ply"
    trimesh.Trimesh(rec.vertices, rec.faces, process=False).export(str(ply))
    return ply


def panel(rec: Reconstruction):
    """A matplotlib figure: the photo, D1, D3, D5, the layer-1 classes and the overhead heights."""
    from matplotlib.figure import Figure

    a = rec.arrays
    fig = Figure(figsize=(15, 2.6))
    images = [("photo", rec.rgb, None), ("D1", a["depth"][0], "viridis"), ("D3", a["depth"][2], "viridis"),
              ("D5 (envelope)", a["depth"][4], "viridis"), ("classes, layer 1", a["category"][0], "tab20"),
              ("overhead height", a["overhead_height"], "magma")]
    for k, (title, image, cmap) in enumerate(images):
        ax = fig.add_subplot(1, len(images), k + 1)
        ax.imshow(image, cmap=cmap, interpolation="nearest")
        ax.set_title(title, fontsize=9)
        ax.axis("off")
    fig.suptitle(rec.name, fontsize=10)
    return fig
