"""Looking at a stored view: a PNG panel and a coloured point cloud of its layers, and a
predicted view under its truth.

The panel shows the RGB image, D1..D5 on one colour scale, the classes of layers 1, 3 and
5, the overhead height map and classes, and a top-down view (world X right, Z down) of the
view's layer points with the frontal camera and the overhead camera's footprint.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .conventions import LAYER_NAMES, NYU40_NAMES
from .errors import MissingDependencyError

if TYPE_CHECKING:
    import matplotlib.figure

    from .store import SceneStore

#: colour of each layer D1..D5 in point clouds and the top-down view (RGB, 0..255)
LAYER_COLORS = np.array([[230, 60, 50], [240, 150, 40], [60, 110, 230], [80, 190, 220], [150, 150, 150]],
                        dtype=np.uint8)


def layer_points(K: np.ndarray, cam_to_world: np.ndarray, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World points of every finite depth pixel.

    K            : (3, 3) float   intrinsics, pixel centres at integer + 0.5
    cam_to_world : (4, 4) float   OpenCV pose
    depth        : (L, H, W) float planar depth per layer, NaN = no surface
    Returns points (n, 3) float64 and their layer (n,) int64, layer by layer in row-major order.
    """
    L, H, W = depth.shape
    layer, i, j = np.nonzero(np.isfinite(depth))
    z = depth[layer, i, j].astype(np.float64)
    uv1 = np.stack([j + 0.5, i + 0.5, np.ones_like(z)], axis=1)
    cam = (uv1 @ np.linalg.inv(K).T) * z[:, None]
    return cam @ cam_to_world[:3, :3].T + cam_to_world[:3, 3], layer


def write_point_cloud(store: "SceneStore", index: int, path: str | Path) -> Path:
    """Write view ``index``'s D1..D5 points as a PLY point cloud coloured by layer
    (:data:`LAYER_COLORS`), world coordinates in metres."""
    import trimesh

    v = store.view(index)
    points, layer = layer_points(v["K"], v["cam_to_world"], v["depth"])
    colors = np.column_stack([LAYER_COLORS[layer], np.full(len(layer), 255, np.uint8)])
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    trimesh.PointCloud(points, colors=colors).export(path)
    return path


def _footprint(overhead_cam_to_world: np.ndarray, extent: float) -> np.ndarray:
    """(5, 3) float64 the overhead image's corners in world coordinates, closed."""
    R, t = overhead_cam_to_world[:3, :3], overhead_cam_to_world[:3, 3]
    corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1], [-1, -1]], dtype=np.float64) * extent
    return t + corners[:, :1] * R[:, 0] + corners[:, 1:] * R[:, 1]


def _image(ax, data, title, cmap=None, fontsize=10, **kw) -> None:
    """``data`` on ``ax`` pixel for pixel under ``title``; NaN (no surface) shows white."""
    import matplotlib

    if cmap is not None:
        cmap = (matplotlib.colormaps[cmap] if isinstance(cmap, str) else cmap).with_extremes(bad="white")
    ax.imshow(data, interpolation="nearest", cmap=cmap, **kw)
    ax.set_title(title, fontsize=fontsize)


def view_panel(store: "SceneStore", index: int) -> "matplotlib.figure.Figure":
    """The panel of view ``index`` as a matplotlib figure (Agg, no display needed)."""
    try:
        from matplotlib.colors import ListedColormap
        from matplotlib.figure import Figure
    except ImportError as e:
        raise MissingDependencyError("matplotlib", "the view panel", "pip install sceneforge[plot]") from e
    from .houses.inspect import category_colors

    v = store.view(index)
    classes = ListedColormap(category_colors() / 255.0)
    fig = Figure(figsize=(20, 12), layout="constrained")
    grid = fig.add_gridspec(3, 5)
    axes = [[fig.add_subplot(grid[r, c]) for c in range(5)] for r in range(2)]
    axes.append([fig.add_subplot(grid[2, 0]), fig.add_subplot(grid[2, 1]), fig.add_subplot(grid[2, 2:4]),
                 fig.add_subplot(grid[2, 4])])
    for ax in fig.axes:
        ax.set_xticks([])
        ax.set_yticks([])

    if "rgb" in v:
        _image(axes[0][0], v["rgb"], "RGB")
    else:
        axes[0][0].set_title("RGB (not rendered)", fontsize=10)
    depth = v["depth"]
    finite = depth[np.isfinite(depth)]
    vmax = float(finite.max()) if finite.size else 1.0
    for k, name in enumerate(LAYER_NAMES):
        ax = axes[0][k + 1] if k < 4 else axes[1][0]
        _image(ax, depth[k], f"{name} (m)", cmap="viridis", vmin=0.0, vmax=vmax)
    fig.colorbar(axes[1][0].images[0], ax=[*axes[0][1:], axes[1][0]], label="planar depth (m), white = no surface",
                 shrink=0.8)
    for k, name in enumerate(("D1", "D3", "D5")):
        _image(axes[1][k + 1], v["category"][k], f"class of {name}", cmap=classes, vmin=0, vmax=len(NYU40_NAMES) - 1)
    present = sorted(set(np.unique(v["category"]).tolist()) | set(np.unique(v["overhead_category"]).tolist()))
    axes[1][4].axis("off")
    axes[1][4].set_title("classes", fontsize=10)
    for row, c in enumerate(present):
        y = 1 - 0.06 * (row + 1)
        axes[1][4].scatter([0.05], [y], marker="s", s=60, color=classes(c), edgecolors="k",
                           transform=axes[1][4].transAxes)
        axes[1][4].text(0.12, y, NYU40_NAMES[c], va="center", fontsize=9, transform=axes[1][4].transAxes)
    _image(axes[2][0], v["overhead_height"], "overhead height above floor (m)", cmap="magma", vmin=0.0)
    fig.colorbar(axes[2][0].images[0], ax=axes[2][0], shrink=0.8)
    _image(axes[2][1], v["overhead_category"], "overhead classes", cmap=classes, vmin=0, vmax=len(NYU40_NAMES) - 1)

    _top_down(axes[2][2], v)
    axes[2][3].axis("off")
    tx, ty, tz, theta, sigma = v["overhead_params"]
    lines = [f"view {index % len(store)} of {len(store)}", f"house {v['house_id']}", f"camera {int(v['camera_id'])}",
             f"valid: {bool(v['valid'])}", f"tx {tx:.2f}  ty {ty:.2f} m", f"tz {tz:.2f} m  sigma {sigma:.2f} m",
             f"theta {theta:.4f} rad", f"half-extent {float(v['overhead_extent']):.2f} m"]
    axes[2][3].text(0.0, 1.0, "\n".join(lines), va="top", fontsize=10, family="monospace",
                    transform=axes[2][3].transAxes)
    return fig


def comparison_panel(pred: "SceneStore", truth: "SceneStore", index: int) -> "matplotlib.figure.Figure":
    """View ``index`` of a store of predictions (``sceneforge predict``) under the same view of
    its ground truth: the truth's RGB, D1..D5 on the truth's colour scale, the classes of
    layers 1 and 3, and the overhead heights; white = no surface (a masked or removed
    prediction). The caller checks that the two views are the same view."""
    try:
        from matplotlib.colors import ListedColormap
        from matplotlib.figure import Figure
    except ImportError as e:
        raise MissingDependencyError("matplotlib", "the comparison panel", "pip install sceneforge[plot]") from e
    from .houses.inspect import category_colors

    rows = (("truth", truth.view(index)), ("prediction", pred.view(index)))
    classes = ListedColormap(category_colors() / 255.0)
    fig = Figure(figsize=(22, 5.2), layout="constrained")
    axes = fig.subplots(2, 9)
    finite = rows[0][1]["depth"][np.isfinite(rows[0][1]["depth"])]
    vmax = float(finite.max()) if finite.size else 1.0
    heights = rows[0][1]["overhead_height"][np.isfinite(rows[0][1]["overhead_height"])]
    hmax = float(heights.max()) if heights.size else 1.0
    for r, (label, v) in enumerate(rows):
        panels = [(rows[0][1].get("rgb"), "RGB (the input)", {}),
                  *[(v["depth"][k], f"{name} (m)", {"cmap": "viridis", "vmin": 0.0, "vmax": vmax})
                    for k, name in enumerate(LAYER_NAMES)],
                  *[(v["category"][k], f"class of {name}",
                     {"cmap": classes, "vmin": 0, "vmax": len(NYU40_NAMES) - 1}) for k, name in ((0, "D1"), (1, "D3"))],
                  (v["overhead_height"], "overhead height (m)", {"cmap": "magma", "vmin": 0.0, "vmax": hmax})]
        for c, (data, title, kw) in enumerate(panels):
            ax = axes[r][c]
            ax.set_xticks([])
            ax.set_yticks([])
            if data is None:
                ax.set_title("RGB (not rendered)", fontsize=9)
                continue
            _image(ax, data, title if r == 0 else "", fontsize=9, **kw)
        axes[r][0].set_ylabel(label, fontsize=11)
    fig.suptitle(f"view {index}: house {rows[0][1]['house_id']}, camera {int(rows[0][1]['camera_id'])}"
                 "; top: the truth, bottom: the prediction", fontsize=10)
    return fig


def _top_down(ax, v: dict) -> None:
    """World X right, Z down: layer points, the frontal camera and the overhead footprint."""
    points, layer = layer_points(v["K"], v["cam_to_world"], v["depth"])
    step = max(1, len(points) // 20000)
    ax.scatter(points[::step, 0], points[::step, 2], s=0.5, c=LAYER_COLORS[layer[::step]] / 255.0)
    eye, forward = v["cam_to_world"][:3, 3], v["cam_to_world"][:3, 2]
    ax.plot([eye[0]], [eye[2]], "k^", markersize=8)
    ax.annotate("", xy=(eye[0] + forward[0], eye[2] + forward[2]), xytext=(eye[0], eye[2]),
                arrowprops={"arrowstyle": "->", "color": "k"})
    if bool(v["valid"]):
        box = _footprint(v["overhead_cam_to_world"], float(v["overhead_extent"]))
        ax.plot(box[:, 0], box[:, 2], "-", color="tab:purple", label="overhead footprint")
        ax.legend(loc="upper right", fontsize=8)
    ax.set_aspect("equal")
    ax.invert_yaxis()
    ax.set_title("top-down: layer points, camera, overhead footprint", fontsize=10)


def write_panel(store: "SceneStore", index: int, path: str | Path, truth: "SceneStore | None" = None) -> Path:
    """Write the panel of view ``index`` to a PNG at ``path``: :func:`view_panel`, or with
    ``truth`` (``store`` holding predictions) :func:`comparison_panel`."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig = view_panel(store, index) if truth is None else comparison_panel(store, truth, index)
    fig.savefig(path, dpi=80)
    return path
