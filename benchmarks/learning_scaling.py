"""How the learning check's scores grow with the number of training houses.

    python benchmarks/learning_scaling.py HOUSES WORKDIR [--sizes 8 16 32 64] [--val 4] [--test 4]
        [--plot docs/learning_scaling.png]

HOUSES is a folder of houses (e.g. ``sceneforge toy-houses houses --count 72 --seed 50``).
Its houses, sorted by name and shuffled with ``--seed``, give the validation houses, then the
test houses, then the training houses; every point trains on the first N of the training
houses and is validated and tested on the same houses. Each point is the recipe of
``benchmarks/learning_check.sh`` (its config files, so the same epochs: a fixed number of
steps per view, and steps that grow with N) on a store of its own houses
(``WORKDIR/nN/``), with the operating point chosen on the validation houses. A killed run
starts again where it stopped: finished points are read back, the others resume.

Prints one line per point (seconds, D1-4 & overhead precision and recall at 5 cm, depth
abs-rel beside its baseline, seg mIoU, overhead L1) and writes ``WORKDIR/scaling.json`` and
the plot.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
RECIPE = HERE / "learning"


def sceneforge() -> str:
    found = shutil.which("sceneforge")
    return found or str(HERE.parent / ".venv" / "bin" / "sceneforge")


def run(*args: str) -> None:
    print("  $", " ".join(args), file=sys.stderr, flush=True)
    subprocess.run(args, check=True)


def point(houses: list[Path], val: list[str], test: list[str], n: int, work: Path) -> dict:
    """Render, train, predict and evaluate the recipe on ``n`` training houses."""
    done = work / "point.json"
    if done.exists():
        return json.loads(done.read_text())
    sf = sceneforge()
    folder = work / "houses"
    folder.mkdir(parents=True, exist_ok=True)
    for house in houses:
        link = folder / house.name
        if not link.exists():
            link.symlink_to(house.resolve(), target_is_directory=True)
    times = {}
    t0 = time.perf_counter()
    store = work / "gt.zarr"
    if not (work / "rendered").exists():
        run(sf, "render", str(folder), str(store), "--config", str(RECIPE / "render.json"), "--workers", "2")
        (work / "rendered").touch()
    times["render"] = time.perf_counter() - t0
    # the split the recipe's default config names (fractions 0.1 / 0.1, seed 0) holds these lists
    split = work / "gt.split.json"
    if not split.exists():
        train = sorted(h.name for h in houses if h.name not in val and h.name not in test)
        split.write_text(json.dumps({"version": 1, "val_fraction": 0.1, "test_fraction": 0.1, "seed": 0,
                                     "stores": [str(store.resolve())], "train": train, "val": sorted(val),
                                     "test": sorted(test)}, indent=1) + "\n")
    for stage in ("depth", "seg", "overhead"):
        t = time.perf_counter()
        runs = work / "runs" / stage
        more = ["--resume"] if (runs / "checkpoint.pt").exists() else []
        if stage == "overhead":
            more += ["--depth-run", str(work / "runs" / "depth"), "--seg-run", str(work / "runs" / "seg")]
        run(sf, "train", str(store), "--config", str(RECIPE / f"{stage}.json"), "--run", str(runs), *more)
        times[stage] = time.perf_counter() - t
    t = time.perf_counter()
    pred = work / "pred.zarr"
    run(sf, "predict", str(work / "runs" / "overhead"), str(store), str(pred), "--config",
        str(RECIPE / "predict.json"), "--overwrite")
    times["predict"] = time.perf_counter() - t
    t = time.perf_counter()
    report = work / "evaluation.json"
    run(sf, "evaluate", "predictions", str(pred), str(store), "--json", str(report), "--plot",
        str(work / "predictions.png"))
    times["evaluate"] = time.perf_counter() - t
    data = json.loads(report.read_text())
    variant = data["variants"]["D1-4 & overhead"]["objects"]
    learning = data["learning"]
    result = {"train_houses": n, "precision": variant["precision"], "recall": variant["recall"],
              "operating_point": data["operating_point"],
              "depth_absrel": learning["depth_absrel"], "seg_miou": learning["seg_miou"],
              "overhead_height_l1": learning["overhead_height_l1"],
              "seconds": {k: round(v, 1) for k, v in times.items()}}
    done.write_text(json.dumps(result, indent=1) + "\n")
    return result


def plot(results: list[dict], path: Path) -> None:
    from matplotlib.figure import Figure

    n = [r["train_houses"] for r in results]
    fig = Figure(figsize=(9, 3.6), layout="constrained")
    left, right = fig.subplots(1, 2)
    left.plot(n, [r["precision"] for r in results], "o-", label="precision")
    left.plot(n, [r["recall"] for r in results], "s-", label="recall")
    left.axhline(0.30, color="0.6", ls="--", lw=0.8, label="target 0.30")
    left.set_title("D1-4 & overhead at 5 cm, test houses")
    left.set_ylim(0, max(0.6, *(r["precision"] for r in results)))
    right.plot(n, [r["depth_absrel"]["model"] for r in results], "o-", label="model")
    right.plot(n, [r["depth_absrel"]["baseline"] for r in results], "o--", color="0.5", label="training mean")
    right.set_title("depth abs-rel of D1-D4 (lower is better)")
    for ax in (left, right):
        ax.set_xscale("log", base=2)
        ax.set_xticks(n, [str(x) for x in n])
        ax.set_xlabel("training houses (32 views each)")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize="small")
    fig.savefig(path, dpi=110)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("houses", type=Path)
    parser.add_argument("work", type=Path)
    parser.add_argument("--sizes", type=int, nargs="+", default=[8, 16, 32, 64])
    parser.add_argument("--val", type=int, default=4, help="validation houses")
    parser.add_argument("--test", type=int, default=4, help="test houses")
    parser.add_argument("--seed", type=int, default=0, help="the shuffle of the houses")
    parser.add_argument("--plot", type=Path, default=None, help="the plot [default: WORKDIR/scaling.png]")
    args = parser.parse_args()
    houses = sorted(p for p in args.houses.iterdir() if p.is_dir())
    houses = [houses[i] for i in np.random.default_rng(args.seed).permutation(len(houses))]
    need = args.val + args.test + max(args.sizes)
    if len(houses) < need:
        sys.exit(f"error: {args.houses} holds {len(houses)} houses; the sizes need {need}")
    val = [h.name for h in houses[:args.val]]
    test = [h.name for h in houses[args.val:args.val + args.test]]
    train = houses[args.val + args.test:]
    results = []
    for n in sorted(args.sizes):
        r = point(houses[:args.val + args.test] + train[:n], val, test, n, args.work / f"n{n}")
        results.append(r)
        point_op = r["operating_point"]
        print(f"{n:4d} training houses: P {r['precision']:.3f} R {r['recall']:.3f} "
              f"(at {point_op['min_object_probability']} / {point_op['min_overhead_object_probability']}), "
              f"depth abs-rel {r['depth_absrel']['model']:.3f} (baseline {r['depth_absrel']['baseline']:.3f}), "
              f"mIoU {r['seg_miou']['model']:.3f}, overhead L1 {r['overhead_height_l1']['model']:.3f}; "
              f"{sum(r['seconds'].values()):.0f} s", flush=True)
    (args.work / "scaling.json").write_text(json.dumps(results, indent=1) + "\n")
    plot(results, args.plot or args.work / "scaling.png")
    print(f"values: {args.work / 'scaling.json'}  plot: {args.plot or args.work / 'scaling.png'}")


if __name__ == "__main__":
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    main()
