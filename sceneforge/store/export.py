"""Stored views as files (``sceneforge export``): the formats (:data:`FORMATS`: one OpenEXR
file per view, :func:`export_exr`; LaRI's ScanNet++ layout, :func:`lari_files`), and which
folders export may write into (:func:`check_export_folder`)."""

from __future__ import annotations

import io
import json
import os
import re
import shutil
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Callable, Collection, Mapping

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


# ---------------------------------------------------------------------------------- LaRI

#: the ray-intersection layers LaRI reads (docs/spec.md §4.7)
LARI_DEPTH = "intersections/depth"
#: the labels of those layers written beside LaRI's ``ldi`` key: npz key → store array
LARI_LABELS = {"normal": "intersections/normal", "instance": "intersections/instance",
               "category": "intersections/category", "front_facing": "intersections/front_facing"}
#: LaRI's depth of an empty layer: PyTorch3D's rasteriser pads its zbuf with -1 and their
#: loader takes depth > 0 as valid (LaRI ``src/utils/geometry.py``)
LARI_EMPTY = -1.0
#: the JPEG quality of the images (LaRI's ScanNet++ images are JPEG)
LARI_JPEG_QUALITY = 95
#: the files of one view, in LaRI's ScanNet++ layout (``src/datasets/scannetpp.py``)
LARI_IMAGE = "{house}/dslr/downscaled_undistorted_images/{view}.JPG"
LARI_LDI = "{house}/dslr/ldi/{view}_ldi.npz"
LARI_CAMERA = "{house}/dslr/ldi/{view}.npz"
#: the list of a split's views (``"HOUSE VIEW"`` entries, as LaRI's ``data_lists/*.json``)
LARI_LIST = "lari_{split}.json"
#: the list of every view, for a store without a house split
LARI_ALL = "all"


def _view_id(index: int) -> str:
    return f"view_{index:06d}"


def lari_views(store: SceneStore) -> list[int]:
    """The views a LaRI export writes: the valid ones (a failed view has no layers).

    Raises :class:`SceneforgeError` when the store has no ray-intersection layers or no RGB
    (LaRI's loader reads both), or when a house id would break LaRI's list entries
    (``"HOUSE VIEW"``, split at the space) or paths.
    """
    if LARI_DEPTH not in store.names:
        raise SceneforgeError(f"{store.where}: the store has no ray-intersection layers ({LARI_DEPTH}), which "
                              "LaRI reads; render it with --intersections K (e.g. --intersections 10)")
    if "rgb" not in store.names:
        raise SceneforgeError(f"{store.where}: the store has no RGB images, which LaRI's loader reads; "
                              "render it with --rgb raster or pathtraced")
    views = np.flatnonzero(np.asarray(store.array("valid")[:], dtype=bool)).tolist()
    houses = {str(h) for h in np.asarray(store.array("house_id")[:])[views]}
    bad = sorted(h for h in houses if re.search(r"\s|\\", h) or {"", ".", ".."} & set(h.split("/")))
    if bad:
        raise SceneforgeError(f"{store.where}: house ids {listed(map(repr, bad))} cannot name LaRI's folders and "
                              "list entries (no spaces, backslashes or empty, '.' or '..' parts); rename the houses")
    return views


def _npz(compressed: bool, **arrays: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    (np.savez_compressed if compressed else np.savez)(buffer, **arrays)
    return buffer.getvalue()


def lari_arrays(store: SceneStore, index: int) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """View ``index`` as LaRI reads it: the ``*_ldi.npz`` arrays and the camera ``*.npz`` arrays.

    ``*_ldi.npz``: LaRI's key ``ldi`` (H, W, L) float16, the planar depth of the L
    intersection layers, :data:`LARI_EMPTY` past the ray's last surface (LaRI's
    ``save_ldi_matrix``); and sceneforge's labels of those layers, layer axis after the
    pixels as in ``ldi`` (the store's fill past the last surface): ``normal`` (H, W, L, 3)
    float16 (NaN), ``instance`` (H, W, L) int32 (−1), ``category`` (H, W, L) uint8 NYU40
    (0), ``front_facing`` (H, W, L) bool (false).

    camera ``*.npz`` (LaRI's ScanNet++ keys): ``K`` (3, 3) float32, the store's intrinsics
    with the pixel centres at integer coordinates, as LaRI's ``depthmap_to_camera_coordinates``
    unprojects (sceneforge's are at integer + 0.5: cx and cy less 0.5); ``Tr_w2c_cv`` (4, 4)
    float32, world to camera in OpenCV axes (the inverse of ``cam_to_world``).
    """
    def read(name: str) -> np.ndarray:
        return np.asarray(store.array(name)[index])

    depth = read(LARI_DEPTH)  # (L, H, W)
    ldi = {"ldi": np.where(np.isnan(depth), np.float32(LARI_EMPTY), depth).transpose(1, 2, 0).astype(np.float16)}
    for key, name in LARI_LABELS.items():
        if name in store.names:
            labels = read(name)  # (L, H, W), normals (L, 3, H, W)
            ldi[key] = labels.transpose(2, 3, 0, 1).astype(np.float16) if key == "normal" else labels.transpose(1, 2, 0)
    K = read("K").astype(np.float64)
    K[:2, 2] -= 0.5
    camera = {"K": K.astype(np.float32), "Tr_w2c_cv": np.linalg.inv(read("cam_to_world")).astype(np.float32)}
    return ldi, camera


def _write_bytes(data: bytes, path) -> None:
    Path(path).write_bytes(data)


def lari_files(store: SceneStore, index: int) -> list[tuple[str, Callable]]:
    """The three files of view ``index`` in LaRI's ScanNet++ layout (:data:`LARI_IMAGE`,
    :data:`LARI_LDI`, :data:`LARI_CAMERA`; HOUSE the house id, VIEW ``view_`` and the
    view index in six digits), each (path relative to the export folder, writer of the
    file at a given path); the arrays are :func:`lari_arrays`', the image the store's sRGB
    as JPEG."""
    from PIL import Image

    where = {"house": str(np.asarray(store.array("house_id")[index])), "view": _view_id(index)}
    ldi, camera = lari_arrays(store, index)
    jpeg = io.BytesIO()
    Image.fromarray(np.asarray(store.array("rgb")[index])).save(jpeg, format="JPEG", quality=LARI_JPEG_QUALITY)
    return [(LARI_IMAGE.format(**where), partial(_write_bytes, jpeg.getvalue())),
            (LARI_LDI.format(**where), partial(_write_bytes, _npz(True, **ldi))),
            (LARI_CAMERA.format(**where), partial(_write_bytes, _npz(False, **camera)))]


def lari_lists(store: SceneStore, views: list[int], split: Mapping[str, Collection[str]] | None) -> dict[str, bytes]:
    """LaRI's data lists of ``views``: JSON lists of ``"HOUSE VIEW"`` entries, one per split
    of ``split`` (house ids by split name: ``lari_train.json``, ``lari_val.json``,
    ``lari_test.json``), or ``lari_all.json`` of every view where ``split`` is None.

    Raises :class:`SceneforgeError` when a view's house is in none of the splits.
    """
    ids = np.asarray(store.array("house_id")[:])
    house = {i: str(ids[i]) for i in views}
    if split is None:
        split = {LARI_ALL: set(house.values())}
    missing = sorted(set(house.values()).difference(*map(set, split.values())))
    if missing:
        raise SceneforgeError(f"{store.where}: houses {listed(missing)} are in none of the splits of its split "
                              "file; give --split-file with a split of this store's houses")
    lists = {}
    for name, houses in split.items():
        members = set(houses)
        entries = [f"{house[i]} {_view_id(i)}" for i in views if house[i] in members]
        lists[LARI_LIST.format(split=name)] = (json.dumps(entries, indent=1) + "\n").encode()
    return lists


# ------------------------------------------------------------------------------- formats


@dataclass(frozen=True)
class ExportFormat:
    """One format of ``sceneforge export``: which views it writes, each view's files and
    the files beside them.

    help  : what ``export --format`` says of it
    views : (store) → the view indices it writes; raises :class:`SceneforgeError`, before
            anything is written, where the store cannot be written in this format
    files : (store, index) → the view's files: (path relative to the export folder,
            writer of that file at a given path)
    lists : (store, views, split) → files beside the views, {relative path: bytes};
            ``split`` house ids by split name (the store's house split), or None (none)
    paths : the relative paths of the files it writes (``/`` separated), a regular
            expression; :func:`check_export_folder` adds the temporary files of killed
            writes (``cli.output.atomic_output``)
    """

    help: str
    views: Callable[[SceneStore], list[int]]
    files: Callable[[SceneStore, int], list[tuple[str, Callable]]]
    paths: str
    lists: Callable[[SceneStore, list[int], Mapping[str, Collection[str]] | None], dict[str, bytes]] | None = None


def _exr_files(store: SceneStore, index: int) -> list[tuple[str, Callable]]:
    return [(f"{_view_id(index)}.exr", partial(export_exr, store, index))]


def _paths(folder: str, stem: str, suffix: str) -> str:
    """Files ``folder + stem + suffix``, and the temporary files of their killed writes."""
    return rf"{folder}(?:{stem}|\.{stem}\.[0-9a-f]{{8}}\.partial){suffix}"


_VIEW = r"view_\d{6,}"
_HOUSE = r"(?:[^/\s\\]+/)+dslr/"
#: the file formats of ``sceneforge export --format``, by name
FORMATS: dict[str, ExportFormat] = {
    "exr": ExportFormat(
        help="one multi-part OpenEXR per view, view_NNNNNN.exr (frontal: D1..D5 and RGB as float channels, "
             "the classes category.D1/D3/D5 and instances instance.D1/D3 as uint channels; overhead: height, "
             "D1..D5 and category; camera metadata in the headers)",
        views=lambda store: list(range(len(store))), files=_exr_files, paths=_paths("", _VIEW, r"\.exr")),
    "lari": ExportFormat(
        help="LaRI's ScanNet++ layout, for a store rendered with --intersections K and RGB: per valid view "
             "an image, its K layers and its camera under HOUSE/dslr/, and lists lari_*.json (docs/store.md)",
        views=lari_views, files=lari_files, lists=lari_lists,
        paths="|".join([_paths(_HOUSE + "downscaled_undistorted_images/", _VIEW, r"\.JPG"),
                        _paths(_HOUSE + "ldi/", _VIEW + "(?:_ldi)?", r"\.npz"),
                        _paths("", "lari_(?:train|val|test|all)", r"\.json")])),
}
#: the relative paths of every file export writes, in any format
EXPORT_FILE = re.compile("|".join(f"(?:{f.paths})" for f in FORMATS.values()))


def _files_below(folder: Path) -> list[Path]:
    return sorted(p for p in folder.rglob("*") if not p.is_dir())


def check_export_folder(out_dir: str | os.PathLike, store: str, *, overwrite: bool) -> list[Path]:
    """Check that ``sceneforge export`` may write the views of ``store`` into ``out_dir``,
    and return the entries of an earlier export there (files and folders of
    :data:`EXPORT_FILE`, in any format; empty unless ``overwrite``), which the caller
    removes (:func:`remove_export`) before writing, so that the folder never mixes two
    exports (an earlier export of a larger store left views beyond this one's count).

    Raises :class:`SceneforgeError`, before anything is written, when ``out_dir`` is the
    store, lies inside it or holds it, lies inside any zarr store or is one, holds anything
    export did not write (a folder is export's when it holds files and only files export
    writes), or, without ``overwrite``, holds an earlier export.
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

    def exports(entry: Path) -> bool:
        files = _files_below(entry) if entry.is_dir() else [entry]
        return bool(files) and all(EXPORT_FILE.fullmatch(p.relative_to(folder).as_posix()) for p in files)

    entries = sorted(folder.iterdir())
    foreign = [p.name + "/" * p.is_dir() for p in entries if not exports(p)]
    if foreign:
        raise SceneforgeError(f"{out_dir}: the export folder holds files export did not write: {listed(foreign)}; "
                              "export writes into an empty folder, or over an earlier export (--overwrite): "
                              "choose another folder")
    if entries and not overwrite:
        files = sum(len(_files_below(p)) if p.is_dir() else 1 for p in entries)
        raise SceneforgeError(f"{out_dir}: the export folder holds an earlier export "
                              f"({plural(files, 'file')}); pass --overwrite to replace it")
    return entries


def remove_export(entries: list[Path]) -> None:
    """Remove the files and folders of an earlier export (:func:`check_export_folder`'s)."""
    for path in entries:
        if path.is_dir():
            shutil.rmtree(path)
        else:
            path.unlink()
