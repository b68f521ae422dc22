"""Fault injection: SIGKILL renders at random moments, resume each, compare with a run that
was never interrupted.

Two uninterrupted renders (in child processes, like a user's) give the reference store and
the wall time T (their mean). Then, N times: a fresh render is started and SIGKILLed at a
random moment (seeded): once the run has staged a random number of its files (house records,
shard markers and mesh parts: from "nothing yet" to "all shards done, finalizing"), plus a
random 0-0.3 s, so kills land while houses are planned, shards written or the store
finalized; the same command is run again to completion, and the resumed store's per-array
digests (``sceneforge.store.array_digests``) are compared with the reference's;
``validate`` must pass too. Prints per kill the moment, what had been staged, whether the
store is identical and the time lost (time to the kill + resume time - T), then the totals.

    python benchmarks/fault_injection.py --kills 8 --seed 0
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from sceneforge.store import array_digests, validate_store

CLI = "from sceneforge.cli.main import main; main()"


def n_staged(out: Path) -> int:
    """Files the run has staged so far (house records, shard markers, mesh parts)."""
    try:
        return sum(1 for p in (out / "_staging").rglob("*") if p.is_file() and not p.name.endswith(".partial"))
    except OSError:  # the folder went while it was listed: the run is finalizing
        return 1 << 30


def render(args: list[str], kill: tuple[int, float] | None = None) -> tuple[float, bool, str]:
    """Run ``sceneforge render args``; with ``kill = (files, delay)``, SIGKILL it ``delay``
    seconds after it has staged ``files`` files. Returns the wall time, whether it was
    killed (False: it ended first) and how many shards it wrote ("?" when killed)."""
    out = Path(args[1])
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-c", CLI, "render", *args], stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)
    if kill is not None:
        files, delay = kill
        while proc.poll() is None and n_staged(out) < files:
            time.sleep(0.005)
        time.sleep(delay)
        if proc.poll() is None:
            proc.send_signal(signal.SIGKILL)
            proc.wait()
            return time.perf_counter() - t0, True, "?"
    _, err = proc.communicate()
    if proc.returncode != 0:
        raise SystemExit(f"render failed ({proc.returncode}): {err}")
    written = re.search(r"\((\d+) written now\)", err)
    return time.perf_counter() - t0, False, written.group(1) if written else "0"


def staged(out: Path) -> str:
    """What an interrupted run had staged: house records and shard markers."""
    if not (out / "_staging").is_dir():
        return "nothing staged" if not (out / "zarr.json").exists() else "complete"
    houses = len(list((out / "_staging" / "houses").glob("*.json")))
    shards = len(list((out / "_staging" / "done").glob("*.json")))
    return f"{houses} houses planned, {shards} shards done"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--kills", type=int, default=8, help="renders to kill (default 8)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the kill moments")
    parser.add_argument("--houses", default="bundled:toy")
    parser.add_argument("--workers", type=int, default=1)
    args = parser.parse_args()

    root = Path(tempfile.mkdtemp(prefix="sceneforge-faults-"))
    config = root / "config.json"
    # small views, two per shard: 6 shards, each a moment at which a kill leaves one half written
    config.write_text(json.dumps({"width": 64, "height": 48, "views_per_house": 4, "rgb": {"enabled": True},
                                  "view": {"overhead": {"resolution": 32}}, "store": {"views_per_shard": 2}}))
    common = ["--config", str(config), "--workers", str(args.workers)]
    try:
        times, digests = [], []
        for k in range(2):
            reference = root / f"reference_{k}.zarr"
            times.append(render([args.houses, str(reference), *common])[0])
            digests.append(array_digests(str(reference)))
        assert digests[0] == digests[1], "two uninterrupted renders differ"
        want, T = digests[0], float(np.mean(times))
        print(f"uninterrupted render: {times[0]:.1f} s and {times[1]:.1f} s (T = {T:.1f} s), {len(want)} arrays")
        n_houses = len(json.loads((root / "reference_0.zarr" / "zarr.json").read_text())["attributes"]["houses"])
        n_shards = len(list((root / "reference_0.zarr" / "valid" / "c").glob("*")))
        staged_total = 2 + n_houses + 2 * n_shards
        rng = np.random.default_rng(args.seed)
        identical = landed = 0
        lost = []
        for k in range(args.kills):
            out = root / f"killed_{k}.zarr"
            # 0 .. every file a run stages (run, created, a record per house, a marker and a mesh part per shard)
            files, delay = int(rng.integers(0, staged_total + 1)), float(rng.uniform(0.0, 0.3))
            t_kill, killed, _ = render([args.houses, str(out), *common], kill=(files, delay))
            state = staged(out) if killed else "ended before the kill"
            t_resume, _, rendered = render([args.houses, str(out), *common])
            same = array_digests(str(out)) == want and validate_store(str(out)) == []
            identical += same
            landed += killed
            lost.append(t_kill + t_resume - T)
            print(f"kill {k + 1}: after {files:2d} staged files + {delay:.2f} s = {t_kill:5.1f} s ({state}); "
                  f"resumed in {t_resume:5.1f} s ({rendered} of {n_shards} shards rendered); "
                  f"{'identical' if same else 'DIFFERENT'}; "
                  f"time lost {lost[-1]:5.1f} s")
            shutil.rmtree(out)
        print(f"kills tried {args.kills}, landed {landed}, stores identical {identical} of {args.kills}; "
              f"time lost per kill: mean {np.mean(lost):.1f} s, max {np.max(lost):.1f} s "
              f"(uninterrupted: {T:.1f} s)")
        if identical != args.kills:
            raise SystemExit(1)
    finally:
        shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    main()
