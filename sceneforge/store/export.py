"""A stored view as an OpenEXR file (``sceneforge export``)."""

from __future__ import annotations

import numpy as np

from ..conventions import LAYER_NAMES
from ..errors import MissingDependencyError
from .reader import SceneStore


def _srgb_to_linear(rgb: np.ndarray) -> np.ndarray:
    c = rgb.astype(np.float32) / 255.0
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4).astype(np.float32)


def export_exr(store: SceneStore, index: int, path) -> None:
    """Write view ``index`` as a two-part OpenEXR file (OpenEXR >= 3.2 Python API).

    Part ``frontal`` (H × W): float channels ``D1``..``D5`` (planar depth, metres, NaN = no
    surface) and, with RGB, linear ``R``, ``G``, ``B``. Part ``overhead`` (Ho × Wo):
    ``height`` and ``D1``..``D5``. Headers carry ``K`` (3×3), ``cam_to_world`` (4×4, OpenCV
    axes), ``house_id``, ``camera_id`` and ``view``; the overhead part also
    ``overhead_cam_to_world``, ``overhead_extent`` and ``tx ty tz theta sigma``.
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
    overhead = {name: np.ascontiguousarray(v["overhead_depth"][k]) for k, name in enumerate(LAYER_NAMES)}
    overhead["height"] = np.ascontiguousarray(v["overhead_height"])
    params = dict(zip(("tx", "ty", "tz", "theta", "sigma"), map(float, v["overhead_params"])))
    top = {**common, "overhead_cam_to_world": v["overhead_cam_to_world"].astype(np.float64),
           "overhead_extent": float(v["overhead_extent"]), **params}
    parts = [OpenEXR.Part(common, frontal, name="frontal"), OpenEXR.Part(top, overhead, name="overhead")]
    OpenEXR.File(parts).write(str(path))
