"""Config dataclasses → JSON in and out, JSON Schemas and command-line options; and the
configuration of a ``sceneforge render`` run.

Every config of sceneforge is a frozen dataclass with a ``#:`` doc above each field, next
to the code it steers. This module is the one machinery they all go through:

- :func:`dataclass_to_dict` / :func:`dataclass_from_dict`: JSON-ready data and back;
- :func:`object_schema`: the JSON Schema of a dataclass (types, defaults, the ``#:`` docs
  as descriptions, unknown keys rejected); :data:`SCHEMAS` names the root configs whose
  schemas live in ``schemas/`` (a test checks the files against them; regenerate them
  with ``python -m sceneforge.config``);
- :func:`resolve_config`: defaults < a JSON config file < command-line overrides, validated
  against the root's schema;
- :func:`field_docs`, :func:`field_default`, :func:`field_type`: what ``sceneforge.cli``
  builds every option's help, shown default and type from, so they exist once.

:class:`DatasetConfig` composes the configs of a render run
(:class:`~sceneforge.houses.LoadOptions`, :class:`~sceneforge.camera_sampler.CameraSamplerConfig`,
:class:`~sceneforge.view.ViewConfig`, :class:`~sceneforge.render.RenderConfig`) with the
RGB switches and store settings defined here. A run resolves it once, validates it against
``schemas/config.schema.json`` and saves it, resolved, into the store it writes; the saved
dict loads back into the same config with :meth:`DatasetConfig.from_dict`.

The image size is set once, by :attr:`DatasetConfig.width` and :attr:`DatasetConfig.height`;
the camera sampler's own ``width``/``height`` follow them and are not part of the file.
"""

from __future__ import annotations

import importlib
import inspect
import json
import re
import types
import typing
from dataclasses import MISSING, dataclass, field, fields, is_dataclass, replace
from functools import lru_cache
from pathlib import Path

from .camera_sampler import CameraSamplerConfig
from .errors import SceneforgeError
from .houses import LoadOptions
from .render import RenderConfig
from .view import ViewConfig

#: Fields of a sub-config that a config file does not set (they follow another field).
_DERIVED: dict[type, frozenset[str]] = {CameraSamplerConfig: frozenset({"width", "height"}),
                                        ViewConfig: frozenset({"with_mesh"})}

#: Keys earlier versions of the render config had, by dotted name, and what replaced them.
#: A config a store recorded drops them (its arrays were made already); a config file a user
#: gives that still sets one is an error saying what to set instead.
RETIRED: dict[str, str] = {
    "rgb.lighting.light": "lights are physical now: set rgb.lighting.lamp_power (lumens), "
                          "and rgb.lighting.exposure for a fixed exposure",
    "rgb.lighting.window_light": "windows are sky panels now: set rgb.lighting.sky_luminance (cd/m²)",
    "view.with_mesh": "whether the store keeps the ground-truth meshes is store.gt_mesh now: \"all\" or \"none\"",
}
#: Retired keys whose value a recorded config carries over to the key that replaced them:
#: dotted name → (new dotted name, the new value from the old).
CARRIED: dict[str, tuple[str, typing.Callable]] = {
    "view.with_mesh": ("store.gt_mesh", lambda with_mesh: "all" if with_mesh else "none"),
}


@dataclass(frozen=True)
class RGBConfig:
    """How RGB images are rendered: rasterised (pyrender, EGL) or path-traced (Mitsuba 3)."""

    #: render RGB images; without them the store has no ``rgb`` array
    enabled: bool = True
    #: how RGB images are made: ``raster`` (pyrender through EGL, per-pixel lights, fast) or
    #: ``pathtraced`` (Mitsuba 3, global illumination, seconds per view); the store's saved
    #: config records it
    mode: typing.Literal["raster", "pathtraced"] = "raster"
    #: raster only: multisample antialiasing (off: every pixel shows the surface its centre
    #: sees, like the layers)
    antialias: bool = False
    #: pathtraced only: samples per pixel (fixed, with a fixed seed: the same view gives the same image)
    samples: int = 64
    #: pathtraced only: denoise each frame with Intel Open Image Denoise guided by the path
    #: tracer's albedo and normals (pyoidn; deterministic)
    denoise: bool = True
    #: lights and background
    lighting: RenderConfig = field(default_factory=RenderConfig)

    def __post_init__(self):
        if self.samples < 1:
            raise ValueError(f"samples must be at least 1, got {self.samples}")


@dataclass(frozen=True)
class StoreConfig:
    """How the zarr store is laid out on disk."""

    #: views per shard file: every per-view array keeps one view per chunk and this many per shard
    views_per_shard: int = 4
    #: how arrays are compressed: "blosc-zstd-per-array" (Blosc, then zstd; each array's shuffle
    #: and one Blosc block per chunk chosen by measurement, benchmarks/bench_store_bytes.py),
    #: "blosc-zstd" (Blosc byte-shuffles every array alike, Blosc's own blocks, then zstd: the
    #: stores written before per-array codecs) or "zstd" (plain zstd, for readers without Blosc);
    #: all zarr v3 core codecs, and the arrays' values are the same with any of them
    codec: typing.Literal["blosc-zstd-per-array", "blosc-zstd", "zstd"] = "blosc-zstd-per-array"
    #: compression level of every array (1 fastest; 9 smallest with Blosc, 22 with plain zstd)
    compression_level: int = 3
    #: also store the first-hit normals (N, 3, H, W) float32, camera frame (docs/spec.md §4.6)
    normals: bool = False
    #: the views whose ground-truth meshes (docs/spec.md §5, what only `evaluate` reads) the store keeps:
    #: "none" (evaluate makes them from the houses the store records for the views it scores, and
    #: caches them beside the store) or "all"
    gt_mesh: typing.Literal["all", "none"] = "none"

    def __post_init__(self):
        if self.views_per_shard < 1:
            raise ValueError(f"views_per_shard must be at least 1, got {self.views_per_shard}")
        top = 22 if self.codec == "zstd" else 9
        if not 1 <= self.compression_level <= top:
            raise ValueError(f"compression_level must be in 1..{top} for codec {self.codec}, "
                             f"got {self.compression_level}")


@dataclass(frozen=True)
class DatasetConfig:
    """Everything that decides what ``sceneforge render`` writes (not how fast: workers and
    the Dask scheduler are run options, so stores written with any of them are identical)."""

    #: the fields naming files, made absolute when the config is resolved (:func:`absolute_paths`)
    PATHS: typing.ClassVar[tuple[str, ...]] = ("cameras", "houses.name_map", "houses.future_dir")

    #: frontal image width, pixels
    width: int = 320
    #: frontal image height, pixels
    height: int = 240
    #: cameras sampled per house (when ``cameras`` is not set); a house may get fewer
    views_per_house: int = 4
    #: folder of PBRS camera files ``<cameras>/<house id>/room_camera.txt``, every line used
    #: in order; None = sample ``views_per_house`` cameras per house
    cameras: str | None = None
    #: seed of the camera sampler; a house's cameras depend only on it and the house id
    seed: int = 0
    #: how houses are read
    houses: LoadOptions = field(default_factory=LoadOptions)
    #: how cameras are sampled
    sampler: CameraSamplerConfig = field(default_factory=CameraSamplerConfig)
    #: the ground truth computed per view (overhead camera, overhead truth, mesh)
    view: ViewConfig = field(default_factory=ViewConfig)
    #: RGB rendering
    rgb: RGBConfig = field(default_factory=RGBConfig)
    #: store layout
    store: StoreConfig = field(default_factory=StoreConfig)

    def __post_init__(self):
        if self.width < 1 or self.height < 1:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")
        if self.views_per_house < 1:
            raise ValueError(f"views_per_house must be at least 1, got {self.views_per_house}")
        if (self.sampler.width, self.sampler.height) != (self.width, self.height):
            object.__setattr__(self, "sampler", replace(self.sampler, width=self.width, height=self.height))
        with_mesh = self.store.gt_mesh == "all"
        if self.view.with_mesh != with_mesh:  # a view's mesh is computed when the store keeps it
            object.__setattr__(self, "view", replace(self.view, with_mesh=with_mesh))

    def to_dict(self) -> dict:
        """The resolved config as JSON-ready data (what the store saves)."""
        return dataclass_to_dict(self)

    @classmethod
    def from_dict(cls, data: dict, *, what: str = "config", recorded: bool = False) -> "DatasetConfig":
        """Validate ``data`` against the config schema and build the config. ``recorded``:
        ``data`` is the config a store was written with, whose :data:`RETIRED` keys are dropped.

        Raises :class:`SceneforgeError` naming ``what`` and the problem.
        """
        return build_config(cls, _retire(data, what, drop=recorded), schema="config", what=what)


def _retire(data: dict, what: str, *, drop: bool) -> dict:
    """``data`` without its :data:`RETIRED` keys (``drop``; the value of a :data:`CARRIED`
    one moves to its new key), or a SceneforgeError naming the first."""
    out = dict(data)
    for dotted, instead in RETIRED.items():
        *parents, key = dotted.split(".")
        node = _node(out, parents)
        if node is not None and key in node:
            if not drop:
                raise SceneforgeError(f"{what}: '{dotted}' was removed: {instead}")
            value = node.pop(key)
            if dotted in CARRIED:
                new, convert = CARRIED[dotted]
                *new_parents, new_key = new.split(".")
                _node(out, new_parents, create=True)[new_key] = convert(value)
    return out


def _node(data: dict, parents: list[str], create: bool = False) -> dict | None:
    """The dict at ``parents`` in ``data``, each level copied (so ``data``'s caller keeps its
    own); None when a level is missing (created empty with ``create``)."""
    node = data
    for parent in parents:
        if not isinstance(node.get(parent), dict):
            if not create:
                return None
            node[parent] = {}
        node[parent] = dict(node[parent])
        node = node[parent]
    return node


def load_config(path: str | Path | None = None, overrides: dict | None = None) -> DatasetConfig:
    """Defaults, updated by the JSON config file at ``path``, updated by ``overrides``.

    ``overrides`` is nested like the file (``{"view": {"overhead": {"resolution": 64}}}``).
    Raises :class:`SceneforgeError` for an unreadable file or an invalid config.
    """
    return resolve_config(DatasetConfig, path, overrides)


# ----------------------------------------------------------------------------- resolving

#: schema name → its root config dataclass ("module:attribute", imported when needed) and
#: title; each is written to ``schemas/<name>.schema.json``
SCHEMAS: dict[str, tuple[str, str]] = {
    "config": ("sceneforge.config:DatasetConfig", "sceneforge render config"),
    "train": ("sceneforge.learn.config:TrainConfig", "sceneforge train config"),
    "predict": ("sceneforge.learn.config:PredictConfig", "sceneforge predict config"),
    "evaluate": ("sceneforge.evaluate.config:EvaluateConfig", "sceneforge evaluate config"),
}


def root_config(name: str) -> type:
    """The root config dataclass of schema ``name``."""
    module, attr = SCHEMAS[name][0].split(":")
    return getattr(importlib.import_module(module), attr)


def schema_of(cls: type) -> str:
    """The name of the schema (in :data:`SCHEMAS`) whose root config is ``cls``."""
    for name, (target, _) in SCHEMAS.items():
        if target == f"{cls.__module__}:{cls.__qualname__}":
            return name
    raise KeyError(f"{cls.__qualname__} is the root of no schema in SCHEMAS")


def build_config(cls, data: dict, *, schema: str, what: str):
    """``data`` validated against ``schemas/<schema>.schema.json``, as the config ``cls``.

    Raises :class:`SceneforgeError` naming ``what`` and the problem: an unknown key (by its
    dotted name), a value of the wrong type, or a value the dataclass rejects.
    """
    from sceneforge import schemas

    schemas.validate_or_raise(data, schema, what=what)
    try:
        return dataclass_from_dict(cls, data)
    except (TypeError, ValueError) as e:
        raise SceneforgeError(f"{what}: {e}") from None


def read_config_file(path: str | Path) -> dict:
    """The JSON object in the config file ``path`` (not yet validated)."""
    try:
        data = json.loads(Path(path).read_text())
    except OSError as e:
        raise SceneforgeError(f"{path}: cannot read config ({e.strerror or e})") from None
    except ValueError as e:
        raise SceneforgeError(f"{path}: not valid JSON ({e})") from None
    if not isinstance(data, dict):
        raise SceneforgeError(f"{path}: a config file holds one JSON object")
    return data


def resolve_config(cls, path: str | Path | None = None, overrides: dict | None = None):
    """The root config ``cls`` (a class of :data:`SCHEMAS`): its defaults, updated by the
    JSON file at ``path``, updated by ``overrides`` (nested like the file), validated.

    Raises :class:`SceneforgeError` for an unreadable file or an invalid config.
    """
    data = {} if path is None else read_config_file(path)
    what = "config" if path is None else str(path)
    return cls.from_dict(absolute_paths(cls, _merge(data, overrides or {})), what=what)


def absolute_paths(cls, data: dict) -> dict:
    """``data`` with the values of ``cls.PATHS`` (dotted names of the fields that name a file
    or folder) made absolute against the working folder, URLs left as they are: the config
    a store or a run saves names its files from any folder (``evaluate``, ``--update``,
    ``overhead-camera`` run elsewhere)."""
    out = data
    for dotted in getattr(cls, "PATHS", ()):
        *parents, key = dotted.split(".")
        node = out
        for parent in parents:
            node = node.get(parent) if isinstance(node, dict) else None
        value = node.get(key) if isinstance(node, dict) else None
        if isinstance(value, str) and value and not re.match(r"^[a-zA-Z][a-zA-Z0-9+.-]*://", value):
            out = _merge(out, _nested(dotted, str(Path(value).expanduser().resolve())))
    return out


def _nested(dotted: str, value) -> dict:
    """``{"a": {"b": value}}`` for ``"a.b"``."""
    for key in reversed(dotted.split(".")):
        value = {key: value}
    return value


def _merge(base: dict, update: dict) -> dict:
    out = dict(base)
    for key, value in update.items():
        out[key] = _merge(out.get(key) or {}, value) if isinstance(value, dict) else value
    return out


def dataclass_to_dict(obj) -> dict:
    """A (nested) config dataclass as plain JSON-ready data, derived fields left out."""
    skip = _DERIVED.get(type(obj), frozenset())
    out = {}
    for f in fields(obj):
        if f.name in skip:
            continue
        value = getattr(obj, f.name)
        if is_dataclass(value):
            out[f.name] = dataclass_to_dict(value)
        elif isinstance(value, tuple):
            out[f.name] = list(value)
        else:
            out[f.name] = value
    return out


def dataclass_from_dict(cls, data: dict):
    """The config dataclass ``cls`` built from :func:`dataclass_to_dict` output (nested)."""
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for f in fields(cls):
        if f.name not in data:
            continue
        kwargs[f.name] = _coerce(hints[f.name], data[f.name])
    return cls(**kwargs)


def _coerce(hint, value):
    """``value`` (schema-valid JSON) as the Python type ``hint``: JSON Schema counts 2.0 as an
    integer and 2 as a number, the dataclasses expect int and float."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if value is None:
        return None
    if is_dataclass(hint):
        return dataclass_from_dict(hint, value)
    if origin in (typing.Union, types.UnionType):
        return _coerce(_optional_inner(hint), value)
    if origin is tuple:
        item = args[0]
        return tuple(_coerce(args[i] if args[-1] is not Ellipsis else item, v) for i, v in enumerate(value))
    if hint in (int, float):
        return hint(value)
    return value


def _optional_inner(hint):
    """``X`` of ``X | None`` (the only unions configs use)."""
    (inner,) = [a for a in typing.get_args(hint) if a is not type(None)]
    return inner


# ----------------------------------------------------------------------------- fields

@lru_cache(maxsize=None)
def field_docs(cls) -> dict[str, str]:
    """The ``#:`` comments written above each field of a dataclass, by field name."""
    docs, pending = {}, []
    for line in inspect.getsource(cls).splitlines():
        stripped = line.strip()
        if stripped.startswith("#:"):
            pending.append(stripped[2:].strip())
            continue
        match = re.match(r"(\w+)\s*:", stripped)
        if match and pending:
            docs[match.group(1)] = " ".join(pending)
        pending = []
    return docs


def _field_path(cls, path: str) -> list[tuple[type, "typing.Any"]]:
    """(dataclass, field) for each step of the dotted ``path`` from ``cls``."""
    steps = []
    for name in path.split("."):
        match = [f for f in fields(cls) if f.name == name]
        if not match:
            raise KeyError(f"{cls.__qualname__} has no field {name!r} (in {path!r})")
        steps.append((cls, match[0]))
        cls = typing.get_type_hints(cls)[name]
    return steps


def field_type(cls, path: str):
    """The type hint of the field at the dotted ``path`` (``"view.overhead.resolution"``)."""
    owner, f = _field_path(cls, path)[-1]
    return typing.get_type_hints(owner)[f.name]


def field_doc(cls, path: str) -> str | None:
    """The ``#:`` doc of the field at the dotted ``path``."""
    owner, f = _field_path(cls, path)[-1]
    return field_docs(owner).get(f.name)


def field_default(cls, path: str):
    """The default of the field at the dotted ``path``: the value a config has there when
    neither a file nor an option sets it (``MISSING`` for a required field). Nested
    defaults are read from the instance their parent's factory makes."""
    steps = _field_path(cls, path)
    _, first = steps[0]
    value = first.default if first.default_factory is MISSING else first.default_factory()
    for _, f in steps[1:]:
        value = getattr(value, f.name)
    return value


# ----------------------------------------------------------------------------- schema

_JSON_TYPES = {bool: "boolean", int: "integer", float: "number", str: "string"}


def _type_schema(hint) -> dict:
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if is_dataclass(hint):
        return object_schema(hint)
    if origin is typing.Literal:
        return {"type": _JSON_TYPES[type(args[0])], "enum": list(args)}
    if origin in (typing.Union, types.UnionType):
        schema = _type_schema(_optional_inner(hint))
        schema["type"] = [schema["type"], "null"]
        if "enum" in schema:
            schema["enum"] = [*schema["enum"], None]
        return schema
    if origin is tuple:
        if len(args) == 2 and args[1] is Ellipsis:
            return {"type": "array", "items": _type_schema(args[0])}
        return {"type": "array", "items": _type_schema(args[0]), "minItems": len(args), "maxItems": len(args)}
    return {"type": _JSON_TYPES[hint]}


def object_schema(cls) -> dict:
    """The JSON Schema of the config dataclass ``cls`` (nested dataclasses inline)."""
    hints = typing.get_type_hints(cls)
    docs = field_docs(cls)
    skip = _DERIVED.get(cls, frozenset())
    props, required = {}, []
    for f in fields(cls):
        if f.name in skip:
            continue
        prop = _type_schema(hints[f.name])
        if f.name in docs:
            prop = {"description": docs[f.name], **prop}
        if f.default is not MISSING and not is_dataclass(f.default):
            prop["default"] = list(f.default) if isinstance(f.default, tuple) else f.default
        elif f.default is MISSING and f.default_factory is MISSING:
            required.append(f.name)
        props[f.name] = prop
    schema = {"type": "object", "description": inspect.getdoc(cls).split("\n\n")[0].replace("\n", " "),
              "properties": props}
    if required:
        schema["required"] = required
    return {**schema, "additionalProperties": False}


def schema(name: str) -> dict:
    """The JSON Schema ``schemas/<name>.schema.json``, generated from its root config."""
    title = SCHEMAS[name][1]
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "$id": f"https://sceneforge.invalid/schemas/{name}.schema.json",
        "title": title,
        **object_schema(root_config(name)),
    }


def config_schema() -> dict:
    """The JSON Schema of a render config file (and of the config saved in a store)."""
    return schema("config")


def write_schemas(folder: str | Path | None = None) -> list[Path]:
    """Write every schema of :data:`SCHEMAS` into ``folder`` (default: the installed
    ``schemas/``); the paths written."""
    from sceneforge import schemas

    folder = Path(folder or Path(schemas.__file__).parent)
    paths = []
    for name in SCHEMAS:
        path = folder / f"{name}.schema.json"
        path.write_text(json.dumps(schema(name), indent=2, ensure_ascii=False) + "\n")
        paths.append(path)
    return paths


if __name__ == "__main__":
    for written in write_schemas():
        print(written)
