"""3D-FRONT houses: one scene JSON plus 3D-FUTURE furniture models.

A 3D-FRONT root, as released and as :func:`sceneforge.testing.front3d.write_house` writes it::

    <root>/3D-FRONT/<uid>.json                    one house
    <root>/3D-FUTURE-model/<jid>/raw_model.obj    a furniture model (+ its .mtl, texture.png)
    <root>/3D-FUTURE-model/model_info.json        [{model_id, category, super-category, ...}]
    <root>/3D-FRONT-texture/<jid>/texture.png     the texture of the architecture material <jid>

The scene JSON is read as the well-kept readers read it (the 3D-FRONT-ToolBox's
``scripts/scene.py`` and ``utils.py``, ATISS's ``threed_front`` datasets, BlenderProc's
``Front3DLoader``), with what real files hold:

- ``furniture[]``: ``uid``, ``jid`` (the 3D-FUTURE model), ``title``, ``category``, ``valid``,
  ``bbox``/``size``. Only entries with ``valid: true`` are read, as all three readers do: the
  others (a third of real entries, often only ``uid``/``jid``/``aid``) are unreleased doors,
  windows, curtains and kitchen parts; they are counted and skipped before anything looks at
  their category. A missing ``raw_model.obj`` skips that piece (3D-FRONT references models that
  were never released); an unreadable one skips it with a warning naming the file.
- Categories go through ``sceneforge/data/front3d_categories.json``, finest name first: the
  model's ``category`` in ``model_info.json`` (by ``jid``), then the title (``super/sub``: the
  whole title when the table knows it, else its super-category), then the entry's own
  ``category`` (often a super-category: ``Cabinet/Shelf/Desk``), then the model's
  ``super-category``. The first name the table knows (or that is an NYU40 class name) decides
  the class; the first name given is the instance label. A piece any of its names calls a plant
  or a person is dropped.
- ``mesh[]``: architecture inline, in world coordinates: ``uid``, ``type`` (Floor, WallInner,
  Ceiling, Door, ...), flat ``xyz``, ``faces``, ``uv``, ``normal`` (numbers or numeric strings),
  ``material`` and ``constructid``. Meshes without faces are skipped (no category is looked
  up); exterior-only types (:data:`EXTERIOR_TYPES`: the outer faces of exterior walls and the
  sides and underside of the floor slab) are skipped and counted: no camera inside the house
  sees them, and kept as envelope they would end rays that leave through a window.
- Meshes with an empty ``type`` (real files hold customised architecture so: uid
  ``<n>/customizedfeaturemodel_1/<k>``, often with a ``constructid``) are typed from what
  the file says (:func:`untyped_kind`): the type of the first mesh of the same
  ``constructid`` that has one (the rest of the construct), else, for a customised feature
  model (the uid's segment), its geometry's main orientation: mostly horizontal faces are a
  ``CustomizedCeiling`` above :data:`CEILING_FEATURE_Y` and a ``CustomizedPlatform`` below it,
  anything else a ``CustomizedFeatureWall`` (the panelled background walls these mostly
  are). Each is counted (:data:`UNTYPED`); one none of this types keeps no category.
- Openings: a released ``Door``/``Window``/``BayWindow``/``Hole``/``Pocket`` mesh is only the
  jamb around its opening (the door and window models are not released), so every ray would
  pass through into the next room or outside. A mesh of those types whose faces all run through
  the wall (:func:`opening_rectangle`) gets a closing surface: a rectangle spanning the opening,
  halfway through the wall, recorded as door or window envelope (a ``Hole``/``Pocket`` is a
  door when it reaches down to its room's floor), so that D5 stops there as it did at the door
  and window models of the paper's SUNCG houses. Closing surfaces come after every other
  instance; two on the same opening count once (a Door/Window before a Hole/Pocket).
- Object meshes (cabinet boards, customised furniture: non-envelope types) of one room that
  share a ``constructid`` are one instance, the unit the file builds them as (a kitchen's 84
  boards are its few cabinets); each piece's material is a face group of the instance.
- ``material[]``: ``uid``, ``jid``, ``color`` (RGBA 0–255), ``texture`` (a URL, empty in real
  files), ``UVTransform``. The texture is ``3D-FRONT-texture/<jid>/texture.png`` (the
  toolbox's path; else the folder the URL names); ``uv`` becomes ``UVTransform[:2, :2] · uv``
  with ``UVTransform`` a row-major 3×3, as the toolbox applies it (its translation unused).
- ``scene.room[]``: ``type``, ``instanceid`` and ``children[]`` of
  ``{ref, instanceid, pos, rot, scale}``. Each child places the furniture or mesh whose uid
  is ``ref`` at ``R(rot) · (scale ⊙ v) + pos`` with ``rot`` a unit quaternion
  **(x, y, z, w)** (the toolbox's ``quaternion_to_matrix``); a mirroring (negative) scale
  reverses the face winding. Mesh children carry the identity in the released data. When two
  entries share a uid the last one is used, as the toolbox's dictionaries do.

Every loss is counted (:meth:`~sceneforge.houses.model.House.count_loss`: one line per reason in
``warnings``, so ``houses inspect`` and the store's provenance show it): unreleased pieces,
child references to no uid, duplicate uids, missing and unreadable models, unreadable meshes
and placements, exterior meshes, dropped plants. Pieces whose ``scale`` or model size look
wrong are kept and counted as flagged (:data:`SCALE_LIMIT`, :data:`SIZE_LIMIT`). A model folder
without ``model_info.json``, or with the models one folder too deep
(``3D-FUTURE-model/3D-FUTURE-model``), is an error naming the expected path.

Units are metres and +Y is up, as in sceneforge.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, replace
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ...conventions import NYU40_IDS, is_dropped, is_envelope, nyu40_id
from ...errors import HouseError, SceneforgeError
from ..categories import data_file, resolve
from ..model import House, Material, Room, make_instance
from .base import Format, HouseSource, json_document
from .meshio import Mesh, place, quaternion_matrix
from .obj import read_obj

if TYPE_CHECKING:
    from .. import LoadOptions

SCENE_DIR = "3D-FRONT"
MODEL_DIR = "3D-FUTURE-model"
TEXTURE_DIR = "3D-FRONT-texture"
MODEL_INFO = "model_info.json"
CATEGORY_FILE = "front3d_categories.json"

#: Mesh types only the outside of the house shows (normalised as :func:`_key` does).
EXTERIOR_TYPES: frozenset[str] = frozenset({"wallouter", "slabside", "slabbottom"})
#: Mesh types that frame an opening → the class of its closing surface (None: door when the
#: opening reaches the floor, else window).
OPENING_TYPES: dict[str, str | None] = {
    "door": "door", "window": "window", "baywindow": "window", "hole": None, "pocket": None,
}
#: A mesh is a jamb when at most this fraction of its face area faces along the wall's
#: through axis (a door leaf or a window frame faces along it with most of its area).
JAMB_FACING = 0.1
#: A Hole/Pocket whose bottom is within this of its room's floor is a door (metres).
DOOR_SILL = 0.15
#: Two closing surfaces whose corners agree to this are one opening (metres).
SAME_OPENING = 0.02
#: A child whose scale has a component (in absolute value) above this or below its inverse is
#: flagged (ATISS drops rooms with a scale above 5).
SCALE_LIMIT = 5.0
#: A model whose extent differs from its entry's ``bbox``/``size`` by more than this factor on
#: an axis longer than 1 cm is flagged (raw or as scaled, metres or centimetres).
SIZE_LIMIT = 2.0

#: a horizontal customised feature model (no ``type``) whose lowest point is above this is a
#: ceiling (a suspended or coffered ceiling), else a floor platform (metres above y = 0, the
#: floor of 3D-FRONT's one-level houses)
CEILING_FEATURE_Y = 1.5
#: a face is horizontal when its unit normal's |y| is above this
HORIZONTAL_FACE = 0.9

# Reasons for House.count_loss.
UNRELEASED = "furniture pieces skipped: unreleased (no 'valid': true)"
DANGLING = "children skipped: their ref names no furniture or mesh uid"
DUPLICATE = "duplicate uids in furniture[]/mesh[] (the last entry used)"
NO_MODEL = "furniture pieces skipped: 3D-FUTURE model missing"
BAD_MODEL = "furniture pieces skipped: 3D-FUTURE model unreadable"
BAD_PIECE = "pieces skipped: unreadable arrays, placement or geometry"
EXTERIOR = "exterior-only meshes skipped (WallOuter, SlabSide, SlabBottom)"
DROPPED = "pieces dropped: plants and persons"
NO_TEXTURE = "architecture materials whose texture image is missing"
UNTYPED = "meshes without a type, typed from their constructid or uid (kept)"
SCALE_FLAG = f"furniture pieces flagged: a scale outside 1/{SCALE_LIMIT:g}..{SCALE_LIMIT:g} (kept)"
SIZE_FLAG = f"furniture pieces flagged: model size {SIZE_LIMIT:g}x off the entry's bbox/size (kept)"


def detect(path: Path) -> bool:
    """True for a 3D-FRONT root (a folder holding ``3D-FRONT/``) or a scene JSON (``furniture``
    and ``scene``)."""
    if path.is_dir():
        return (path / SCENE_DIR).is_dir()
    doc = json_document(path)
    return isinstance(doc, dict) and "furniture" in doc and "scene" in doc


def list_houses(path: Path) -> list[HouseSource]:
    """Every scene of a root's ``3D-FRONT/`` folder, or the one scene of a scene JSON."""
    if path.is_dir():
        from . import find  # the registry, which imports this module

        return find(path / SCENE_DIR, FORMAT)
    return [HouseSource(path.stem, FORMAT.name, path)]


def _key(name: str) -> str:
    """A table key: lower case, runs of spaces as one, no spaces around ``/``."""
    return re.sub(r"\s*/\s*", "/", " ".join(str(name).split())).lower()


@lru_cache(maxsize=1)
def _tables() -> tuple[dict[str, str], tuple[tuple[str, str], ...]]:
    path = data_file(CATEGORY_FILE)
    try:
        raw = json.loads(path.read_text())
        table = {_key(k): str(v) for k, v in raw["categories"].items()}
        # a prefix keeps its trailing space ("300 - "), which _key drops
        prefixes = tuple((_key(k) + " " * k.endswith(" "), str(v)) for k, v in raw.get("prefixes", {}).items())
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as e:
        raise SceneforgeError(f"cannot read the 3D-FRONT category table {path}: {e}") from None
    targets = set(table.values()) | {v for _, v in prefixes}
    bad = sorted(v for v in targets if nyu40_id(v) is None and not is_dropped(0, v))
    if bad:
        raise SceneforgeError(f"{path}: {', '.join(bad)} are not NYU40 class names")
    return table, prefixes


def category_table() -> dict[str, str]:
    """Normalised 3D-FRONT name → NYU40 class name (or a dropped name: plant, person)."""
    return _tables()[0]


def _target(name: str) -> str | None:
    """The NYU40 (or dropped) class name ``name`` maps to, or None when unknown."""
    table, prefixes = _tables()
    key = _key(name)
    if key in table:
        return table[key]
    for prefix, target in prefixes:
        if key.startswith(prefix):
            return target
    return name if nyu40_id(name) is not None else None


def lookup(names) -> tuple[str, int | None, bool]:
    """``(label, NYU40 id or None, dropped)`` for the candidate names of one piece, best first.

    The label is the first (finest) name; the first name that maps decides the class;
    ``dropped`` is True when any name maps to, or is, a dropped class.
    """
    names = [str(n).strip() for n in names if n and str(n).strip()]
    cid, dropped = None, False
    for name in names:
        target = _target(name)
        dropped = dropped or is_dropped(0, name) or (target is not None and is_dropped(0, target))
        if target is not None and cid is None and not is_dropped(0, target):
            cid = nyu40_id(target)
    return (names[0] if names else ""), cid, dropped


def untyped_kind(entry: dict, xyz: np.ndarray, faces: np.ndarray, construct_types: dict[str, str]) -> str:
    """The mesh type of a ``mesh[]`` entry whose ``type`` is empty (module docs), or "" when
    nothing in the file says one.

    xyz   : (n, 3) float64 its vertices
    faces : (m, 3) int64   its faces
    construct_types : ``constructid`` → the type of its first mesh that has one
    """
    construct = str(entry.get("constructid") or "")
    if construct_types.get(construct):
        return construct_types[construct]
    segments = {re.sub(r"_\d+$", "", part.lower()) for part in str(entry.get("uid") or "").split("/")}
    if "customizedfeaturemodel" not in segments or not len(faces):
        return ""
    tri = xyz[faces]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = np.linalg.norm(normal, axis=1)
    flat = np.abs(normal[:, 1]) > HORIZONTAL_FACE * np.maximum(area, 1e-300)
    if area.sum() > 0 and area[flat].sum() >= 0.5 * area.sum():
        return "CustomizedCeiling" if xyz[:, 1].min() > CEILING_FEATURE_Y else "CustomizedPlatform"
    return "CustomizedFeatureWall"


def title_names(title) -> list[str]:
    """The category names a ``super/sub`` title gives: the whole title when the table knows
    it (``Corner/Side Table``), else its super-category (``plants/plants - on top of others``
    → ``plants``)."""
    title = str(title or "").strip()
    if not title or _target(title) is not None or "/" not in title:
        return [title] if title else []
    return [title.split("/", 1)[0]]


def opening_rectangle(vertices, faces) -> np.ndarray | None:
    """(4, 3) float64 corners of the opening a jamb mesh frames, or None when it frames none.

    vertices : (n, 3) float  world coordinates; faces : (m, 3) int

    The wall's through axis is the horizontal principal axis of the vertices along which they
    spread least (an opening is wider than its wall is thick). The mesh is a jamb when its faces
    run through the wall: at most :data:`JAMB_FACING` of their area faces along that axis (a
    door leaf, a glazed window or a window frame face along it). The rectangle spans the
    vertices along the wall and in height, halfway through the wall (either side faces the
    rays: they see back faces too).
    """
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if not len(f):
        return None
    used = v[np.unique(f)]
    xz = used[:, [0, 2]] - used[:, [0, 2]].mean(axis=0)
    _, axes2 = np.linalg.eigh(xz.T @ xz)
    axes = [np.array([a[0], 0.0, a[1]]) for a in axes2.T]
    spread = [np.ptp(used @ a) for a in axes]
    along = axes[1] if spread[0] <= spread[1] else axes[0]
    # eigenvectors come with either sign: fix one, so that the corners do not depend on LAPACK
    along = along if (round(along[0], 9), round(along[2], 9)) > (0.0, 0.0) else -along
    through = np.array([-along[2], 0.0, along[0]])
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    area = np.linalg.norm(n, axis=1).sum()
    if area <= 0 or np.abs(n @ through).sum() > JAMB_FACING * area:
        return None
    s, y, t = used @ along, used[:, 1], used @ through
    if np.ptp(s) < SAME_OPENING or np.ptp(y) < SAME_OPENING:
        return None
    mid = (t.min() + t.max()) / 2
    corners = [(s.min(), y.min()), (s.max(), y.min()), (s.max(), y.max()), (s.min(), y.max())]
    return np.array([a * along + b * np.array([0.0, 1.0, 0.0]) + mid * through for a, b in corners])


def _future_dir(path: Path, options: LoadOptions) -> Path:
    if options.future_dir:
        return Path(options.future_dir)
    for cand in (path.parent.parent / MODEL_DIR, path.parent / MODEL_DIR):
        if cand.is_dir():
            return cand
    return path.parent.parent / MODEL_DIR


def _numbers(value, width: int) -> np.ndarray:
    """(k, width) float64 rows of a flat list of numbers or numeric strings; ValueError else."""
    try:
        return np.asarray(value if value is not None else [], dtype=np.float64).reshape(-1, width)
    except (TypeError, ValueError) as e:
        raise ValueError(f"not a flat list of {width}k numbers ({e})") from None


def _declared_extent(entry: dict) -> np.ndarray | None:
    """(3,) float64 the extent a furniture entry declares (``bbox``, else ``size``): three
    lengths, or two or eight corners; None when it declares none."""
    for key in ("bbox", "size"):
        try:
            a = np.asarray(entry.get(key), dtype=np.float64)
        except (TypeError, ValueError):
            continue
        if a.size == 3:
            a = np.abs(a.reshape(3))
        elif a.size in (6, 24):
            a = np.ptp(a.reshape(-1, 3), axis=0)
        else:
            continue
        if np.isfinite(a).all() and (a > 0).any():
            return a
    return None


def _size_agrees(extent: np.ndarray, declared: np.ndarray) -> bool:
    """True when ``extent`` matches ``declared`` within :data:`SIZE_LIMIT` on every axis the
    declaration makes longer than 1 cm."""
    axes = declared > 0.01
    with np.errstate(divide="ignore"):
        ratio = extent[axes] / declared[axes]
    return bool(axes.any() and (ratio <= SIZE_LIMIT).all() and (ratio >= 1 / SIZE_LIMIT).all())


@dataclass
class _Piece:
    """One instance to be: its geometry in world coordinates and what to call it."""

    name: str
    category: int
    label: str
    room_id: str | None
    vertices: np.ndarray
    faces: np.ndarray
    uv: np.ndarray | None
    material: Material | tuple[Material, ...] | None  # a tuple: face groups, see face_material
    file: Path
    group: tuple | None = None  # pieces with the same group become one instance
    face_material: np.ndarray | None = None  # (m,) int32 index into the material tuple


@dataclass
class _Opening:
    """A closing surface to be: the rectangle a jamb frames."""

    corners: np.ndarray  # (4, 3) float64
    kind: str | None  # "door", "window", or None (decided by the floor)
    label: str
    room_id: str | None
    material: Material | None
    name: str


class _Reader:
    """State of one scene being read: paths, tables, model cache, the pieces, the house."""

    def __init__(self, path: Path, options: LoadOptions):
        self.path = path
        self.strict = options.strict
        self.future = _future_dir(path, options)
        self.textures = path.parent.parent / TEXTURE_DIR
        self.house = House(id=path.stem, instances=[], rooms=[], source_format="front3d",
                           source_path=str(path))
        self.info: dict[str, tuple[str, str]] = {}
        self.pieces: list[_Piece] = []
        self.openings: list[_Opening] = []
        self._models: dict[str, Mesh | str] = {}  # jid → model, or BAD_MODEL
        self._materials: dict[str, tuple[Material, np.ndarray | None]] = {}

    def error(self, problem: str, file: Path | None = None) -> HouseError:
        return HouseError(self.house.id, file or self.path, problem)

    def skip(self, reason: str, warning: str | None = None) -> None:
        """Count one piece left out for ``reason``, with a warning saying which one."""
        if warning is not None:
            self.house.warnings.append(warning)
        self.house.count_loss(reason)

    # ---- the files ---------------------------------------------------------------------

    def read_doc(self) -> dict:
        try:
            doc = json.loads(self.path.read_text(encoding="utf-8"))
        except (OSError, ValueError) as e:
            raise self.error(f"cannot read scene JSON: {e}") from None
        scene = doc.get("scene") if isinstance(doc, dict) else None
        if not (isinstance(scene, dict) and isinstance(scene.get("room"), list)):
            raise self.error("not a 3D-FRONT scene: no 'scene.room' list")
        return doc

    def index(self, doc: dict, key: str, count_duplicates: bool = True) -> dict:
        """The entries of ``doc[key]`` by uid (the last of a duplicated uid)."""
        out: dict = {}
        for entry in doc.get(key) or []:
            if isinstance(entry, dict):
                if count_duplicates and entry.get("uid") in out:
                    self.house.count_loss(DUPLICATE)
                out[entry.get("uid")] = entry
        return out

    def read_models(self) -> None:
        """Check the 3D-FUTURE folder and read its ``model_info.json``."""
        if not self.future.is_dir():
            raise self.error("3D-FUTURE model folder not found (pass --future-dir)", self.future)
        nested = self.future / MODEL_DIR
        if nested.is_dir():
            raise self.error(f"3D-FUTURE models are one folder too deep: expected {self.future}/<jid>/"
                             f"raw_model.obj and {self.future / MODEL_INFO}, found the folder {nested} "
                             f"(pass --future-dir {nested}, or move its content up)", nested)
        info_path = self.future / MODEL_INFO
        if not info_path.is_file():
            elsewhere = [p for p in (self.future.parent / MODEL_INFO, self.path.parent / MODEL_INFO) if p.is_file()]
            hint = f" (found {elsewhere[0]}: move it there)" if elsewhere else ""
            raise self.error(f"3D-FUTURE model info not found: expected {info_path}{hint}", info_path)
        try:
            entries = json.loads(info_path.read_text(encoding="utf-8"))
            self.info = {str(m["model_id"]): (m.get("category") or "", m.get("super-category") or "")
                         for m in entries if isinstance(m, dict)}
        except (OSError, ValueError, KeyError, TypeError, AttributeError) as e:
            raise self.error(f"cannot read 3D-FUTURE model info: {e}", info_path) from None

    def model(self, jid: str) -> Mesh | str:
        """The 3D-FUTURE model ``jid`` (its texture.png as texture), or :data:`BAD_MODEL` when
        its file cannot be read (the first time, with a warning naming the file)."""
        if jid not in self._models:
            file = self.future / jid / "raw_model.obj"
            try:
                mesh = read_obj(file)
            except (OSError, ValueError) as e:
                self.house.warnings.append(f"furniture model {jid}: cannot read {file}: {e}; its pieces skipped")
                self._models[jid] = BAD_MODEL
                return BAD_MODEL
            texture = file.parent / "texture.png"
            if texture.is_file():
                textured = tuple(replace(m, texture=texture) for m in mesh.materials)
                mesh = replace(mesh, material=textured if mesh.face_material is not None else textured[0])
            self._models[jid] = mesh
        return self._models[jid]

    def material(self, entry: dict | None) -> tuple[Material, np.ndarray | None]:
        """A mesh material (``color``: RGB or RGBA, 0–255; its texture) and the (2, 2) matrix
        its ``UVTransform`` applies to uv (None: identity)."""
        if not isinstance(entry, dict):
            return Material(), None
        uid = str(entry.get("uid"))
        if uid in self._materials:
            return self._materials[uid]
        try:
            c = np.asarray(entry.get("color") or [], dtype=np.float64).reshape(-1)
        except (TypeError, ValueError):
            c = np.empty(0)
        base = Material().base_color
        if 3 <= len(c) <= 4 and np.isfinite(c).all():
            base = tuple(float(x) for x in np.clip(np.append(c / 255, 1.0)[:4], 0, 1))
        url = str(entry.get("texture") or "").rstrip("/")
        folders = [str(entry.get("jid") or ""), url.split("/")[-2] if "/" in url else ""]
        found = [self.textures / d / "texture.png" for d in folders if d and d not in (".", "..")]
        texture = next((p for p in found if p.is_file()), None)
        if texture is None and (url or entry.get("colorMode") == "texture"):
            self.house.count_loss(NO_TEXTURE)
        transform = None
        if entry.get("UVTransform") is not None:
            try:
                m = np.asarray(entry["UVTransform"], dtype=np.float64).reshape(3, 3)[:2, :2]
                transform = m if np.isfinite(m).all() else None
            except (TypeError, ValueError):
                transform = None
            if transform is None:
                self.house.warnings.append(f"material {uid!r}: UVTransform is not 9 numbers, ignored")
        self._materials[uid] = Material(base_color=base, texture=texture), transform
        return self._materials[uid]

    # ---- pieces ------------------------------------------------------------------------

    def matrix(self, child: dict) -> np.ndarray | None:
        """Child placement ``pos + R(rot) · (scale ⊙ v)`` as a 4×4, or None (with a warning)."""
        try:
            pos = np.asarray(child.get("pos", [0, 0, 0]), dtype=np.float64)
            rot = np.asarray(child.get("rot", [0, 0, 0, 1]), dtype=np.float64)
            scale = np.asarray(child.get("scale", [1, 1, 1]), dtype=np.float64)
            ok = pos.shape == (3,) and rot.shape == (4,) and scale.shape == (3,)
            ok = ok and all(np.isfinite(a).all() for a in (pos, rot, scale)) and np.linalg.norm(rot) > 0
        except (TypeError, ValueError):
            ok = False
        if not ok:
            self.skip(BAD_PIECE, f"child {child.get('instanceid', child.get('ref'))!r}: pos/rot/scale must be "
                      "3, 4 (a non-zero quaternion x, y, z, w) and 3 finite numbers; skipped")
            return None
        m = np.eye(4)
        m[:3, :3] = quaternion_matrix(rot) * scale
        m[:3, 3] = pos
        return m

    def category(self, names, what: str) -> tuple[str, int] | None:
        """(label, NYU40 id) of a piece, or None when it is dropped (counted)."""
        label, cid, dropped = lookup(names)
        if dropped:
            self.house.count_loss(DROPPED)
            return None
        return label, resolve(self.house, label or f"{what} without a category", cid,
                              strict=self.strict, file=self.path)

    def furniture(self, entry: dict, child: dict, room_id: str | None) -> None:
        if entry.get("valid") is not True:
            self.house.count_loss(UNRELEASED)
            return
        jid = str(entry.get("jid") or "")
        if not (self.future / jid / "raw_model.obj").is_file():  # before its category, like validity
            self.house.count_loss(NO_MODEL)
            return
        fine, coarse = self.info.get(jid, ("", ""))
        cat = self.category([fine, *title_names(entry.get("title")), entry.get("category"), coarse], "furniture")
        if cat is None:
            return
        mesh = self.model(jid)
        if isinstance(mesh, str):
            self.house.count_loss(mesh)
            return
        m = self.matrix(child)
        if m is None:
            return
        self.flag_scale(entry, np.abs(np.linalg.norm(m[:3, :3], axis=0)), mesh)
        label, cid = cat
        v, f = place(mesh.vertices, mesh.faces, m)
        self.pieces.append(_Piece(f"{label or 'furniture'}#{child.get('instanceid', entry.get('uid'))}", cid,
                                  label, room_id, v, f, mesh.uv, mesh.material, self.future / jid / "raw_model.obj",
                                  face_material=mesh.face_material))

    def flag_scale(self, entry: dict, scale: np.ndarray, mesh: Mesh) -> None:
        """Count a piece whose scale or model size looks wrong (the piece is kept)."""
        if (scale > SCALE_LIMIT).any() or (scale < 1 / SCALE_LIMIT).any():
            self.house.count_loss(SCALE_FLAG)
        declared = _declared_extent(entry)
        if declared is not None and len(mesh.vertices):
            raw = np.ptp(mesh.vertices, axis=0)
            if not any(_size_agrees(e * unit, declared) for e in (raw, raw * scale) for unit in (1, 100)):
                self.house.count_loss(SIZE_FLAG)

    def mesh(self, entry: dict, child: dict, room_id: str | None, materials: dict,
             construct_types: dict[str, str] | None = None) -> None:
        kind_name = str(entry.get("type") or "").strip()
        kind = _key(kind_name)
        uid = entry.get("uid")
        if kind in EXTERIOR_TYPES:
            self.house.count_loss(EXTERIOR)
            return
        try:
            xyz, faces = _numbers(entry.get("xyz"), 3), _numbers(entry.get("faces"), 3).astype(np.int64)
        except ValueError as e:
            self.skip(BAD_PIECE, f"mesh {uid!r}: 'xyz' and 'faces' must be flat lists of 3k numbers: {e}; skipped")
            return
        if not len(faces):
            return  # nothing to see, nothing lost: no category is looked up
        if not kind_name:
            valid = faces.min() >= 0 and faces.max() < len(xyz)
            kind_name = untyped_kind(entry, xyz, faces, construct_types or {}) if valid else ""
            if kind_name:
                self.house.count_loss(UNTYPED)
        cat = self.category([kind_name], "mesh")
        if cat is None:
            return
        m = self.matrix(child)
        if m is None:
            return
        label, cid = cat
        material, transform = self.material(materials.get(entry.get("material")))
        try:
            uv = _numbers(entry.get("uv"), 2) if entry.get("uv") else None
        except ValueError:
            uv = None
        if uv is not None and (len(uv) != len(xyz) or not np.isfinite(uv).all()):
            uv = None
        if uv is not None and transform is not None:
            uv = uv @ transform.T
        v, f = place(xyz, faces, m)
        name = f"{label or 'mesh'}#{child.get('instanceid', uid)}"
        construct = entry.get("constructid")
        group = (room_id, str(construct), cid, label) if construct and not is_envelope(cid, label) else None
        self.pieces.append(_Piece(name, cid, label, room_id, v, f, uv, material, self.path, group))
        if kind in OPENING_TYPES:
            corners = opening_rectangle(v, f)
            if corners is not None:
                self.openings.append(_Opening(corners, OPENING_TYPES[kind], label, room_id, material, name))

    # ---- instances ---------------------------------------------------------------------

    def finish(self) -> House:
        """Make the instances: pieces (groups merged, in order of their first piece), then the
        closing surfaces of the openings."""
        merged: list[_Piece] = []
        groups: dict[tuple, list[_Piece]] = {}
        for piece in self.pieces:
            if piece.group is None:
                merged.append(piece)
            elif piece.group in groups:
                groups[piece.group].append(piece)
            else:
                groups[piece.group] = [piece]
                merged.append(piece)
        for piece in merged:
            if piece.group is not None and len(groups[piece.group]) > 1:
                piece = _merge(groups[piece.group])
            try:
                make_instance(self.house, name=piece.name, category=piece.category, label=piece.label,
                              room_id=piece.room_id, vertices=piece.vertices, faces=piece.faces, uv=piece.uv,
                              file=piece.file, material=piece.material, face_material=piece.face_material)
            except HouseError as e:
                self.skip(BAD_PIECE, f"{e.problem}; skipped")
        self.close_openings()
        if not self.house.instances and self.house.warnings:
            raise self.error(f"house is empty (no instance with geometry): {'; '.join(self.house.warnings)}")
        return self.house.check_not_empty()

    def close_openings(self) -> None:
        floors: dict[str | None, float] = {}
        for inst in self.house.instances:
            if inst.category == NYU40_IDS["floor"]:
                y = float(inst.vertices[:, 1].min())
                floors[inst.room_id] = min(y, floors.get(inst.room_id, y))
        house_floor = min(floors.values(), default=0.0)
        kept: list[int] = []
        # a Door/Window names its opening better than a Hole/Pocket on the same one
        for k in sorted(range(len(self.openings)), key=lambda k: self.openings[k].kind is None):
            corners = self.openings[k].corners
            if not any(np.abs(corners - self.openings[j].corners).max() <= SAME_OPENING for j in kept):
                kept.append(k)
        for op in (self.openings[k] for k in sorted(kept)):
            kind = op.kind
            if kind is None:
                sill = op.corners[:, 1].min() - floors.get(op.room_id, house_floor)
                kind = "door" if sill <= DOOR_SILL else "window"
            make_instance(self.house, name=f"{kind} opening of {op.name}", category=NYU40_IDS[kind],
                          label=f"{op.label} opening", room_id=op.room_id, vertices=op.corners,
                          faces=[[0, 1, 2], [0, 2, 3]], file=self.path, material=op.material)


def _merge(pieces: list[_Piece]) -> _Piece:
    """One piece of several (same room, construct and class), each piece's materials its
    face groups."""
    offsets = np.cumsum([0] + [len(p.vertices) for p in pieces[:-1]])
    materials, face_material = [], []

    def own_of(p: _Piece) -> tuple[Material, ...]:
        return p.material if isinstance(p.material, tuple) else (p.material or Material(),)

    for p in pieces:
        own = own_of(p)
        index = p.face_material if p.face_material is not None else np.zeros(len(p.faces), np.int32)
        face_material.append(index + len(materials))
        materials += own
    first = pieces[0]
    # uv when any piece has them (the others' corners (0, 0), their textures dropped: nothing
    # places them), so that one piece without uv does not take the others' textures (issue 40)
    uv = None
    if any(p.uv is not None for p in pieces):
        uv = np.concatenate([p.uv if p.uv is not None else np.zeros((len(p.vertices), 2)) for p in pieces])
        materials = [replace(m, texture=None) if m.texture is not None and pieces[k].uv is None else m
                     for k, m in zip(np.repeat(np.arange(len(pieces)), [len(own_of(p)) for p in pieces]),
                                     materials, strict=True)]
    return replace(first, name=f"{first.label or 'mesh'}#{first.group[1]}",
                   vertices=np.concatenate([p.vertices for p in pieces]),
                   faces=np.concatenate([p.faces + o for p, o in zip(pieces, offsets)]), uv=uv,
                   material=tuple(materials), face_material=np.concatenate(face_material).astype(np.int32))


def load_house(path: Path, options: LoadOptions) -> House:
    """Read one 3D-FRONT scene JSON (its furniture from the 3D-FUTURE model folder)."""
    r = _Reader(Path(path), options)
    doc = r.read_doc()
    furniture = r.index(doc, "furniture")
    meshes = r.index(doc, "mesh")
    materials = r.index(doc, "material", count_duplicates=False)
    rooms = [room for room in doc["scene"]["room"] if isinstance(room, dict)]
    children = [c for room in rooms for c in room.get("children") or [] if isinstance(c, dict)]
    if any(furniture.get(c.get("ref"), {}).get("valid") is True for c in children):
        r.read_models()
    construct_types: dict[str, str] = {}
    for entry in meshes.values():
        construct, kind = str(entry.get("constructid") or ""), str(entry.get("type") or "").strip()
        if construct and kind:
            construct_types.setdefault(construct, kind)
    for room in rooms:
        # the writer's convention for pieces outside any room: a room without an instanceid
        room_id = str(room.get("instanceid") or "") or None
        if room_id is not None:
            r.house.rooms.append(Room(room_id, str(room.get("type") or ""), 0))
        for child in room.get("children") or []:
            ref = child.get("ref") if isinstance(child, dict) else None
            if ref in furniture:
                r.furniture(furniture[ref], child, room_id)
            elif ref in meshes:
                r.mesh(meshes[ref], child, room_id, materials, construct_types)
            else:
                r.house.count_loss(DANGLING)
    return r.finish()


def _load(source: HouseSource, options: LoadOptions) -> House:
    return load_house(source.path, options)


FORMAT = Format(
    "front3d", detect=detect, list=list_houses, load=_load,
    # scene files vary: inside a root, or when 3D-FRONT is asked for, any other JSON is one
    fallback=lambda path: path.suffix.lower() == ".json" and not path.is_dir(),
)
