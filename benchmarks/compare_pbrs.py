"""Region-by-region comparison of a store's RGB with PBRS images of the same houses and cameras
(issue 24's "Must show"), and the wall noise of the store's frames.

Render the SUNCG houses with their PBRS cameras first (``--cameras``: PBRS's
``<house>/room_camera.txt``, line k = camera k), once per mode::

    sceneforge render SUNCG/ raster.zarr --cameras CAMS
    sceneforge render SUNCG/ pt.zarr --cameras CAMS --rgb pathtraced

then compare each with PBRS's images (``<pbrs>/<house>/<camera:06d>_mlt.png``, the file names
of the released PBRS renders; ``--pattern`` for others)::

    python benchmarks/compare_pbrs.py raster.zarr PBRS_DIR
    python benchmarks/compare_pbrs.py pt.zarr PBRS_DIR

Regions of a view: each object instance on the pixels where it is seen first (D1's instance
layer), and each envelope class on the pixels where no object is in front (D1 empty: D5's
class); regions under ``--min-pixels`` are left out. Per region, in both images: colour is the
chromaticity (r, g) = (R, G) / (R + G + B) of the mean linear RGB (sRGB decoded), brightness
the mean luminance over the frame's median luminance (the store's seen pixels). Printed: the
share of regions whose chromaticities are within ``--chroma`` (0.05, the largest of |Δr|, |Δg|)
and whose relative brightnesses are within ``--stops`` (1) of each other, and the median wall
noise of both (median |Y − 5×5 median(Y)| over wall pixels 3 px inside their region, Y on
0–255). A view whose PBRS image is missing is counted and skipped.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from PIL import Image
from scipy import ndimage

from sceneforge.colour import srgb_to_linear
from sceneforge.conventions import NYU40_IDS
from sceneforge.store import open_store

LUMINANCE = np.array([0.2126, 0.7152, 0.0722])


def regions(instance: np.ndarray, category: np.ndarray, min_pixels: int) -> list[np.ndarray]:
    """(H, W) bool masks: every D1 instance where seen first, every D5 class where no object is.

    instance : (2, H, W) int32  the store's instance layers (-1: none)
    category : (3, H, W) uint8  the store's class layers (layers 1, 3, 5)
    """
    out = []
    first = instance[0]
    for i in np.unique(first[first >= 0]):
        out.append(first == i)
    empty = first < 0
    for c in np.unique(category[2][empty]):
        if c:
            out.append(empty & (category[2] == c))
    return [m for m in out if m.sum() >= min_pixels]


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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("store")
    parser.add_argument("pbrs", type=Path)
    parser.add_argument("--pattern", default="{house}/{camera:06d}_mlt.png")
    parser.add_argument("--chroma", type=float, default=0.05)
    parser.add_argument("--stops", type=float, default=1.0)
    parser.add_argument("--min-pixels", type=int, default=50)
    args = parser.parse_args()

    store = open_store(args.store)
    ours_all, theirs_all, noise_ours, noise_theirs, missing = [], [], [], [], 0
    for k in range(len(store)):
        view = store.view(k)
        if not bool(view["valid"]):
            continue
        path = args.pbrs / args.pattern.format(house=str(view["house_id"]), camera=int(view["camera_id"]))
        if not path.is_file():
            missing += 1
            continue
        theirs = np.asarray(Image.open(path).convert("RGB"))
        ours = np.asarray(view["rgb"])
        if theirs.shape != ours.shape:
            theirs = np.asarray(Image.fromarray(theirs).resize(ours.shape[1::-1], Image.BILINEAR))
        seen = np.isfinite(np.asarray(view["depth"])[4]) | np.isfinite(np.asarray(view["depth"])[0])
        masks = regions(np.asarray(view["instance"]), np.asarray(view["category"]), args.min_pixels)
        ours_all.append(region_stats(ours, masks, seen))
        theirs_all.append(region_stats(theirs, masks, seen))
        wall = (np.asarray(view["instance"])[0] < 0) & (np.asarray(view["category"])[2] == NYU40_IDS["wall"])
        for image, into in ((ours, noise_ours), (theirs, noise_theirs)):
            noise = wall_noise(image, wall)
            if noise is not None:
                into.append(noise)
    if not ours_all:
        raise SystemExit(f"no view of {args.store} has a PBRS image under {args.pbrs} ({missing} missing)")
    ours, theirs = np.concatenate(ours_all), np.concatenate(theirs_all)
    chroma_ok = np.abs(ours[:, :2] - theirs[:, :2]).max(axis=1) <= args.chroma
    stops = np.abs(np.log2(np.maximum(ours[:, 2], 1e-9) / np.maximum(theirs[:, 2], 1e-9)))
    print(f"{len(ours_all)} views, {len(ours)} regions ({missing} views without a PBRS image)")
    print(f"chromaticity within {args.chroma}: {chroma_ok.mean():.1%} of regions")
    print(f"relative brightness within {args.stops:g} stop: {(stops <= args.stops).mean():.1%} of regions "
          f"(median {np.median(stops):.2f} stops off)")
    if noise_ours:
        print(f"wall noise (median |Y - 5x5 median(Y)|, 0-255): {np.median(noise_ours):.2f} here, "
              f"{np.median(noise_theirs):.2f} PBRS")


if __name__ == "__main__":
    main()
