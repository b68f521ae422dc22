"""Step 2 of a run: number the views house by house, from the records of step 1
(:mod:`.plan`), and say what each shard's views are made from."""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ViewPlan:
    """One view to compute: its index, house and camera."""

    index: int
    house: int
    camera_id: int
    K: np.ndarray
    cam_to_world: np.ndarray


@dataclass(frozen=True)
class Plan:
    """Every view of a run in order, and the houses they come from (records of step 1)."""

    houses: tuple[dict, ...]
    views: tuple[ViewPlan, ...]

    @classmethod
    def from_records(cls, records: list[dict]) -> "Plan":
        views, houses = [], []
        for h, rec in enumerate(records):
            start = len(views)
            if "failure" not in rec:
                for cid, K, pose in zip(rec["camera_id"], rec["K"], rec["cam_to_world"]):
                    views.append(ViewPlan(len(views), h, cid, np.array(K), np.array(pose)))
            houses.append({**rec, "views": [start, len(views)]})
        return cls(tuple(houses), tuple(views))

    def shards(self, per_shard: int) -> list[tuple[int, int]]:
        n = len(self.views)
        return [(s, min(s + per_shard, n)) for s in range(0, n, per_shard)]

    def digest(self, start: int, stop: int) -> str:
        """SHA-256 (hex) of what views ``start:stop`` are made from: per view its index,
        house id, the house's input fingerprint, camera id and camera. A shard's marker
        keeps it: the shard is reused only where the plan gives the same digest."""
        h = hashlib.sha256()
        for v in self.views[start:stop]:
            rec = self.houses[v.house]
            h.update(json.dumps([v.index, rec["id"], rec.get("inputs"), v.camera_id, v.K.tolist(),
                                 v.cam_to_world.tolist()], sort_keys=True).encode())
        return h.hexdigest()
