"""Step 4 of a run (main process, single writer): the staged mesh parts into the ragged mesh
arrays, provenance and the failure log into the attributes with ``complete: true``, and the
staging folder removed."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from ..store import StoreWriter
from .assign import Plan
from .staging import STAGING, mesh_parts

if TYPE_CHECKING:
    from ..config import DatasetConfig

#: the planning record's entries that the store's ``houses`` attribute keeps
PROVENANCE = ("id", "format", "path", "views", "instances", "triangles", "rooms", "warnings", "notes", "cameras",
              "inputs")


def finalize_store(writer: StoreWriter, plan: Plan, config: "DatasetConfig", houses: str,
                   markers: list[dict]) -> tuple[list[dict], list[dict]]:
    """Step 4, given every shard's marker in shard order. Returns the houses' provenance
    and the failure log."""
    provenance, failures = provenance_of(plan, markers)
    if config.view.with_mesh:
        counts = np.concatenate([np.array(m["mesh_counts"], dtype=np.int64).reshape(-1, 2, 2) for m in markers]
                                or [np.zeros((0, 2, 2), np.int64)])
        writer.write_meshes(config, counts, mesh_parts(writer, markers))
    files = {key: digest for m in markers for key, digest in m["files"].items() if not key.startswith(STAGING)}
    writer.finalize(config, houses, len(plan.views), houses=provenance, failures=failures, files=files)
    writer.rm(STAGING)
    return provenance, failures


def provenance_of(plan: Plan, markers: list[dict]) -> tuple[list[dict], list[dict]]:
    """Every house's provenance (status ``ok`` or ``failed``), and the failure log: each
    failed house, then its failed views, in house order."""
    view_failures = {}
    for m in markers:
        for f in m["failures"]:
            view_failures.setdefault(f["house"], []).append(f)
    failures, provenance = [], []
    for rec in plan.houses:
        entry = {k: rec[k] for k in PROVENANCE if k in rec}
        entry["status"] = "failed" if "failure" in rec else "ok"
        provenance.append(entry)
        if "failure" in rec:
            failures.append({"house": rec["id"], **rec["failure"], "view": None})
        failures += view_failures.get(rec["id"], [])
    return provenance, failures
