"""Command-line options generated from the config dataclasses, so that every option's help,
shown default and type come from one place: the field's ``#:`` doc, its default and its
type hint (the way tyro does it for nerfstudio, with Click).

A command declares once which options set which config fields (a list of
:class:`ConfigOption`); :func:`config_options` adds them with ``--config FILE`` and hands
the command the resolved config: defaults < the file < the options given on the command
line. An option that was not given leaves the file's value alone: Click's parameter source
says what was typed, defaults are never passed as overrides.
"""

from __future__ import annotations

import functools
import re
import types
import typing
from collections.abc import Callable, Sequence
from dataclasses import MISSING, dataclass

import click
from click.core import ParameterSource

from sceneforge.config import (
    field_default,
    field_doc,
    field_type,
    read_config_file,
    resolve_config,
    schema_of,
)
from sceneforge.houses import FORMATS

_TYPES = {bool: click.BOOL, int: click.INT, float: click.FLOAT, str: click.STRING}


@dataclass(frozen=True)
class ConfigOption:
    """A command-line option (or argument) that sets config fields.

    decl     : the option as typed, ``"--views-per-house"``; a bool field makes it a
               ``--x/--no-x`` flag; without leading dashes, an argument (``"stores"``)
    fields   : dotted path(s) of the field(s) it sets, ``"view.overhead.resolution"``; with
               several, a tuple value is spread over them (``--resolution WxH`` → width,
               height) and any other value sets them all (``--seed``)
    help     : an option of several fields only, and required there: what the option does
               as a whole (each field's doc says what that field is, and two docs glued
               together do not read as one help); an option of one field takes its doc
    type     : a Click type narrower than the field's (a range, an existing path, a parser
               such as :class:`Size`); default: from the field's type hint
    convert  : applied to the parsed value before it becomes an override (e.g. a path made absolute)
    metavar  : shown for the value in ``--help``
    """

    decl: str
    fields: str | tuple[str, ...]
    type: click.ParamType | None = None
    convert: Callable | None = None
    metavar: str | None = None
    help: str | None = None

    def __post_init__(self):
        if (len(self.paths) > 1) != (self.help is not None):
            raise TypeError(f"{self.decl}: an option that sets several fields says what it does in help=, "
                            "an option of one field takes its field's doc")

    @property
    def paths(self) -> tuple[str, ...]:
        return (self.fields,) if isinstance(self.fields, str) else tuple(self.fields)

    @property
    def is_argument(self) -> bool:
        return not self.decl.startswith("-")

    @property
    def name(self) -> str:
        """The Click parameter name (what ``ctx.get_parameter_source`` takes)."""
        return self.decl.split("/")[0].lstrip("-").replace("-", "_")


class Size(click.ParamType):
    """``WIDTHxHEIGHT`` (``x``, ``X`` or ``×``) → (width, height), both positive."""

    name = "WxH"

    def convert(self, value, param, ctx):
        if isinstance(value, tuple):
            return value
        match = re.fullmatch(r"(\d+)[xX×](\d+)", value)
        if not match or not all(int(g) > 0 for g in match.groups()):
            self.fail(f"expected WIDTHxHEIGHT such as 320x240, got {value!r}", param, ctx)
        return int(match.group(1)), int(match.group(2))

    @staticmethod
    def show(values) -> str:
        return "x".join(map(str, values))


def _inner(hint):
    """``X`` of ``X | None``."""
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        (hint,) = [a for a in typing.get_args(hint) if a is not type(None)]
    return hint


def _click_kwargs(hint) -> dict:
    """Click's type (and nargs/multiple) for a field type hint."""
    hint = _inner(hint)
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin is typing.Literal:
        return {"type": click.Choice(list(args))}
    if origin is tuple:
        if len(args) == 2 and args[1] is Ellipsis:
            return {"type": _TYPES[args[0]], "multiple": True}
        return {"type": _TYPES[args[0]], "nargs": len(args)}
    return {"type": _TYPES[hint]}


def _help(doc: str) -> str:
    """A field's doc (or an option's own help) as a sentence of help text (``None = x``, the
    docs' way to say what an unset field means, reads "not set: x" on the command line)."""
    text = doc.replace("``", "").replace("None = ", "not set: ")
    text = text[:1].upper() + text[1:]
    return text if text.endswith(".") else text + "."


def _doc(root: type, path: str) -> str:
    doc = field_doc(root, path)
    if not doc:
        raise TypeError(f"{root.__name__}.{path} has no #: doc to be its option's help")
    return doc


def _default(opt: ConfigOption, defaults: list):
    """The field's default as Click takes it, so ``--help`` shows it (None: nothing to show).
    It is never passed on as an override: :func:`config_options` only reads the options typed."""
    if any(d is MISSING or d is None for d in defaults):
        return None
    if len(defaults) > 1 and hasattr(opt.type, "show"):
        return opt.type.show(defaults)
    return defaults[0]


def _parameter(root: type, opt: ConfigOption):
    """The Click decorator adding ``opt``, its help, default and type read from ``root``'s fields."""
    hint = field_type(root, opt.paths[0])
    defaults = [field_default(root, p) for p in opt.paths]
    kwargs = _click_kwargs(hint)
    if opt.type is not None:
        kwargs["type"] = opt.type
    if opt.is_argument:
        nargs = -1 if kwargs.pop("multiple", False) else kwargs.pop("nargs", 1)
        return click.argument(opt.name, nargs=nargs, type=kwargs["type"], required=False)
    flag = _inner(hint) is bool
    decl = opt.decl
    if flag:
        kwargs.pop("type")
        if "/" not in decl:
            decl = f"{decl}/--no-{decl.lstrip('-')}"
    default = _default(opt, defaults)
    return click.option(decl, opt.name, default=default, show_default=default is not None, metavar=opt.metavar,
                        help=_help(opt.help or _doc(root, opt.paths[0])), **kwargs)


def _given(ctx: click.Context, name: str) -> bool:
    return ctx.get_parameter_source(name) not in (None, ParameterSource.DEFAULT, ParameterSource.DEFAULT_MAP)


def _set(tree: dict, path: str, value) -> None:
    *parents, leaf = path.split(".")
    for key in parents:
        tree = tree.setdefault(key, {})
    tree[leaf] = list(value) if isinstance(value, tuple) else value


def config_options(root: type, options: Sequence[ConfigOption]):
    """Add ``--config FILE`` (checked against the root's schema) and ``options`` to a command,
    and pass it ``config``: ``root`` resolved from its defaults, the file and the options
    given. An option (or argument) for a field without a default must be given unless the
    file sets that field."""
    schema = schema_of(root)

    def decorate(func):
        @functools.wraps(func)
        def wrapper(*args, config_file, **kwargs):
            ctx = click.get_current_context()
            data = read_config_file(config_file) if config_file else {}
            overrides: dict = {}
            for opt in options:
                value = kwargs.pop(opt.name)
                if not _given(ctx, opt.name) or value == ():
                    _require(root, opt, data)
                    continue
                value = opt.convert(value) if opt.convert else value
                spread = len(opt.paths) > 1 and isinstance(value, tuple)
                for k, path in enumerate(opt.paths):
                    _set(overrides, path, value[k] if spread else value)
            return func(*args, config=resolve_config(root, config_file, overrides), **kwargs)

        for opt in reversed(options):
            wrapper = _parameter(root, opt)(wrapper)
        return click.option("--config", "config_file", type=click.Path(exists=True, dir_okay=False), default=None,
                            metavar="FILE",
                            help=f"JSON config (schemas/{schema}.schema.json); the options below override it.")(wrapper)

    return decorate


def _require(root: type, opt: ConfigOption, data: dict) -> None:
    """A usage error when ``opt`` sets a required field that the config file does not set."""
    for path in opt.paths:
        if field_default(root, path) is not MISSING:
            continue
        tree = data
        for key in path.split("."):
            tree = tree.get(key) if isinstance(tree, dict) else None
        if tree is None:
            what = f"argument '{opt.name.upper()}...'" if opt.is_argument else f"option '{opt.decl}'"
            raise click.UsageError(f"Missing {what} (or {path!r} in --config FILE).")


def absolute_path(path: str) -> str:
    """``path`` made absolute, a URL left as it is (a config saved with a store names its
    files from anywhere)."""
    from sceneforge.store.location import resolve

    return resolve(path)


#: the house-reading options of every command that reads houses (fields of ``houses``)
HOUSE_OPTIONS = (
    ConfigOption("--format", "houses.format", type=click.Choice(FORMATS)),
    ConfigOption("--strict", "houses.strict"),
    ConfigOption("--scale", "houses.scale", type=click.FloatRange(min=0, min_open=True)),
    ConfigOption("--up-axis", "houses.up_axis"),
    ConfigOption("--name-map", "houses.name_map", type=click.Path(exists=True, dir_okay=False)),
    ConfigOption("--future-dir", "houses.future_dir", type=click.Path(exists=True, file_okay=False)),
    ConfigOption("--suncg-textures", "houses.suncg_textures", type=click.Choice(["replace", "multiply"])),
)


def check_device(device: str) -> str:
    """``device`` (``--device``) if torch can use it: ``auto``, ``cpu``, ``mps``, ``cuda`` or
    ``cuda:N``; else :class:`SceneforgeError`, one line saying what is accepted (or that
    there is no such GPU)."""
    from sceneforge.errors import SceneforgeError

    match = re.fullmatch(r"auto|cpu|mps|cuda(?::(\d+))?", device)
    if match is None:
        raise SceneforgeError(f"--device {device}: expected auto, cpu, cuda, cuda:N (N a GPU index) or mps")
    if device.startswith("cuda"):
        import torch

        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0:
            raise SceneforgeError(f"--device {device}: torch sees no CUDA GPU (torch {torch.__version__}); "
                                  "use --device cpu")
        if match.group(1) is not None and int(match.group(1)) >= count:
            raise SceneforgeError(f"--device {device}: torch sees {count} CUDA GPU(s), numbered from 0")
    return device
