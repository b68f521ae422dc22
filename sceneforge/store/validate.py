"""Checking a store (:func:`check_store`, :func:`validate_store`): against the schema and the
layout, its manifest's file hashes, and for internal consistency and the ground-truth rules.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from ..conventions import LAYER_NAMES, NYU40_NAMES, nyu40_table, tol
from ..errors import SceneforgeError, listed, plural
from .layout import MESH_KINDS, array_specs, sizes_of
from .reader import SceneStore, arrays_of, open_group
from .writer import StoreWriter

if TYPE_CHECKING:
    import zarr

    from ..config import DatasetConfig


#: the problem of a shard zarr cannot decode
UNDECODABLE = "cannot be decoded"


def describe(group: "zarr.Group") -> dict:
    """The document ``schemas/store.schema.json`` validates: attributes and array metadata."""
    arrays = {}
    for path, array in arrays_of(group):
        codecs = []
        for codec in array.metadata.codecs:
            codecs.append(codec.to_dict()["name"])
            codecs += [c.to_dict()["name"] for c in getattr(codec, "codecs", ())]
        arrays[path] = {
            "shape": list(array.shape),
            "dtype": array.metadata.data_type.to_json(zarr_format=3),
            "chunks": list(array.chunks),
            "shards": list(array.shards) if array.shards else None,
            "codecs": codecs,
        }
    return {"attributes": group.attrs.asdict(), "arrays": arrays}


@dataclass
class StoreCheck:
    """What :func:`check_store` found.

    kind     : ``"dataset"`` (written by render) or ``"prediction"`` (by predict)
    problems : one line each, most telling first (empty: valid)
    notes    : what was not checked, and why; for damaged files, how to repair them
    prediction : a prediction store's ``prediction`` attribute (what predict recorded: the
               ``views`` it predicted, of the split ``split``); None for a dataset store
    """

    path: str
    kind: str
    views: int
    complete: bool
    problems: list[str]
    notes: list[str]
    prediction: dict | None = None

    @property
    def valid(self) -> bool:
        return not self.problems

    def summary(self) -> str:
        """One line: valid, incomplete, or how many problems."""
        if not self.complete:
            return (f"{self.path}: incomplete: a run writing it is in progress or was interrupted; run the same "
                    "command again to finish it")
        what = f"{self.kind} store, {plural(self.views, 'view')}"
        predicted = (self.prediction or {}).get("views")
        if isinstance(predicted, list):  # the other views of a prediction store are blank: not predictions
            split = self.prediction.get("split")
            what = f"prediction store, {plural(len(predicted), 'predicted view')} of {self.views}"
            what += f", split {split}" if split else ""
        if self.valid:
            return f"{self.path}: valid ({what})"
        n = len(self.problems)
        return f"{self.path}: invalid, {n} problem{'s' if n != 1 else ''} ({what})"


def validate_store(path: str, storage_options: dict | None = None) -> list[str]:
    """Every problem of the store at ``path`` (empty = valid): :func:`check_store`'s."""
    return check_store(path, storage_options).problems


def check_store(path: str, storage_options: dict | None = None) -> StoreCheck:
    """Check the store at ``path`` for what a reader relies on.

    - the schema and layout (arrays, shapes, chunks, attributes), and that it is complete
      (an incomplete store is reported as that one problem);
    - its files: every file of the manifest present with the SHA-256 recorded when it was
      written (a shard that is all fill values has no file, which the manifest records),
      none that the run did not write, no staging folder or temporary files left;
    - every shard decodable;
    - the attributes consistent with the arrays (view ranges, ids, the failure log, the views
      a prediction store predicted);
    - content: cameras finite and rigid, classes in 0..40, failed views blank; in a dataset
      store also the ground-truth rules (M1 = M2, M3 = M4, D3 only after D1, depths
      ordered and >= 0, classes and instances set exactly where a layer is; the labels of
      every layer, where the store has them, docs/spec.md §4.7), which a prediction store
      does not follow (noted, not checked);
    - the ray-intersection layers, where the store has them (docs/spec.md §4.7): depths
      ascending along the layers and NaN past the last, labels and unit normals set exactly
      where a depth is, the first layer where the first surface (D1 or D5) is and no deeper;
    - meshes: offsets from 0 to the row counts, faces within their view's vertices,
      non-empty, non-degenerate meshes where the view has layers.
    Raises :class:`SceneforgeError` when there is no store at ``path``.
    """
    from sceneforge import schemas

    from ..config import DatasetConfig

    group = open_group(path, "r", storage_options)
    doc = describe(group)
    attrs = doc["attributes"]
    kind = "prediction" if "prediction" in attrs else "dataset"
    n = attrs.get("views", 0) if isinstance(attrs.get("views"), int) else 0
    check = StoreCheck(str(path), kind, n, bool(attrs.get("complete", True)), [], [], attrs.get("prediction"))
    check.problems += schemas.errors(doc, "store")
    if check.problems:
        return check
    if not check.complete:
        check.problems.append("incomplete: a run writing it is in progress or was interrupted; run the same "
                              "command again to finish it")
        return check
    try:
        config = DatasetConfig.from_dict(attrs["config"], what="config attribute", recorded=True)
    except SceneforgeError as e:
        check.problems.append(str(e))
        return check
    if n == 0:
        failed = len({f["house"] for f in attrs.get("failures", [])})
        check.problems.append(f"no views: the store holds none ({plural(failed, 'house')} failed; its "
                              "failure log says why)")
        return check
    check.problems += _check_layout(doc["arrays"], config, n)
    check.problems += _check_attrs(attrs, n)
    if check.problems:
        return check
    files = StoreWriter(str(path), storage_options)
    file_problems = _check_files(files, attrs, config, check.notes)
    check.problems += file_problems
    store = SceneStore(group)
    problems, layers = _check_views(store, config, kind == "prediction", check.notes)
    check.problems += problems
    if store.has_mesh:
        check.problems += _check_meshes(store, layers)
    if file_problems or any(UNDECODABLE in p for p in problems):
        check.notes.append(repair_hint(str(path), attrs))
    return check


def repair_hint(path: str, attrs: dict) -> str:
    """How to repair the store at ``path`` (of group attributes ``attrs``): the command that
    wrote it, run again."""
    prediction = attrs.get("prediction")
    if prediction:
        return (f"repair: predict again, `sceneforge predict {prediction.get('run', 'RUN')} "
                f"{prediction.get('source', 'STORE')} {path} --overwrite` (with the options it was predicted with)")
    return (f"repair: `sceneforge render {attrs['houses_source']} {path} --repair` re-renders exactly the damaged "
            "shards (with the config the store records) and removes the files no run wrote")


def _check_files(files: "StoreWriter", attrs: dict, config: "DatasetConfig", notes: list[str]) -> list[str]:
    """The store's files against its manifest; what a run leaves behind."""
    problems = []
    if files.exists("_staging"):
        problems.append("_staging/: a run's staging folder is left in a complete store (a second run wrote "
                        "into it, or it was copied while a run was writing)")
    if files.local:
        partial = [p for p in files.fs.find(files.root) if p.endswith(".partial")]
        if partial:
            problems.append(f"{len(partial)} temporary file(s) of writes cut short (*.partial)")
    record = attrs.get("manifest")
    if record is None:
        notes.append("no manifest (a store written before sceneforge recorded one): file hashes not checked")
        return problems
    found = file_damage(files, attrs, config)
    if found.manifest:
        return problems + [found.manifest]
    for what, keys in (("missing (written by the run, gone since)", found.missing),
                       ("damaged (not the bytes written: truncated or changed)", found.damaged),
                       ("not written by the run", found.unexpected)):
        if keys:
            problems.append(f"{len(keys)} file(s) {what}: {listed(sorted(keys))}")
    return problems


@dataclass
class FileDamage:
    """A store's files against its manifest: the keys ``missing`` (written, gone since),
    ``damaged`` (not the bytes written) and ``unexpected`` (not written by the run);
    ``manifest``: the problem of the manifest itself (missing or changed: nothing else is
    known then), else empty. No manifest at all (older stores): nothing found."""

    missing: list[str] = field(default_factory=list)
    damaged: list[str] = field(default_factory=list)
    unexpected: list[str] = field(default_factory=list)
    manifest: str = ""


def file_damage(files: "StoreWriter", attrs: dict, config: "DatasetConfig") -> FileDamage:
    """Hash every file the manifest of the store (``attrs``, its group attributes) lists and
    list the array files it does not: what :func:`check_store` reports and ``sceneforge
    render`` repairs."""
    record = attrs.get("manifest")
    if record is None:
        return FileDamage()
    data = files.get(record["file"])
    if data is None or hashlib.sha256(data).hexdigest() != record["sha256"]:
        return FileDamage(manifest=f"{record['file']}: {'missing' if data is None else 'not the one written with the store'}")
    manifest = json.loads(data)["files"]
    found = FileDamage()
    for key, digest in manifest.items():
        now = files.sha256(key)
        if now != digest:
            (found.missing if now is None else found.unexpected if digest is None else found.damaged).append(key)
    listed = set(manifest)
    for spec in array_specs(config):
        found.unexpected += [key for key in files._chunk_files(spec.name) if key not in listed]
    return found


def _check_layout(arrays: dict, config: "DatasetConfig", n: int) -> list[str]:
    problems = []
    sizes = sizes_of(config, n)
    expected = {s.name: s for s in array_specs(config)}
    for name in sorted(set(arrays) - set(expected)):
        problems.append(f"{name}: not expected with this config")
    for name, spec in expected.items():
        meta = arrays.get(name)
        if meta is None:
            problems.append(f"{name}: missing")
            continue
        shape = tuple(meta["shape"])
        if spec.per_view:
            want = spec.shape(sizes)
            if shape != want:
                problems.append(f"{name}: shape {shape}, expected {want} {spec.dims}")
            if tuple(meta["chunks"]) != (1, *want[1:]):
                problems.append(f"{name}: chunks {meta['chunks']}, expected one view per chunk")
            if meta["shards"][0] != config.store.views_per_shard:
                problems.append(f"{name}: {meta['shards'][0]} views per shard, config says "
                                f"{config.store.views_per_shard}")
        elif spec.dims == ("N+1",) and shape != (n + 1,):
            problems.append(f"{name}: shape {shape}, expected ({n + 1},)")
        elif len(shape) != len(spec.dims) or any(isinstance(d, int) and d != s for d, s in zip(spec.dims, shape)):
            problems.append(f"{name}: shape {shape} does not match {spec.dims}")
    return problems


def _check_attrs(attrs: dict, n: int) -> list[str]:
    problems = []
    if attrs["nyu40"] != nyu40_table():
        problems.append("nyu40: the label table differs from this sceneforge's")
    spans = [tuple(h["views"]) for h in attrs["houses"] if h["status"] == "ok"]
    covered = sum(b - a for a, b in spans)
    if sorted(spans) != spans or any(a2 != b1 for (_, b1), (a2, _) in zip(spans, spans[1:])) or covered != n:
        problems.append(f"houses: view ranges {spans} do not tile the {n} views in order")
    ids = {h["id"] for h in attrs["houses"]}
    for f in attrs["failures"]:
        if f["house"] not in ids:
            problems.append(f"failures: house {f['house']!r} is not in the houses list")
    predicted = (attrs.get("prediction") or {}).get("views")
    in_range = isinstance(predicted, list) and all(isinstance(i, int) and 0 <= i < n for i in predicted)
    if predicted is not None and not (in_range and len(set(predicted)) == len(predicted)):
        problems.append(f"prediction: views is not a list of distinct view indices in 0..{n - 1}")
    return problems


def _rigid_problems(T: np.ndarray) -> np.ndarray:
    """(n,) bool: the (n, 4, 4) poses that are not finite rigid transforms."""
    R = T[:, :3, :3]
    bad = ~np.isfinite(T).all(axis=(1, 2))
    with np.errstate(invalid="ignore"):
        bad |= ~np.isclose(np.einsum("nji,njk->nik", R, R), np.eye(3), atol=tol.rotation).all(axis=(1, 2))
        bad |= np.linalg.det(np.where(np.isfinite(R), R, 0)) < 0
    bad |= ~(T[:, 3] == [0, 0, 0, 1]).all(axis=1)
    return bad


def _per_view(mask: np.ndarray) -> np.ndarray:
    """(n,) bool: the views of an (n, ...) mask with any pixel set."""
    return mask.reshape(len(mask), -1).any(axis=1)


class _Findings:
    """Views found breaking each rule, reported as one line per rule over the whole store."""

    def __init__(self):
        self.views: dict[str, list[int]] = {}

    def add(self, rule: str, bad: np.ndarray, start: int) -> None:
        hits = np.flatnonzero(bad)
        if len(hits):
            self.views.setdefault(rule, []).extend(int(start + i) for i in hits)

    def lines(self) -> list[str]:
        out = []
        for rule, views in self.views.items():
            shown = ", ".join(map(str, views[:5])) + (", ..." if len(views) > 5 else "")
            out.append(f"{rule}: {len(views)} view{'s' if len(views) != 1 else ''} ({shown})")
        return out


def _check_views(store: SceneStore, config: "DatasetConfig", prediction: bool,
                 notes: list[str]) -> tuple[list[str], np.ndarray | None]:
    """The problems of the per-view arrays, and per view whether D1 and D5 are set
    (``(n, 2) bool``, what :func:`_check_meshes` expects meshes for; None for predictions
    or when a shard cannot be read)."""
    problems, layers = [], []
    spans = {h["id"]: h["views"] for h in store.attrs["houses"] if h["status"] == "ok"}
    failed_views = {f["view"] for f in store.attrs["failures"] if f["stage"] == "view"}
    step = config.store.views_per_shard
    n_classes = len(NYU40_NAMES)
    found = _Findings()
    report = found.add
    if prediction:
        notes.append("a prediction store: the ground-truth rules (layer masks and order, instances) do not "
                     "apply and were not checked")

    for start in range(0, len(store), step):
        stop = min(start + step, len(store))
        a, broken = {}, False
        for name in store.names:
            try:
                a[name] = store.array(name)[start:stop]
            except Exception as e:  # a damaged shard: zarr's codecs raise many kinds
                problems.append(f"{name}: shard {start // step} (views {start}-{stop - 1}) {UNDECODABLE} "
                                f"({type(e).__name__}: {e})")
                broken = True
        if broken:
            layers.append(np.zeros((stop - start, 2), bool))  # unknown: no mesh required
            continue
        valid = a["valid"]
        owners = np.array([(span := spans.get(str(hid))) is None or not span[0] <= start + i < span[1]
                           for i, hid in enumerate(a["house_id"])])
        report("house_id is not the house whose view range holds the view", owners, start)
        logged = np.array([(start + i) in failed_views for i in range(stop - start)])
        report("valid disagrees with the failure log", valid.astype(bool) == logged, start)
        report("camera_id < 0", a["camera_id"] < 0, start)
        K = a["K"]
        report("K is not finite with positive focal lengths",
               ~np.isfinite(K).all(axis=(1, 2)) | ~(K[:, 0, 0] > 0) | ~(K[:, 1, 1] > 0), start)
        report("cam_to_world is not a rigid transform", _rigid_problems(a["cam_to_world"]), start)
        v = valid.astype(bool)
        report("overhead_cam_to_world is not a rigid transform", v & _rigid_problems(a["overhead_cam_to_world"]),
               start)
        report("overhead_extent is not > 0", v & ~(a["overhead_extent"] > 0), start)
        d, cat = a["depth"], a["category"]
        f = np.isfinite(d)
        report("a class outside 0..40", _per_view(cat >= n_classes) | _per_view(a["overhead_category"] >= n_classes),
               start)
        od = a["overhead_depth"]
        fo = np.isfinite(od)
        report("a failed view holds data", ~v & (_per_view(f) | _per_view(fo)), start)
        if "rgb" in a:
            report("a failed view holds an RGB image", ~v & _per_view(a["rgb"] != 0), start)
        if prediction:
            continue
        inst = a["instance"]
        report("D1 and D2 are not set on the same pixels (M1 != M2)", _per_view(f[:, 0] != f[:, 1]), start)
        report("D3 and D4 are not set on the same pixels (M3 != M4)", _per_view(f[:, 2] != f[:, 3]), start)
        report("D3 is set where D1 is not", _per_view(f[:, 2] & ~f[:, 0]), start)
        with np.errstate(invalid="ignore"):
            report("negative depth", _per_view(d < 0), start)
            report("D2 before D1", _per_view(d[:, 1] < d[:, 0] - tol.stored_depth), start)
            report("D4 before D3", _per_view(d[:, 3] < d[:, 2] - tol.stored_depth), start)
            report("D3 before D2", _per_view(d[:, 2] < d[:, 1] - tol.same_instance_hit - tol.stored_depth), start)
            report("an object layer behind D5", _per_view(d[:, :4] > d[:, 4:] + tol.envelope_slack + tol.stored_depth),
                   start)
        for k, layer in ((0, 0), (1, 2), (2, 4)):
            report(f"category of {LAYER_NAMES[layer]} set where {LAYER_NAMES[layer]} is NaN",
                   _per_view(~f[:, layer] & (cat[:, k] != 0)), start)
        for k, layer in ((0, 0), (1, 2)):
            report(f"instance of {LAYER_NAMES[layer]} is not set exactly where {LAYER_NAMES[layer]} is",
                   _per_view(f[:, layer] != (inst[:, k] >= 0)), start)
        if "layers/category" in a:
            _check_layer_labels(a, f, report, start)
        if "intersections/depth" in a:
            _check_intersections(a, v, report, start)
        report("overhead: D1 and D2 are not set on the same pixels", _per_view(fo[:, 0] != fo[:, 1]), start)
        report("overhead_height is not set exactly where overhead D1 is",
               _per_view(np.isfinite(a["overhead_height"]) != fo[:, 0]), start)
        # what a ground-truth mesh must hold: objects wherever D1 is, the envelope wherever D5 is
        layers.append(np.stack([_per_view(f[:, 0]), _per_view(f[:, 4])], axis=1))
    complete = not prediction and sum(map(len, layers)) == len(store)
    return problems + found.lines(), np.concatenate(layers) if complete and layers else None


def _check_layer_labels(a: dict[str, np.ndarray], f: np.ndarray, report, start: int) -> None:
    """The rules of the labels of every layer (docs/spec.md §4.7) on a block of views: ``a``
    its arrays, ``f`` (n, 5, H, W) bool where its layers are set."""
    cat, inst, normal = a["layers/category"], a["layers/instance"], a["layers/normal"]
    report("layers/category of D1, D3, D5 is not the category array", _per_view(cat[:, 0::2] != a["category"]), start)
    report("layers/instance of D1, D3 is not the instance array", _per_view(inst[:, [0, 2]] != a["instance"]), start)
    report("layers/category, layers/instance: D2 is not labelled as D1, or D4 as D3",
           _per_view(cat[:, [1, 3]] != cat[:, [0, 2]]) | _per_view(inst[:, [1, 3]] != inst[:, [0, 2]]), start)
    report("layers/instance is not set exactly where its layer is", _per_view((inst >= 0) != f), start)
    report("layers/category is set where its layer is NaN", _per_view(~f & (cat != 0)), start)
    finite = np.isfinite(normal)
    report("layers/normal is not set exactly where its layer is (all three components)",
           _per_view(finite.any(axis=2) != f) | _per_view(finite.any(axis=2) != finite.all(axis=2)), start)
    with np.errstate(invalid="ignore"):
        report("layers/normal is not of unit length", _per_view(np.abs(np.linalg.norm(normal, axis=2) - 1)
                                                                 > tol.stored_normal), start)
        if "normal" in a:
            # where D1 is nearer than D5, D1's face is the first hit: the stored first-hit
            # normal is its winding normal, turned to face the camera
            d = a["depth"]
            first = f[:, 0] & ~(d[:, 4] <= d[:, 0])
            cos = np.abs(np.einsum("nchw,nchw->nhw", normal[:, 0], a["normal"]))
            report("layers/normal of D1 is not the first-hit normal (up to its facing) where D1 is the first hit",
                   _per_view(first & ~(cos >= 1 - tol.stored_normal)), start)


def _check_intersections(a: dict[str, np.ndarray], valid: np.ndarray, report, start: int) -> None:
    """The rules of the ray-intersection layers (docs/spec.md §4.7) on a block of views: ``a``
    its arrays, ``valid`` (n,) bool its computed views."""
    d = a["intersections/depth"]
    f = np.isfinite(d)
    report("intersections: a failed view holds data", ~valid & _per_view(f), start)
    report("intersections/depth: a layer set after an empty one (NaN must be past the last surface)",
           _per_view(f[:, 1:] & ~f[:, :-1]), start)
    with np.errstate(invalid="ignore"):
        report("intersections/depth: negative depth", _per_view(d < 0), start)
        report("intersections/depth: not ascending along the layers", _per_view(d[:, 1:] < d[:, :-1]), start)
        # the first surface of a ray is its first object hit or its closing hit, whichever is
        # nearer; the closing hit is the nearest envelope hit up to float32 ties, so only
        # "not deeper" holds exactly
        first = np.fmin(a["depth"][:, 0], a["depth"][:, 4])
        report("intersections/depth: layer 0 is not set exactly where D1 or D5 is", _per_view(f[:, 0] != np.isfinite(first)),
               start)
        report("intersections/depth: layer 0 is deeper than D1 or D5", _per_view(d[:, 0] > first), start)
    report("intersections/instance is not set exactly where its depth is", _per_view((a["intersections/instance"] >= 0) != f),
           start)
    report("intersections/category is set where its depth is NaN", _per_view(~f & (a["intersections/category"] != 0)), start)
    report("intersections/category: a class outside 0..40", _per_view(a["intersections/category"] >= len(NYU40_NAMES)),
           start)
    report("intersections/front_facing is set where its depth is NaN", _per_view(~f & a["intersections/front_facing"]),
           start)
    normal = a["intersections/normal"]
    finite = np.isfinite(normal)
    report("intersections/normal is not set exactly where its depth is (all three components)",
           _per_view(finite.any(axis=2) != f) | _per_view(finite.any(axis=2) != finite.all(axis=2)), start)
    with np.errstate(invalid="ignore"):
        report("intersections/normal is not of unit length",
               _per_view(np.abs(np.linalg.norm(normal, axis=2) - 1) > tol.stored_normal), start)


def _check_meshes(store: SceneStore, layers: np.ndarray | None) -> list[str]:
    problems = []
    found = _Findings()
    for kind in MESH_KINDS:
        try:
            vo = store.array(f"mesh/{kind}/vertex_offsets")[:]
            fo = store.array(f"mesh/{kind}/face_offsets")[:]
        except Exception as e:
            problems.append(f"mesh/{kind}: the offsets cannot be decoded ({type(e).__name__}: {e})")
            continue
        nv, nf = store.array(f"mesh/{kind}/vertices").shape[0], store.array(f"mesh/{kind}/faces").shape[0]
        bad_offsets = False
        for name, off, total in (("vertex_offsets", vo, nv), ("face_offsets", fo, nf)):
            if off[0] != 0 or off[-1] != total or (np.diff(off) < 0).any():
                problems.append(f"mesh/{kind}/{name}: not non-decreasing from 0 to {total}")
                bad_offsets = True
        if bad_offsets:
            continue
        vertices, faces = store.array(f"mesh/{kind}/vertices"), store.array(f"mesh/{kind}/faces")
        for start in range(0, len(store), 4096):
            stop = min(start + 4096, len(store))
            try:
                f = np.asarray(faces[fo[start]:fo[stop]])
                v = np.asarray(vertices[vo[start]:vo[stop]])
            except Exception as e:
                problems.append(f"mesh/{kind}: views {start}-{stop - 1} cannot be decoded ({type(e).__name__}: {e})")
                continue
            owner = np.repeat(np.arange(start, stop), np.diff(fo[start:stop + 1]))
            limit = (vo[owner + 1] - vo[owner])[:, None]
            outside = ((f < 0) | (f >= limit)).any(axis=1)
            found.add(f"mesh/{kind}/faces: face indices outside the view's vertices",
                      np.bincount(owner[outside] - start, minlength=stop - start) > 0, start)
            if layers is None:
                continue
            # faces index their view's rows: shift them to rows of this block's vertices
            rows = np.where(outside[:, None], 0, f + (vo[owner] - vo[start])[:, None])
            tri = v[rows] if len(v) else np.zeros((len(f), 3, 3), np.float32)
            area2 = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
            solid = np.bincount(owner[area2 > 0] - start, minlength=stop - start) > 0
            what = "D1" if kind == "objects" else "D5"
            found.add(f"mesh/{kind}: empty or degenerate (zero-area faces only) in a view whose {what} is set",
                      layers[start:stop, 0 if kind == "objects" else 1] & ~solid, start)
        try:
            negative = (store.array(f"mesh/{kind}/instance")[:] < 0).any()
        except Exception as e:
            problems.append(f"mesh/{kind}/instance: cannot be decoded ({type(e).__name__}: {e})")
            continue
        if negative:
            problems.append(f"mesh/{kind}/instance: negative instance index")
    return problems + found.lines()
