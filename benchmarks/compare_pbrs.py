"""Region-by-region comparison of a store's RGB with PBRS images of the same houses and cameras
(issues 24 and 40), and the wall noise of the store's frames.

Render the SUNCG houses with their PBRS cameras first (``--cameras``: PBRS's
``<house>/room_camera.txt``, line k = camera k), once per mode::

    sceneforge render SUNCG/ raster.zarr --cameras CAMS
    sceneforge render SUNCG/ pt.zarr --cameras CAMS --rgb pathtraced

then compare each with PBRS's images::

    python benchmarks/compare_pbrs.py raster.zarr PBRS_DIR
    python benchmarks/compare_pbrs.py pt.zarr PBRS_DIR --with raster.zarr --figure side.png

PBRS images are found by ``--pattern`` (``{house}``, ``{camera}`` fields); without it, by
the first of the known layouts that has the view's file: per-house folders as PBRS
released them (``<house>/<camera:06d>_mlt.png``), or one flat folder of one house
(``<camera:06d>_mlt.png``, as ``shared/scenes/suncg_pbrs/pbrs/`` ships; a store of several
houses must then name its pattern, since a flat folder cannot tell them apart).

Regions of a view: each object instance on the pixels where it is seen first (D1's instance
layer), and each envelope class on the pixels where no object is in front (D1 empty: D5's
class); regions under ``--min-pixels`` are left out. Per region, in both images: colour is the
chromaticity (r, g) = (R, G) / (R + G + B) of the mean linear RGB (sRGB decoded), brightness
the mean luminance over the frame's median luminance (the store's seen pixels). Printed, per
region kind (objects, then each envelope class) and for all: the share of regions whose
chromaticities are within ``--chroma`` (0.05, the largest of |Δr|, |Δg|) and whose relative
brightnesses are within ``--stops`` (1) of each other, with the medians; then the median wall
noise of both (median |Y − 5×5 median(Y)| over wall pixels 3 px inside their region, Y on
0–255) and, by the same measure, the texture detail of their floors (the grain of a
laminate: what the denoiser must keep), and the share of the window regions' pixels that are
white (255, 255, 255) and near white (every channel at least 245) in both, per view: where
the outdoors is burnt out; and the window regions' median luminance over the frame's (the
pixels that see something), linear, in both: for the store, as shown (after its tone
curve) and, where its curve is ``soft``, before the curve (the curve undone per channel; a
window at byte 255 counts as the least value that byte holds, so the ratio is then a lower
bound). ``--regions`` lists every region (its instance's name and label from the house),
worst brightness first. ``--figure PNG`` writes the views side by side: the store's frame,
each ``--with`` store's, then PBRS's, one row per view. A view whose PBRS image is missing is
counted and skipped.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw
from scipy import ndimage

from sceneforge.colour import srgb_to_linear
from sceneforge.conventions import NYU40_IDS
from sceneforge.store import open_store

LUMINANCE = np.array([0.2126, 0.7152, 0.0722])
#: Layouts of PBRS images tried in order when no ``--pattern`` is given (module docs).
PATTERNS = ("{house}/{camera:06d}_mlt.png", "{camera:06d}_mlt.png")
NYU40_NAMES = {v: k for k, v in NYU40_IDS.items()}


def regions(instance: np.ndarray, category: np.ndarray, min_pixels: int) -> list[np.ndarray]:
    """(H, W) bool masks: every D1 instance where seen first, every D5 class where no object is.

    instance : (2, H, W) int32  the store's instance layers (-1: none)
    category : (3, H, W) uint8  the store's class layers (layers 1, 3, 5)
    """
    return [m for m, _ in labelled_regions(instance, category, min_pixels)]


def labelled_regions(instance: np.ndarray, category: np.ndarray,
                     min_pixels: int) -> list[tuple[np.ndarray, tuple[str, int]]]:
    """:func:`regions` with each one's key: ``("object", instance index)`` or
    ``("envelope", NYU40 class)``."""
    out = []
    first = instance[0]
    for i in np.unique(first[first >= 0]):
        out.append((first == i, ("object", int(i))))
    empty = first < 0
    for c in np.unique(category[2][empty]):
        if c:
            out.append((empty & (category[2] == c), ("envelope", int(c))))
    return [(m, key) for m, key in out if m.sum() >= min_pixels]


def region_stats(rgb: np.ndarray, masks: list[np.ndarray], seen: np.ndarray) -> np.ndarray:
    """(n, 3) float64 per region: chromaticity r, g and brightness relative to the frame median."""
    linear = srgb_to_linear(rgb.astype(np.float64) / 255.0)
    y = linear @ LUMINANCE
    median = max(float(np.median(y[seen])), 1e-9)
    stats = []
    for m in masks:
        mean = linear[m].mean(axis=0)
        total = max(mean.sum(), 1e-9)
        stats.append((mean[0] / total, mean[1] / total, float(y[m].mean()) / median))
    return np.array(stats).reshape(-1, 3)


def wall_noise(rgb: np.ndarray, wall: np.ndarray) -> float | None:
    """median |Y − 5×5 median(Y)| (0–255) over ``wall`` eroded by 3 px; None when empty."""
    region = ndimage.binary_erosion(wall, iterations=3)
    if not region.any():
        return None
    y = rgb.astype(np.float64) @ LUMINANCE
    return float(np.median(np.abs(y - ndimage.median_filter(y, size=5))[region]))


def window_ratio(rgb: np.ndarray, window: np.ndarray, seen: np.ndarray, tone: str | None = None) -> float | None:
    """Median linear luminance of the ``window`` pixels over that of the ``seen`` ones. With
    ``tone`` "soft" the curve is undone per channel first (bytes of 255 as the least value
    they hold: a lower bound); "clip" or None: as shown; another curve: None."""
    display = srgb_to_linear(rgb.astype(np.float64) / 255.0)
    if tone == "soft":
        from sceneforge.render.tonemap import SOFT_KNEE as k

        top = float(srgb_to_linear(np.float64(254.5 / 255.0)))
        w = np.minimum(display, top) - k
        display = np.where(w > 0, k + w / (1.0 - w / (1.0 - k)), display)
    elif tone not in (None, "clip"):
        return None
    y = display @ LUMINANCE
    return float(np.median(y[window])) / max(float(np.median(y[seen])), 1e-9)


def pbrs_path(root: Path, pattern: str | None, house: str, camera: int, houses: int) -> Path | None:
    """The PBRS image of a view: ``pattern``'s file, else the first of :data:`PATTERNS` that
    exists (the flat one only for a store of one house); None when there is none."""
    if pattern is not None:
        path = root / pattern.format(house=house, camera=camera)
        return path if path.is_file() else None
    for p in PATTERNS:
        if "{house}" not in p and houses > 1:
            continue
        path = root / p.format(house=house, camera=camera)
        if path.is_file():
            return path
    return None


@dataclass
class Comparison:
    """What :func:`compare` measured: one row per region, the wall noise of each frame."""

    #: per region: view, camera, kind ("objects" or an envelope class name), instance (-1 for
    #: an envelope region), pixels, chroma difference, signed stops (ours / PBRS)
    rows: list[dict] = field(default_factory=list)
    noise_ours: list[float] = field(default_factory=list)
    noise_theirs: list[float] = field(default_factory=list)
    #: the same measure over the floors (texture detail)
    detail_ours: list[float] = field(default_factory=list)
    detail_theirs: list[float] = field(default_factory=list)
    #: per view with a window region: (camera, share of its pixels white (255, 255, 255)
    #: here, in PBRS, share near white (every channel >= 245) here, in PBRS)
    window_white: list[tuple[int, float, float, float, float]] = field(default_factory=list)
    #: per view with a window region: (camera, median window luminance over the frame's here
    #: as shown, here before the tone curve (None: curve not invertible), in PBRS)
    window_ratio: list[tuple[int, float, float | None, float]] = field(default_factory=list)
    views: int = 0
    missing: int = 0
    #: (house, camera, ours (H, W, 3) uint8, PBRS resized to ours) per compared view
    frames: list[tuple[str, int, np.ndarray, np.ndarray]] = field(default_factory=list)

    def table(self, chroma: float, stops: float) -> list[dict]:
        """Per kind (objects, each envelope class by name, then all): regions, share within
        ``chroma`` / ``stops``, their medians."""
        kinds = ["objects"] + sorted({r["kind"] for r in self.rows} - {"objects"}) + ["all"]
        out = []
        for kind in kinds:
            rows = [r for r in self.rows if kind in ("all", r["kind"])]
            if not rows:
                continue
            dc = np.array([r["chroma"] for r in rows])
            ds = np.abs([r["stops"] for r in rows])
            out.append({"kind": kind, "regions": len(rows),
                        "chroma_within": float((dc <= chroma).mean()), "chroma_median": float(np.median(dc)),
                        "stops_within": float((ds <= stops).mean()), "stops_median": float(np.median(ds))})
        return out


def compare(store_path: str, pbrs: Path, pattern: str | None = None, min_pixels: int = 50,
            cameras: set[int] | None = None) -> Comparison:
    """Compare every valid view of the store (of ``cameras`` only, if given) with its PBRS image."""
    store = open_store(store_path)
    tone = store.group.attrs.get("config", {}).get("rgb", {}).get("lighting", {}).get("tone")
    houses = len({str(store.view(k)["house_id"]) for k in range(len(store))})
    out = Comparison()
    for k in range(len(store)):
        view = store.view(k)
        house, camera = str(view["house_id"]), int(view["camera_id"])
        if not bool(view["valid"]) or (cameras is not None and camera not in cameras):
            continue
        path = pbrs_path(pbrs, pattern, house, camera, houses)
        if path is None:
            out.missing += 1
            continue
        ours = np.asarray(view["rgb"])
        theirs = np.asarray(Image.open(path).convert("RGB"))
        if theirs.shape != ours.shape:
            theirs = np.asarray(Image.fromarray(theirs).resize(ours.shape[1::-1], Image.BILINEAR))
        depth, instance, category = (np.asarray(view[n]) for n in ("depth", "instance", "category"))
        seen = np.isfinite(depth[4]) | np.isfinite(depth[0])
        labelled = labelled_regions(instance, category, min_pixels)
        masks = [m for m, _ in labelled]
        a, b = region_stats(ours, masks, seen), region_stats(theirs, masks, seen)
        for (m, (kind, key)), sa, sb in zip(labelled, a, b, strict=True):
            out.rows.append({
                "view": k, "house": house, "camera": camera, "pixels": int(m.sum()),
                "kind": "objects" if kind == "object" else NYU40_NAMES.get(key, str(key)),
                "instance": key if kind == "object" else -1,
                "chroma": float(np.abs(sa[:2] - sb[:2]).max()),
                "stops": float(np.log2(max(sa[2], 1e-9) / max(sb[2], 1e-9))),
                "ours": [float(x) for x in sa], "pbrs": [float(x) for x in sb],
            })
        wall = (instance[0] < 0) & (category[2] == NYU40_IDS["wall"])
        floor = (instance[0] < 0) & (category[2] == NYU40_IDS["floor"])
        window = (instance[0] < 0) & (category[2] == NYU40_IDS["window"])
        if window.any():
            out.window_white.append((camera, *(float((image[window] >= level).all(-1).mean())
                                               for level in (255, 245) for image in (ours, theirs))))
            out.window_ratio.append((camera, window_ratio(ours, window, seen), window_ratio(ours, window, seen, tone),
                                     window_ratio(theirs, window, seen)))
        for image, noise_into, detail_into in ((ours, out.noise_ours, out.detail_ours),
                                               (theirs, out.noise_theirs, out.detail_theirs)):
            noise, detail = wall_noise(image, wall), wall_noise(image, floor)
            if noise is not None:
                noise_into.append(noise)
            if detail is not None:
                detail_into.append(detail)
        out.views += 1
        out.frames.append((house, camera, ours, theirs))
    return out


def side_by_side(columns: list[list[np.ndarray]], titles: list[str], row_titles: list[str]) -> Image.Image:
    """One row per view: each column's frame of it, left to right, titled above and at the left."""
    h, w = columns[0][0].shape[:2]
    pad, head = 4, 14
    canvas = Image.new("RGB", (len(columns) * (w + pad) + pad, len(row_titles) * (h + head + pad) + pad),
                       (255, 255, 255))
    draw = ImageDraw.Draw(canvas)
    for r, row_title in enumerate(row_titles):
        y = pad + r * (h + head + pad)
        for c, (frames, title) in enumerate(zip(columns, titles, strict=True)):
            x = pad + c * (w + pad)
            frame = frames[r]
            if frame.shape[:2] != (h, w):
                frame = np.asarray(Image.fromarray(frame).resize((w, h), Image.BILINEAR))
            canvas.paste(Image.fromarray(frame), (x, y + head))
            draw.text((x + 2, y + 1), f"{row_title}  {title}" if c == 0 else title, fill=(0, 0, 0))
    return canvas


def instance_names(store_path: str, house: str) -> list[tuple[str, str]]:
    """(name, label) of each instance of a house of the store, read as the store read it."""
    from sceneforge.houses import LoadOptions, load

    attrs = open_store(store_path).group.attrs
    record = next(h for h in attrs["houses"] if h["id"] == house)
    options = LoadOptions(**{k: v for k, v in attrs["config"]["houses"].items()
                             if k in LoadOptions.__dataclass_fields__})
    loaded = load(record["path"], options)
    return [(i.name, i.label) for i in loaded.instances]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("store")
    parser.add_argument("pbrs", type=Path)
    parser.add_argument("--pattern", default=None,
                        help="PBRS file under PBRS ({house}, {camera}); default: " + " or ".join(PATTERNS))
    parser.add_argument("--chroma", type=float, default=0.05)
    parser.add_argument("--stops", type=float, default=1.0)
    parser.add_argument("--min-pixels", type=int, default=50)
    parser.add_argument("--cameras", default=None, help="compare these cameras only: 0,1,2,3")
    parser.add_argument("--regions", action="store_true", help="list every region, worst brightness first")
    parser.add_argument("--figure", type=Path, default=None, help="write the side-by-side PNG here")
    parser.add_argument("--with", dest="also", action="append", default=[], metavar="STORE",
                        help="another store's frames beside the first in the figure (repeatable)")
    parser.add_argument("--json", type=Path, default=None, help="write the table and the rows as JSON here")
    args = parser.parse_args()

    cameras = {int(c) for c in args.cameras.split(",")} if args.cameras else None
    result = compare(args.store, args.pbrs, args.pattern, args.min_pixels, cameras)
    if not result.rows:
        raise SystemExit(f"no view of {args.store} has a PBRS image under {args.pbrs} "
                         f"({result.missing} missing)")
    print(f"{result.views} views, {len(result.rows)} regions ({result.missing} views without a PBRS image)")
    table = result.table(args.chroma, args.stops)
    print(f"{'kind':<12} {'regions':>7}  {'chroma<=' + format(args.chroma, 'g'):>12} {'median':>7}  "
          f"{'<=' + format(args.stops, 'g') + ' stop':>9} {'median':>7}")
    for t in table:
        print(f"{t['kind']:<12} {t['regions']:>7}  {t['chroma_within']:>12.1%} {t['chroma_median']:>7.3f}  "
              f"{t['stops_within']:>9.1%} {t['stops_median']:>7.2f}")
    if result.noise_ours:
        print(f"wall noise (median |Y - 5x5 median(Y)|, 0-255): {np.median(result.noise_ours):.2f} here, "
              f"{np.median(result.noise_theirs):.2f} PBRS")
    if result.detail_ours:
        print(f"floor texture detail (the same measure): {np.median(result.detail_ours):.2f} here, "
              f"{np.median(result.detail_theirs):.2f} PBRS")
    for name, k in (("white (255, 255, 255)", 1), ("near white (all >= 245)", 3)):
        if result.window_white:
            per = ", ".join(f"{w[0]}: {w[k]:.0%} / {w[k + 1]:.0%}" for w in result.window_white)
            print(f"window pixels {name}, here / PBRS: {np.mean([w[k] for w in result.window_white]):.1%} / "
                  f"{np.mean([w[k + 1] for w in result.window_white]):.1%} (per camera {per})")
    if result.window_ratio:
        r = np.array([[w[1], np.nan if w[2] is None else w[2], w[3]] for w in result.window_ratio])
        per = ", ".join(f"{w[0]}: {w[1]:.1f} / {'-' if w[2] is None else format(w[2], '.1f')} / {w[3]:.1f}"
                        for w in result.window_ratio)
        print(f"window / frame median luminance, here as shown / here before the curve / PBRS: "
              f"{np.median(r[:, 0]):.1f} / {np.nanmedian(r[:, 1]) if np.isfinite(r[:, 1]).any() else float('nan'):.1f}"
              f" / {np.median(r[:, 2]):.1f} (median of the views; per camera {per})")
    if args.regions:
        names: dict[str, list] = {}
        print(f"{'camera':>6} {'kind':<10} {'pixels':>6} {'dchroma':>7} {'stops':>6}  instance")
        for r in sorted(result.rows, key=lambda r: -abs(r["stops"])):
            label = ""
            if r["instance"] >= 0:
                if r["house"] not in names:
                    names[r["house"]] = instance_names(args.store, r["house"])
                name, lab = names[r["house"]][r["instance"]]
                label = f"{r['instance']} {name} ({lab})"
            print(f"{r['camera']:>6} {r['kind']:<10} {r['pixels']:>6} {r['chroma']:>7.3f} {r['stops']:>+6.2f}  {label}")
    if args.json:
        args.json.write_text(json.dumps({"table": table, "rows": result.rows,
                                         "noise": [result.noise_ours, result.noise_theirs],
                                         "floor_detail": [result.detail_ours, result.detail_theirs],
                                         "window_white": result.window_white,
                                         "window_ratio": result.window_ratio}, indent=1))
    if args.figure:
        columns = [[f[2] for f in result.frames]]
        for other in args.also:
            store = open_store(other)
            by_view = {(str(store.view(k)["house_id"]), int(store.view(k)["camera_id"])): k for k in range(len(store))}
            columns.append([np.asarray(store.view(by_view[(h, c)])["rgb"]) for h, c, _, _ in result.frames])
        columns.append([f[3] for f in result.frames])
        titles = [Path(args.store).stem, *(Path(o).stem for o in args.also), "PBRS"]
        side_by_side(columns, titles, [f"camera {c}" for _, c, _, _ in result.frames]).save(args.figure)
        print(f"wrote {args.figure}")


if __name__ == "__main__":
    main()
