"""Bytes per view of a store, by array: the old defaults against the new, and the codecs tried.

Renders a 320x240 toy store (the bundled toy houses, 4 views each) and a real-style one (the
breakfast room glTF, 4 views, where ``../shared/scenes/breakfast_room/`` is) with the old
defaults (``store.gt_mesh: all``, ``store.codec: blosc-zstd``: meshes kept, every array
byte-shuffled with Blosc's own blocks), with the new (no meshes, ``blosc-zstd-per-array``),
and with the new codecs and the meshes (``--gt-mesh all``). Prints the bytes per view of
every array (its shard files over the views), checks that every array of the new stores
has the values of the old store's (``array_digests``), then tries codecs, Blosc block
sizes and (on image arrays) the transpose codec on each large array, all zarr v3 core
codecs and all lossless, at the store's chunking (one view per chunk, 4 per shard; meshes
65,536 rows per chunk): bytes and write time per view (timings of a loaded machine: compare
the rows of one run only). ``<-`` marks what the new default writes.

    python benchmarks/bench_store_bytes.py [--scenes toy,breakfast_room] [--keep DIR]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
import warnings
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before numpy loads: BLAS threads fight Open3D's

import numpy as np  # noqa: E402
import zarr  # noqa: E402
from zarr.codecs import BloscCodec, TransposeCodec, ZstdCodec  # noqa: E402
from zarr.storage import MemoryStore  # noqa: E402

from sceneforge.config import load_config  # noqa: E402
from sceneforge.houses import BUNDLED_TOY  # noqa: E402
from sceneforge.pipeline import render_dataset  # noqa: E402
from sceneforge.store import array_digests, layout, open_store  # noqa: E402
from sceneforge.store.writer import array_compressor  # noqa: E402

BREAKFAST_ROOM = Path(__file__).resolve().parents[2] / "shared" / "scenes" / "breakfast_room" / "BreakfastRoom.gltf"
SCENES = {"toy": BUNDLED_TOY, "breakfast_room": str(BREAKFAST_ROOM)}
#: the old defaults: every view's meshes kept, every array byte-shuffled by Blosc's own blocks
BEFORE = {"store": {"gt_mesh": "all", "codec": "blosc-zstd"}}
#: the arrays the codecs are tried on (the rest are a few hundred bytes a view)
TRIED = ("depth", "overhead_depth", "overhead_height", "rgb", "category", "overhead_category", "instance",
         "mesh/objects/vertices", "mesh/objects/faces", "mesh/envelope/vertices", "mesh/envelope/faces",
         "mesh/envelope/instance")


def render(houses: str, out: Path, overrides: dict) -> Path:
    if not (out / "zarr.json").exists():
        render_dataset(houses, str(out), load_config(None, {"views_per_house": 4, **overrides}))
    return out


def bytes_by_array(store: Path) -> dict[str, int]:
    """The bytes of every array's chunk (shard) files, and of the rest (metadata, manifest)."""
    out: dict[str, int] = {}
    for path in store.rglob("*"):
        if not path.is_file():
            continue
        key = path.relative_to(store).as_posix()
        name = key.split("/c/")[0] if "/c/" in key else "metadata"
        out[name] = out.get(name, 0) + path.stat().st_size
    return out


def table(before: Path, after: Path, meshes: Path) -> int:
    """Print the bytes per view by array; return the new store's bytes per view."""
    n = len(open_store(str(after)))
    b, a, m = bytes_by_array(before), bytes_by_array(after), bytes_by_array(meshes)
    print(f"{'kB per view':<28}{'before':>10}{'after':>10}{'after/before':>14}{'--gt-mesh all':>15}")
    for name in [name for name in layout() if name in b] + ["metadata", "total"]:
        kb_b, kb_a, kb_m = ((sum(d.values()) if name == "total" else d.get(name, 0)) / n / 1e3 for d in (b, a, m))
        ratio = f"{kb_a / kb_b:.2f}" if kb_b and kb_a else "—"
        print(f"{name:<28}{kb_b:>10.1f}{kb_a:>10.1f}{ratio:>14}{kb_m:>15.1f}")
    return int(sum(a.values()) / n)


def digests_equal(before: Path, after: Path) -> None:
    """Print whether every array of ``after`` holds the values of the same array of ``before``."""
    b, a = array_digests(str(before)), array_digests(str(after))
    same = [k for k in a if b.get(k) == a[k]]
    only = sorted({k.rsplit("/", 1)[0] for k in set(b) - set(a)})
    print(f"array digests, {after.stem} against {before.stem}: {len(same)} of {len(a)} arrays equal"
          f"{'' if len(same) == len(a) else ' (DIFFERENT: ' + ', '.join(sorted(set(a) - set(same))) + ')'}"
          f"{'; not in ' + after.stem + ': ' + ', '.join(only) if only else ''}")
    if len(same) != len(a):
        raise SystemExit("the codecs changed array values")


def encoded(data: np.ndarray, chunks: tuple, shards: tuple, compressor, filters=()) -> tuple[float, float]:
    """(bytes, write seconds) of ``data`` as a sharded zarr array compressed by ``compressor``
    after ``filters``, after checking it reads back equal."""
    group = zarr.open_group(MemoryStore(), mode="w")
    array = group.create_array("a", shape=data.shape, dtype=data.dtype, chunks=chunks, shards=shards,
                               filters=filters, compressors=compressor, fill_value=0)
    t0 = time.perf_counter()
    array[...] = data
    seconds = time.perf_counter() - t0
    if not np.array_equal(array[...], data, equal_nan=data.dtype.kind == "f"):
        raise SystemExit(f"{compressor} is not lossless")
    files = [v for k, v in group.store._store_dict.items() if k.startswith("a/c")]
    return sum(len(f.to_bytes()) for f in files), seconds


def candidates(chunk_bytes: int, image_axes: int | None) -> dict[str, tuple]:
    """Label → (compressor, filters); ``image_axes``: the number of axes of an array that
    ends with an image's rows and columns (None: another array)."""
    out = {}
    for shuffle in ("noshuffle", "shuffle", "bitshuffle"):
        for blocks, size in (("Blosc's blocks", 0), ("block = chunk", chunk_bytes)):
            out[f"blosc zstd 3 {shuffle}, {blocks}"] = (
                BloscCodec(cname="zstd", clevel=3, shuffle=shuffle, blocksize=size), ())
    for shuffle in ("shuffle", "bitshuffle"):
        for cname in ("zstd", "lz4"):
            out[f"blosc {cname} 5 {shuffle}, block = chunk"] = (
                BloscCodec(cname=cname, clevel=5, shuffle=shuffle, blocksize=chunk_bytes), ())
    if image_axes is not None:  # images stored column by column (the transpose codec)
        order = (*range(image_axes - 2), image_axes - 1, image_axes - 2)
        out["transpose to (W, H), blosc zstd 3 shuffle, block = chunk"] = (
            BloscCodec(cname="zstd", clevel=3, shuffle="shuffle", blocksize=chunk_bytes),
            (TransposeCodec(order=order),))
    for level in (3, 9):
        out[f"zstd {level} (no Blosc)"] = (ZstdCodec(level=level), ())
    return out


def trials(before: Path, after: Path) -> None:
    config = open_store(str(after)).config
    n = len(open_store(str(after)))
    specs = layout()
    for name in TRIED:
        source = after if name in open_store(str(after)).names else before
        group = zarr.open_group(str(source), mode="r")
        if name not in group:
            continue
        stored = group[name]
        data = np.asarray(stored[...])
        chunks, shards = stored.chunks, stored.shards
        chunk_bytes = int(np.prod(chunks)) * data.dtype.itemsize
        chosen = array_compressor(config, specs[name], chunks)
        print(f"  {name} {data.shape} {data.dtype}, raw {data.nbytes / n / 1e3:.1f} kB/view")
        image = specs[name].dims[-2:] in (("H", "W"), ("Ho", "Wo"))
        for label, (compressor, filters) in candidates(chunk_bytes, data.ndim if image else None).items():
            size, seconds = encoded(data, chunks, shards, compressor, filters)
            mark = "  <-" if compressor.to_dict() == chosen.to_dict() and not filters else ""
            print(f"    {label:<58}{size / n / 1e3:>9.1f} kB/view {1e3 * seconds / n:>7.1f} ms/view{mark}")


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", default=",".join(SCENES), help="comma-separated: toy, breakfast_room")
    parser.add_argument("--keep", type=Path, default=None, help="render the stores here and keep them (reused)")
    args = parser.parse_args()
    warnings.filterwarnings("ignore", module="zarr")  # the manifest is not a zarr node
    with tempfile.TemporaryDirectory() as tmp:
        root = args.keep or Path(tmp)
        for scene in args.scenes.split(","):
            houses = SCENES[scene]
            if scene == "breakfast_room" and not BREAKFAST_ROOM.exists():
                print(f"== {scene}: skipped, {BREAKFAST_ROOM} is absent (the shared scenes are not checked out)")
                continue
            before = render(houses, root / f"{scene}_before.zarr", BEFORE)
            after = render(houses, root / f"{scene}_after.zarr", {})
            meshes = render(houses, root / f"{scene}_meshes.zarr", {"store": {"gt_mesh": "all"}})
            n = len(open_store(str(after)))
            print(f"== {scene}: {n} views, 320x240, overhead 300x300, RGB raster")
            total = table(before, after, meshes)
            digests_equal(before, after)
            digests_equal(before, meshes)
            if scene == "toy":
                print(f"default toy store: {total / 1e6:.3f} MB per view (target <= 0.5 MB: "
                      f"{'met' if total <= 0.5e6 else 'NOT met'})")
            print("codecs tried (zarr v3 core codecs, lossless; bytes and write time per view):")
            trials(before, after)


if __name__ == "__main__":
    main()
