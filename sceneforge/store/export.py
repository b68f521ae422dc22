"""Stored views as files (``sceneforge export``): one OpenEXR file per view
(:func:`export_exr`), and which folders export may write into (:func:`check_export_folder`)."""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from ..conventions import CLASS_LAYERS, FRONT_LAYERS, LAYER_NAMES
from ..errors import MissingDependencyError, SceneforgeError, listed, plural
from .guard import check_apart, check_not_in_store, describe_kind, store_kind
from .reader import SceneStore


def _srgb_to_linear(rgb: np.ndarray) -> np.ndarray:
    c = rgb.astype(np.float32) / 255.0
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4).astype(np.float32)


def export_exr(store: SceneStore, index: int, path) -> None:
    """Write view ``index`` as a two-part OpenEXR file (OpenEXR >= 3.2 Python API).

    Part ``frontal`` (H × W): FLOAT channels ``D1``..``D5`` (planar depth, metres, NaN = no
    surface) and, with RGB, linear ``R``, ``G``, ``B``; UINT channels ``category.D1``,
    ``category.D3``, ``category.D5`` (the NYU40 class of each layer's surface, 0 = none: the
    store's ``category``) and ``instance.D1``, ``instance.D3`` (the house instance index,
    the store's ``instance``: its int32 bits, so none, -1, reads 4294967295 until viewed as
    int32); a view without them (a reconstruction: classes of D1 and D3 only) has the
    channels of what it holds. Part ``overhead`` (Ho × Wo): FLOAT ``height`` and ``D1``..``D5``, UINT
    ``category`` (the store's ``overhead_category``). Headers carry ``K`` (3×3),
    ``cam_to_world`` (4×4, OpenCV axes), ``house_id``, ``camera_id`` and ``view``; the
    overhead part also ``overhead_cam_to_world``, ``overhead_extent`` and ``tx ty tz theta sigma``.
    """
    try:
        import OpenEXR
    except ImportError as e:
        raise MissingDependencyError("OpenEXR", "EXR export", "pip install sceneforge[store]") from e

    v = store.view(index)
    H, W = v["depth"].shape[1:]
    Ho, Wo = v["overhead_height"].shape
    # parts of one file share the display window; each keeps its own data window
    display = (np.array([0, 0], np.int32), np.array([max(W, Wo) - 1, max(H, Ho) - 1], np.int32))
    common = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage, "displayWindow": display,
              "house_id": str(v["house_id"]), "camera_id": int(v["camera_id"]), "view": int(index) % len(store),
              "K": v["K"].astype(np.float64), "cam_to_world": v["cam_to_world"].astype(np.float64)}
    frontal = {name: np.ascontiguousarray(v["depth"][k]) for k, name in enumerate(LAYER_NAMES)}
    if "rgb" in v:
        lin = _srgb_to_linear(v["rgb"])
        frontal.update({c: np.ascontiguousarray(lin[..., k]) for k, c in enumerate("RGB")})
    # OpenEXR's only integer channel type is UINT (32 bits): classes widen to it, instances
    # keep their bits, so every value, -1 included, reads back exactly
    # a reconstruction (sceneforge reconstruct) has the classes of D1 and D3 only, no instances
    frontal.update({f"category.{LAYER_NAMES[layer]}": c.astype(np.uint32)
                    for layer, c in zip(CLASS_LAYERS, v["category"])})
    if "instance" in v:
        frontal.update({f"instance.{LAYER_NAMES[layer]}": np.ascontiguousarray(v["instance"][k]).view(np.uint32)
                        for k, layer in enumerate(FRONT_LAYERS)})
    overhead = {name: np.ascontiguousarray(v["overhead_depth"][k]) for k, name in enumerate(LAYER_NAMES)}
    overhead["height"] = np.ascontiguousarray(v["overhead_height"])
    overhead["category"] = v["overhead_category"].astype(np.uint32)
    params = dict(zip(("tx", "ty", "tz", "theta", "sigma"), map(float, v["overhead_params"])))
    top = {**common, "overhead_cam_to_world": v["overhead_cam_to_world"].astype(np.float64),
           "overhead_extent": float(v["overhead_extent"]), **params}
    parts = [OpenEXR.Part(common, frontal, name="frontal"), OpenEXR.Part(top, overhead, name="overhead")]
    OpenEXR.File(parts).write(str(path))


#: the file formats of ``sceneforge export --format``: name → writer(store, index, path)
FORMATS = {"exr": export_exr}
#: the names of the files export writes: ``view_NNNNNN.<format>``, and the temporary file of
#: one whose write was killed (``.view_NNNNNN.<8 hex>.partial.<format>``, cli.output.atomic_output)
_SUFFIX = rf"\.({'|'.join(FORMATS)})"
EXPORT_FILE = re.compile(rf"view_\d{{6,}}{_SUFFIX}|\.view_\d{{6,}}\.[0-9a-f]{{8}}\.partial{_SUFFIX}")


def check_export_folder(out_dir: str | os.PathLike, store: str, *, overwrite: bool) -> list[Path]:
    """Check that ``sceneforge export`` may write the views of ``store`` into ``out_dir``,
    and return the files of an earlier export there (:data:`EXPORT_FILE`, empty unless
    ``overwrite``), which the caller deletes before writing, so that the folder never mixes
    two exports (an earlier export of a larger store left views beyond this one's count).

    Raises :class:`SceneforgeError`, before anything is written, when ``out_dir`` is the
    store, lies inside it or holds it, lies inside any zarr store or is one, holds anything
    export did not write, or, without ``overwrite``, holds an earlier export.
    """
    check_apart(out_dir, "export folder", [("store", store)])
    check_not_in_store(out_dir, "export folder")
    kind = store_kind(out_dir)
    if kind is not None:
        raise SceneforgeError(f"{out_dir}: the export folder is {describe_kind(kind)}; export writes its "
                              "files into a folder of their own: choose another path")
    folder = Path(out_dir)
    if not folder.is_dir():
        return []  # made by the caller; a file there is its writability check's to report
    entries = sorted(folder.iterdir())
    foreign = [p.name + "/" * p.is_dir() for p in entries if p.is_dir() or not EXPORT_FILE.fullmatch(p.name)]
    if foreign:
        raise SceneforgeError(f"{out_dir}: the export folder holds files export did not write: {listed(foreign)}; "
                              "export writes into an empty folder, or over an earlier export (--overwrite): "
                              "choose another folder")
    if entries and not overwrite:
        raise SceneforgeError(f"{out_dir}: the export folder holds an earlier export "
                              f"({plural(len(entries), 'file')}); pass --overwrite to replace it")
    return entries
