"""Data safety as a user meets it: every command pointed at the wrong place, every store
damaged, each run as ``sceneforge ...`` in a child process.

Makes a tiny world in a temporary folder (the bundled toy houses rendered at 64x48 with RGB,
a depth run of 2 steps, its prediction store, a copy of the houses, photos, a folder of
someone's files, a zarr store sceneforge did not write), then runs every case: an output
that is an input, an output inside a store, a store of the other kind, ``--overwrite`` on
what the command did not make, readers of a store with a truncated, zeroed or deleted shard,
``render`` repairing it. Prints one row per case: the exit code, the lines printed, whether a
traceback appeared, whether the inputs' bytes are unchanged (every file hashed before and
after), and the first line printed; then the totals and whether the repaired stores hold the
bytes of a clean render (``array_digests`` and every shard file).

    python benchmarks/data_safety.py [--keep DIR]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

CLI = "from sceneforge.cli.main import main; main()"
#: a progress bar's last state, left on the terminal (not a message)
PROGRESS = re.compile(r"━|\d+/\d+ .*ETA")


def digest(*paths: Path) -> str:
    """One SHA-256 over every file under ``paths`` (names and bytes); missing paths count."""
    h = hashlib.sha256()
    for root in map(Path, paths):
        files = [root] if root.is_file() else sorted(p for p in root.rglob("*") if p.is_file())
        h.update(f"{root}:{root.exists()}".encode())
        for p in files:
            h.update(str(p.relative_to(root.parent)).encode())
            h.update(p.read_bytes())
    return h.hexdigest()


def sceneforge(*args, cwd: Path) -> tuple[int, list[str]]:
    res = subprocess.run([sys.executable, "-c", CLI, *map(str, args)], capture_output=True, text=True, cwd=cwd)
    lines = [line for line in (res.stdout + res.stderr).splitlines() if line.strip() and not PROGRESS.search(line)]
    return res.returncode, lines


def check(args, cwd: Path, inputs) -> dict:
    before = digest(*inputs)
    code, lines = sceneforge(*args, cwd=cwd)
    return {"code": code, "lines": len(lines), "traceback": any("Traceback" in line for line in lines),
            "unchanged": digest(*inputs) == before, "first": lines[0] if lines else ""}


def setup(root: Path) -> dict[str, Path]:
    """The tiny world every case runs in."""
    from PIL import Image

    w = {name: root / name for name in ("gt.zarr", "other.zarr", "pred.zarr", "houses", "photos", "notes",
                                        "plain.zarr", "run", "clean.zarr")}
    sceneforge("render", "bundled:toy", w["gt.zarr"], "--views-per-house", 2, "--resolution", "64x48",
               "--overhead-resolution", 32, cwd=root)
    shutil.copytree(w["gt.zarr"], w["clean.zarr"])
    shutil.copytree(w["gt.zarr"], w["other.zarr"])
    code, lines = sceneforge("train", w["gt.zarr"], "--stage", "depth", "--run", w["run"], "--max-steps", 2,
                             "--batch-size", 2, "--width", 0.125, "--val-fraction", 0, "--test-fraction", 0.34,
                             "--device", "cpu", "--no-tensorboard", "--workers", 0, cwd=root)
    assert code == 0, lines
    # the test split: one house of three, so the prediction store has views it did not predict
    code, lines = sceneforge("predict", w["run"], w["gt.zarr"], w["pred.zarr"], "--device", "cpu", "--workers", 0,
                             cwd=root)
    assert code == 0, lines
    from sceneforge.houses import bundled_toy_dir

    shutil.copytree(bundled_toy_dir(), w["houses"])
    w["photos"].mkdir()
    Image.fromarray(_noise()).save(w["photos"] / "a.png")
    w["notes"].mkdir()
    (w["notes"] / "thesis.tex").write_text("months of work\n")
    import zarr

    zarr.open_group(str(w["plain.zarr"]), mode="w").attrs["someone"] = "else"
    return w


def _noise():
    import numpy as np

    return np.random.default_rng(0).integers(0, 255, (48, 64, 3), dtype=np.uint8)


def cases(w: dict[str, Path]) -> list[tuple[str, list, list[Path]]]:
    """(case, arguments, inputs that must stay as they are)."""
    gt, pred, run = w["gt.zarr"], w["pred.zarr"], w["run"]
    every = [gt, pred, w["other.zarr"], w["houses"], w["photos"], w["notes"], w["plain.zarr"], run]
    return [
        ("predict: OUT is its input store, --overwrite", ["predict", run, gt, gt, "--overwrite"], every),
        ("predict: OUT holds a dataset store, --overwrite", ["predict", run, gt, w["other.zarr"], "--overwrite"], every),
        ("predict: OUT is the run folder", ["predict", run, gt, run, "--overwrite"], every),
        ("predict: OUT holds someone's files, --overwrite", ["predict", run, gt, w["notes"], "--overwrite"], every),
        ("render: OUT holds a prediction store, --overwrite", ["render", "bundled:toy", pred, "--overwrite"], every),
        ("render: OUT is a zarr store not ours, --overwrite", ["render", "bundled:toy", w["plain.zarr"], "--overwrite"],
         every),
        ("render: OUT holds someone's files, --overwrite", ["render", "bundled:toy", w["notes"], "--overwrite"], every),
        ("render: OUT is its houses folder", ["render", w["houses"], w["houses"], "--overwrite"], every),
        ("render: OUT inside its houses folder", ["render", w["houses"], w["houses"] / "out.zarr"], every),
        ("render: OUT inside a store", ["render", "bundled:toy", gt / "inner.zarr"], every),
        ("export: OUT_DIR is its store", ["export", gt, gt], every),
        ("export: OUT_DIR inside its store", ["export", gt, gt / "exr"], every),
        ("export: OUT_DIR holds someone's files", ["export", gt, w["notes"]], every),
        ("export: someone's files, --overwrite", ["export", gt, w["notes"], "--overwrite"], every),
        ("reconstruct: --out is its photo folder", ["reconstruct", run, w["photos"], "--out", w["photos"]], every),
        ("reconstruct: --out inside a store", ["reconstruct", run, w["photos"], "--out", gt / "r"], every),
        ("train: the run folder is its store", ["train", gt, "--stage", "depth", "--run", gt], every),
        ("train: the run folder holds someone's files", ["train", gt, "--stage", "depth", "--run", w["notes"]], every),
        ("toy-houses: OUT inside a store", ["toy-houses", gt / "houses"], every),
        ("evaluate: --plot inside a store", ["evaluate", "coverage", gt, "--plot", gt / "c.png"], every),
        ("show: -o inside a store", ["show", gt, "--view", 0, "-o", gt / "p.png"], every),
        ("show --truth: a view never predicted", ["show", pred, "--view", _unpredicted(pred), "--truth", gt, "-o",
                                                  pred.parent / "p.png"], every),
        ("validate: a prediction store", ["validate", pred], every),
    ]


def _unpredicted(pred: Path) -> int:
    import zarr

    predicted = set(zarr.open_group(str(pred), mode="r").attrs["prediction"]["views"])
    return min(set(range(6)) - predicted)


DAMAGE = {
    "truncated": lambda p: p.write_bytes(p.read_bytes()[: len(p.read_bytes()) // 2]),
    "zeroed": lambda p: p.write_bytes(bytes(len(p.read_bytes()))),
    "deleted": lambda p: p.unlink(),
}


def damaged_cases(w: dict[str, Path], root: Path) -> list[tuple[str, list, list[Path], Path]]:
    """Readers on a store with one damaged depth shard (views 4-5), per kind of damage."""
    out = []
    for how, hurt in DAMAGE.items():
        store = root / f"{how}.zarr"
        shutil.copytree(w["clean.zarr"], store)
        hurt(store / "depth" / "c" / "1" / "0" / "0" / "0")
        rows = [("show", ["show", store, "--view", 5, "-o", root / f"{how}.png"]),
                ("export", ["export", store, root / f"{how}_exr"]),
                ("evaluate coverage", ["evaluate", "coverage", store, "--plot", root / f"{how}_c.png"]),
                ("train", ["train", store, "--stage", "depth", "--run", root / f"{how}_run", "--max-steps", 4,
                           "--batch-size", 6, "--width", 0.125, "--val-fraction", 0, "--test-fraction", 0,
                           "--device", "cpu", "--no-tensorboard", "--split-file", root / f"{how}.split.json"]),
                ("validate", ["validate", store]),
                ("render --repair", ["render", "bundled:toy", store, "--repair"])]
        out += [(f"{how} shard: {name}", args, [w["gt.zarr"], w["houses"]], store) for name, args in rows]
    return out


def interrupted_training(w: dict[str, Path], root: Path) -> list[tuple[str, dict]]:
    """Ctrl-C (SIGINT to the process group, as a terminal sends it) during training, once
    a step was taken, then ``--resume``: the hint printed must be the one that works."""
    import os
    import signal

    rows = []
    for when, wait_for in (("before the first step", None), ("after a step", "metrics.csv")):
        run = root / f"ctrl_c_{'step' if wait_for else 'early'}"
        args = ["train", w["other.zarr"], "--stage", "depth", "--run", run, "--max-steps", 60, "--batch-size", 2,
                "--width", 0.125, "--val-fraction", 0, "--test-fraction", 0, "--device", "cpu", "--no-tensorboard",
                "--workers", 0, "--split-file", root / "ctrl_c.split.json"]
        before = digest(w["other.zarr"])
        proc = subprocess.Popen([sys.executable, "-c", CLI, *map(str, args)], stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True, cwd=root, start_new_session=True)
        deadline = time.monotonic() + 120
        # early: once the run folder exists (imports done, the split drawn), before any step
        marker = run / (wait_for or "config.json")
        while proc.poll() is None and time.monotonic() < deadline:
            if marker.exists() and (wait_for is None or len(marker.read_text().splitlines()) > 1):
                break
            time.sleep(0.01)
        os.killpg(proc.pid, signal.SIGINT)
        out, err = proc.communicate()
        lines = [line for line in (out + err).splitlines() if line.strip() and not PROGRESS.search(line)]
        rows.append((f"train: Ctrl-C {when}", {"code": proc.returncode, "lines": len(lines),
                                               "traceback": any("Traceback" in x for x in lines),
                                               "unchanged": digest(w["other.zarr"]) == before,
                                               "first": lines[0] if lines else ""}))
        again = args + (["--resume"] if "again with --resume" in (lines[0] if lines else "") else [])
        rows.append((f"train: the command it says, {'--resume' if '--resume' in again else 'again'}",
                     check(again, root, [w["other.zarr"]])))
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--keep", type=Path, default=None, help="work in this folder and keep it")
    args = parser.parse_args()
    root = args.keep or Path(tempfile.mkdtemp(prefix="sceneforge-safety-"))
    root.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    w = setup(root)
    print(f"set up in {time.perf_counter() - t0:.0f} s: {root}")
    rows = [(name, check(a, root, inputs)) for name, a, inputs in cases(w)]
    rows += interrupted_training(w, root)
    repaired = []
    for name, a, inputs, store in damaged_cases(w, root):
        rows.append((name, check(a, root, inputs)))
        if a[0] == "render":
            repaired.append(store)
    width = max(len(name) for name, _ in rows)
    print(f"{'case':<{width}}  exit  lines  traceback  inputs unchanged  first line")
    for name, r in rows:
        first = r["first"] if len(r["first"]) <= 110 else r["first"][:107] + "..."
        print(f"{name:<{width}}  {r['code']:>4}  {r['lines']:>5}  {'yes' if r['traceback'] else 'no':>9}  "
              f"{'yes' if r['unchanged'] else 'NO':>16}  {first}")
    from sceneforge.store import array_digests, validate_store

    clean = json.dumps(sorted(array_digests(str(w["clean.zarr"])).items()))
    same = 0
    for store in repaired:
        files = [p for p in store.rglob("*") if p.is_file() and p.name != "zarr.json"]
        identical = (json.dumps(sorted(array_digests(str(store)).items())) == clean and not validate_store(str(store))
                     and all(p.read_bytes() == (w["clean.zarr"] / p.relative_to(store)).read_bytes() for p in files))
        same += identical
        print(f"{store.name}: repaired to the clean render's bytes: {'yes' if identical else 'NO'} "
              f"(checksum {hashlib.sha256(json.dumps(sorted(array_digests(str(store)).items())).encode()).hexdigest()[:16]}"
              f", clean {hashlib.sha256(clean.encode()).hexdigest()[:16]})")
    tracebacks = sum(r["traceback"] for _, r in rows)
    changed = sum(not r["unchanged"] for _, r in rows)
    # validate's report is a line per problem by design
    multi = sum(r["lines"] > 1 and r["code"] != 0 for name, r in rows if not name.endswith("validate"))
    print(f"{len(rows)} cases: {tracebacks} tracebacks, {changed} inputs changed, {multi} failures of more than "
          f"one line (validate's report aside); {same} of {len(repaired)} damaged stores repaired to the clean bytes; "
          f"{time.perf_counter() - t0:.0f} s")
    if args.keep is None:
        shutil.rmtree(root)


if __name__ == "__main__":
    main()
