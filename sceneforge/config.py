"""The configuration of a ``sceneforge render`` run: frozen dataclasses, JSON in and out.

:class:`DatasetConfig` composes the configs that sit next to the code they steer
(:class:`~sceneforge.houses.LoadOptions`, :class:`~sceneforge.cameras.CameraSamplerConfig`,
:class:`~sceneforge.view.ViewConfig`, :class:`~sceneforge.render.RenderConfig`) with the
RGB switches and store settings defined here. A run
resolves it once (defaults < config file < command-line overrides), validates it against
``schemas/config.schema.json`` and saves it, resolved, into the store it writes; the saved
dict loads back into the same config with :meth:`DatasetConfig.from_dict`.

The JSON Schema is generated from these dataclasses (:func:`config_schema`: field types,
defaults and the ``#:`` field docs), so the two cannot drift; a test checks the file in
``schemas/`` against it. Regenerate it with ``python -m sceneforge.config``.

The image size is set once, by :attr:`DatasetConfig.width` and :attr:`DatasetConfig.height`;
the camera sampler's own ``width``/``height`` follow them and are not part of the file.
"""

from __future__ import annotations

import inspect
import json
import re
import types
import typing
from dataclasses import MISSING, dataclass, field, fields, is_dataclass, replace
from pathlib import Path

from .cameras import CameraSamplerConfig
from .errors import SceneforgeError
from .houses import LoadOptions
from .render import RenderConfig
from .view import ViewConfig

#: Fields of a sub-config that a config file does not set (they follow another field).
_DERIVED: dict[type, frozenset[str]] = {CameraSamplerConfig: frozenset({"width", "height"})}


@dataclass(frozen=True)
class RGBConfig:
    """How RGB images are rendered (pyrender offscreen, EGL)."""

    #: render RGB images; without them the store has no ``rgb`` array
    enabled: bool = True
    #: multisample antialiasing (off: every pixel shows the surface its centre sees, like the layers)
    antialias: bool = False
    #: lighting and background
    lighting: RenderConfig = field(default_factory=RenderConfig)


@dataclass(frozen=True)
class StoreConfig:
    """How the zarr store is laid out on disk."""

    #: views per shard file: every per-view array keeps one view per chunk and this many per shard
    views_per_shard: int = 4
    #: zstd compression level of every array (1 fastest .. 22 smallest)
    compression_level: int = 3
    #: also store the first-hit normals (N, 3, H, W) float32, camera frame (SPEC §4.6)
    normals: bool = False

    def __post_init__(self):
        if self.views_per_shard < 1:
            raise ValueError(f"views_per_shard must be at least 1, got {self.views_per_shard}")
        if not 1 <= self.compression_level <= 22:
            raise ValueError(f"compression_level must be in 1..22, got {self.compression_level}")


@dataclass(frozen=True)
class DatasetConfig:
    """Everything that decides what ``sceneforge render`` writes (not how fast: workers and
    the Dask scheduler are run options, so stores written with any of them are identical)."""

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

    def to_dict(self) -> dict:
        """The resolved config as JSON-ready data (what the store saves)."""
        return dataclass_to_dict(self)

    @classmethod
    def from_dict(cls, data: dict, *, what: str = "config") -> "DatasetConfig":
        """Validate ``data`` against the config schema and build the config.

        Raises :class:`SceneforgeError` naming ``what`` and the problem.
        """
        from sceneforge import schemas

        schemas.validate_or_raise(data, "config", what=what)
        try:
            return dataclass_from_dict(cls, data)
        except ValueError as e:
            raise SceneforgeError(f"{what}: {e}") from None


def load_config(path: str | Path | None = None, overrides: dict | None = None) -> DatasetConfig:
    """Defaults, updated by the JSON config file at ``path``, updated by ``overrides``.

    ``overrides`` is nested like the file (``{"view": {"overhead": {"resolution": 64}}}``).
    Raises :class:`SceneforgeError` for an unreadable file or an invalid config.
    """
    data: dict = {}
    what = "config"
    if path is not None:
        what = str(path)
        try:
            data = json.loads(Path(path).read_text())
        except OSError as e:
            raise SceneforgeError(f"{path}: cannot read config ({e.strerror or e})") from None
        except ValueError as e:
            raise SceneforgeError(f"{path}: not valid JSON ({e})") from None
        if not isinstance(data, dict):
            raise SceneforgeError(f"{path}: a config file holds one JSON object")
    return DatasetConfig.from_dict(_merge(data, overrides or {}), what=what)


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
        (inner,) = [a for a in args if a is not type(None)]
        return _coerce(inner, value)
    if origin is tuple:
        item = args[0]
        return tuple(_coerce(args[i] if args[-1] is not Ellipsis else item, v) for i, v in enumerate(value))
    if hint in (int, float):
        return hint(value)
    return value


# ----------------------------------------------------------------------------- schema

_JSON_TYPES = {bool: "boolean", int: "integer", float: "number", str: "string"}


def _field_docs(cls) -> dict[str, str]:
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


def _type_schema(hint) -> dict:
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if is_dataclass(hint):
        return _object_schema(hint)
    if origin in (typing.Union, types.UnionType):
        (inner,) = [a for a in args if a is not type(None)]
        schema = _type_schema(inner)
        schema["type"] = [schema["type"], "null"]
        return schema
    if origin is tuple:
        if len(args) == 2 and args[1] is Ellipsis:
            return {"type": "array", "items": _type_schema(args[0])}
        return {"type": "array", "items": _type_schema(args[0]), "minItems": len(args), "maxItems": len(args)}
    return {"type": _JSON_TYPES[hint]}


def _object_schema(cls) -> dict:
    hints = typing.get_type_hints(cls)
    docs = _field_docs(cls)
    skip = _DERIVED.get(cls, frozenset())
    props = {}
    for f in fields(cls):
        if f.name in skip:
            continue
        prop = _type_schema(hints[f.name])
        if f.name in docs:
            prop = {"description": docs[f.name], **prop}
        if f.default is not MISSING and not is_dataclass(f.default):
            prop["default"] = list(f.default) if isinstance(f.default, tuple) else f.default
        props[f.name] = prop
    return {"type": "object", "description": inspect.getdoc(cls).split("\n\n")[0].replace("\n", " "),
            "properties": props, "additionalProperties": False}


def config_schema() -> dict:
    """The JSON Schema of a config file (and of the config saved in a store)."""
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "$id": "https://sceneforge.invalid/schemas/config.schema.json",
        "title": "sceneforge render config",
        **_object_schema(DatasetConfig),
    }


if __name__ == "__main__":
    print(json.dumps(config_schema(), indent=2, ensure_ascii=False))
