"""How the overhead camera of a view was chosen: the ``sceneforge overhead-camera`` command's
library.

It does what a render run does up to the overhead camera (load the house as the run loads
it, sample its cameras with the run's generator or read them from a file, trace the frontal
layers) or reads a rendered store's view back, and keeps, per view, the three candidate boxes
with the frontal points they were built from; :func:`plot_candidates` draws them.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from ..camera_sampler import CameraSamplerConfig, SamplerReport, sample_cameras
from ..cameras import Camera, read_pbrs_cameras
from ..errors import MissingDependencyError, SceneforgeError, plural
from ..houses import HouseSource, LoadOptions, load
from ..layers import frontal_layers
from ..overhead import FrontalPoints, OverheadCamera, OverheadConfig, overhead_camera_and_points
from ..raytrace import HouseTracer
from ..store import open_store
from .inputs import house_path
from .plan import house_rng

if TYPE_CHECKING:
    import matplotlib.figure


@dataclass(frozen=True, eq=False)
class ViewExplanation:
    """How the overhead camera of one frontal view was chosen.

    index    : the view's index among the house's cameras
    camera   : the frontal camera
    overhead : the chosen overhead camera, with its three candidate boxes
    points   : the frontal points the boxes were built from (what :func:`plot_candidates` draws)
    """

    index: int
    camera: Camera
    overhead: OverheadCamera
    points: FrontalPoints


@dataclass(frozen=True, eq=False)
class OverheadExplanation:
    """The overhead cameras of a house's views, and how its cameras were found.

    views   : one explanation per view asked for
    cameras : every camera of the house (read or sampled)
    sampled : the sampler's report (None when the cameras were read from a file); it may
              have found fewer cameras than it was asked for
    """

    views: list[ViewExplanation]
    cameras: list[Camera]
    sampled: SamplerReport | None = None


def explain_overhead_cameras(
    house: str | Path,
    cameras: str | Path | int,
    *,
    options: LoadOptions | None = None,
    sampler: CameraSamplerConfig | None = None,
    seed: int = 0,
    config: OverheadConfig | None = None,
    view_index: int | None = None,
) -> OverheadExplanation:
    """Load ``house``, get its cameras (the PBRS camera file ``cameras``, or that many
    cameras sampled as ``sceneforge render`` samples them: from ``seed`` and the house id),
    trace each view's frontal layers and place its overhead camera; only view
    ``view_index`` when given.

    Raises :class:`SceneforgeError` for a house or camera file that cannot be read, a view
    index beyond the cameras, or a view the overhead camera cannot be placed for.
    """
    config, sampler = config or OverheadConfig(), sampler or CameraSamplerConfig()
    h = load(house, options)
    tracer = HouseTracer(h)
    report = None
    if isinstance(cameras, int):
        found, report = sample_cameras(h, cameras, house_rng(seed, h.id), sampler, tracer)
    else:
        found = read_pbrs_cameras(cameras, sampler.width, sampler.height)
    if view_index is not None and not 0 <= view_index < len(found):
        raise SceneforgeError(f"view {view_index}: {h.id} has {plural(len(found), 'view')}")
    views = []
    for i in range(len(found)) if view_index is None else [view_index]:
        layers = frontal_layers(h, found[i], tracer)
        overhead, points = overhead_camera_and_points(h, found[i], layers, config)
        views.append(ViewExplanation(i, found[i], overhead, points))
    return OverheadExplanation(views, found, report)


def explain_stored_view(store: str, index: int) -> ViewExplanation:
    """How the overhead camera of view ``index`` of the store at ``store`` was chosen: its
    house read as the store's run read it (the store's config and the house's recorded
    path and format), its stored camera, the store's overhead settings; so the overhead
    camera explained is the one the store holds (``overhead_params``).

    Raises :class:`SceneforgeError` for a view out of range or a failed view (it has no
    overhead camera).
    """
    s = open_store(store)
    if not -len(s) <= index < len(s):
        raise SceneforgeError(f"view {index}: {store} has {plural(len(s), 'view')}")
    view, config = s.view(index), s.config
    if not view["valid"]:
        raise SceneforgeError(f"view {index} of {store} failed when it was rendered (see its failure log): "
                              "it has no overhead camera")
    record = next(h for h in s.attrs["houses"] if h["id"] == str(view["house_id"]))
    house = load(HouseSource(record["id"], record["format"], house_path(record)), config.houses)
    camera = Camera(view["K"], view["cam_to_world"], config.width, config.height)
    layers = frontal_layers(house, camera, HouseTracer(house))
    overhead, points = overhead_camera_and_points(house, camera, layers, config.view.overhead)
    return ViewExplanation(index % len(s), camera, overhead, points)


def plot_candidates(points: FrontalPoints, camera: OverheadCamera) -> "matplotlib.figure.Figure":
    """Top view of a frontal view's points with the three candidate boxes and the chosen one.

    Needs matplotlib (``pip install sceneforge[plot]``); uses the Agg backend.
    """
    try:
        from matplotlib.figure import Figure
        from matplotlib.patches import Rectangle
    except ImportError as e:
        raise MissingDependencyError("matplotlib", "plotting", "pip install sceneforge[plot]") from e

    fig = Figure(figsize=(6, 6))
    ax = fig.add_subplot()
    ax.scatter(points.objects[:, 0], points.objects[:, 2], s=1, c="tab:blue", label="D1–D4")
    ax.scatter([0], [0], marker="^", c="k", label="camera")
    colours = ("tab:orange", "tab:green", "tab:purple")
    for cand, colour in zip(camera.candidates, colours):
        if cand.box is None:
            continue
        style = "-" if cand.weight > 0 else ":"
        ax.add_patch(Rectangle(cand.box.lo, *(cand.box.hi - cand.box.lo), fill=False,
                               ec=colour, ls=style, label=f"{cand.name} (w={cand.weight:g})"))
    b = camera.box
    ax.add_patch(Rectangle(b.lo, *(b.hi - b.lo), fill=False, ec="k", lw=2, label="overhead"))
    ax.set_xlabel("right (m)")
    ax.set_ylabel("forward (m)")
    ax.set_aspect("equal")
    ax.autoscale_view()
    ax.legend(loc="best", fontsize="small")
    return fig
