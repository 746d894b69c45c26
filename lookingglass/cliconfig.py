"""Command-line options generated from the config dataclasses, one per (nested) field.

A field `hull.resolution` of a preset's config becomes the option `--hull.resolution` (a bool
field `net.residual`: `--net.residual/--net.no-residual`; underscores become dashes), with the
field's type, its `setting(help=...)`, its range and the default preset's value as the shown
default (other presets' values, where they differ, in the help). Only the values the user gives
replace the chosen preset's (or a loaded config's), through `dataclasses.replace`, so the
configs' own checks (`__post_init__`, ConfigError) judge them; the error names the flag.

A command opts in with `@app.command(cls=config_command(ConfigOptions("pipeline", ...)))`, takes
`ctx: typer.Context` and calls `apply_config_flags(ctx, base_config)`. The options are built when
that command is parsed or its help is shown (the configs import torch): the other commands and
`lookingglass --help` stay quick.
"""

from __future__ import annotations

import dataclasses
import inspect
import types
import typing
from dataclasses import dataclass, field
from typing import Any, Mapping, Optional

import typer
from typer.core import TyperCommand

from .configio import out_of_range
from .errors import ConfigError
from .presets import DEFAULT_PRESET, PRESET_NAMES, preset

CONFIG_VALUES = "lookingglass.config_values"  # ctx.meta key: {dotted field: value given}
SCALARS = (int, float, str, bool)


@dataclass(frozen=True)
class ConfigOptions:
    """Which config of a preset a command takes options for, and how.

    config: a field of presets.Preset ("pipeline", "dataset", "normal_training", "point_training").
    aliases: dotted field -> a second flag for it (the short spellings the docs use:
        "hull.resolution" -> "--hull-resolution"); errors name a field by its alias.
    exclude: dotted fields (or whole nested configs) without an option (the command sets them).
    only: when given, the dotted fields (or whole nested configs) that get an option; no other does.
    """

    config: str
    aliases: Mapping[str, str] = field(default_factory=dict)
    exclude: frozenset[str] = frozenset()
    only: Optional[frozenset[str]] = None

    def wants(self, dotted: str) -> bool:
        parts = dotted.split(".")
        enclosing = {".".join(parts[:k]) for k in range(1, len(parts) + 1)}  # the field and the configs holding it
        if enclosing & self.exclude:
            return False
        # `only` names the field, a config holding it, or (for a nested config) a field inside it
        return self.only is None or bool(enclosing & self.only) or any(o.startswith(dotted + ".") for o in self.only)


@dataclass(frozen=True)
class ConfigFlag:
    """One generated option. dotted: the field's path ("hull.resolution"); param: its Python
    name; decls: its flags; option_type: Optional[the field's type]; spec: the dataclass field;
    owner: the dataclass that holds it; flag: the spelling errors use (the alias, if any)."""

    dotted: str
    param: str
    decls: tuple[str, ...]
    option_type: Any
    spec: dataclasses.Field
    owner: type
    flag: str


def _option_type(hint: Any) -> Any:
    """Optional[hint] for the types an option can take (scalars, Optional scalars, fixed-size
    tuples of scalars); None for the others (variable tuples, dicts), which get no option."""
    if hint in SCALARS:
        return Optional[hint]
    args = typing.get_args(hint)
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        inner = [a for a in args if a is not type(None)]
        return Optional[inner[0]] if len(inner) == 1 and inner[0] in SCALARS else None
    if typing.get_origin(hint) is tuple and args and Ellipsis not in args and all(a in SCALARS for a in args):
        return Optional[hint]
    return None


def config_flags(cls: type, options: ConfigOptions, path: str = "") -> list[ConfigFlag]:
    """The options for dataclass `cls`'s fields, nested configs' included (depth first)."""
    flags = []
    hints = typing.get_type_hints(cls)
    for spec in dataclasses.fields(cls):
        dotted, hint = f"{path}{spec.name}", hints[spec.name]
        if not options.wants(dotted):
            continue
        if dataclasses.is_dataclass(hint):
            flags += config_flags(hint, options, f"{dotted}.")
            continue
        option_type = _option_type(hint)
        if option_type is None:
            continue
        prefix, name = "--" + path.replace("_", "-"), spec.name.replace("_", "-")
        decls = ((f"{prefix}{name}/{prefix}no-{name}",) if hint is bool else
                 (f"{prefix}{name}", *((options.aliases[dotted],) if dotted in options.aliases else ())))
        flag = options.aliases.get(dotted, f"{prefix}{name}")
        flags.append(ConfigFlag(dotted, "config__" + dotted.replace(".", "__"), decls, option_type, spec, cls, flag))
    return flags


def _field_value(config: Any, dotted: str) -> Any:
    for part in dotted.split("."):
        config = getattr(config, part)
    return config


def _shown(value: Any) -> str:
    return " ".join(map(str, value)) if isinstance(value, tuple) else str(value)


def _help(flag: ConfigFlag, configs: dict[str, Any]) -> str:
    """The field's help, the range the command line takes and other presets' differing values."""
    meta = flag.spec.metadata
    text = meta.get("help") or f"{flag.owner.__name__}.{flag.spec.name}."
    bounds = meta.get("cli_range") or meta.get("range")
    if bounds:
        low, high = bounds
        text += f" At least {low}." if high is None else f" At most {high}." if low is None else \
            f" Range: {low} to {high}."
    default = _field_value(configs[DEFAULT_PRESET], flag.dotted)
    others = [f"{name}: {_shown(value)}" for name, config in configs.items()
              if (value := _field_value(config, flag.dotted)) != default]
    return text + (f" ({'; '.join(others)})" if others else "")


def _panel(flag: ConfigFlag, options: ConfigOptions) -> str:
    """The help panel of a field: its dataclass, and the flags' common prefix when nested."""
    path = flag.dotted.rpartition(".")[0]
    return f"{flag.owner.__name__} (--{path.replace('_', '-')}.*)" if path else \
        f"{flag.owner.__name__} (defaults: the {DEFAULT_PRESET} preset's)"


def build_options(options: ConfigOptions) -> tuple[list, list[ConfigFlag]]:
    """The click parameters of `options` (built by typer from a generated signature) and their flags."""
    configs = {name: getattr(preset(name), options.config) for name in PRESET_NAMES}
    # the top level's options first, then each nested config's (sorted is stable)
    flags = sorted(config_flags(type(configs[DEFAULT_PRESET]), options), key=lambda f: f.dotted.count("."))
    parameters = [
        inspect.Parameter(f.param, inspect.Parameter.KEYWORD_ONLY, annotation=f.option_type, default=typer.Option(
            _field_value(configs[DEFAULT_PRESET], f.dotted), *f.decls, help=_help(f, configs), show_default=True,
            rich_help_panel=_panel(f, options)))
        for f in flags]

    def generated(**values: Any) -> None:
        """Never called: typer reads its signature."""

    generated.__signature__ = inspect.Signature(parameters)
    generated.__annotations__ = {p.name: p.annotation for p in parameters}
    holder = typer.Typer(add_completion=False)
    holder.command()(generated)
    names = {f.param for f in flags}
    return [p for p in typer.main.get_command(holder).params if p.name in names], flags


class ConfigCommand(TyperCommand):
    """A typer command with the generated options of `options` (see `config_command`)."""

    options: ConfigOptions
    _built: Optional[tuple[list, list[ConfigFlag]]] = None

    @classmethod
    def generated(cls) -> tuple[list, list[ConfigFlag]]:
        if cls._built is None:
            cls._built = build_options(cls.options)
        return cls._built

    def get_params(self, ctx: Any) -> list:
        """The command's own options, the generated ones, then --help."""
        params, help_option = super().get_params(ctx), self.get_help_option(ctx)
        own = [p for p in params if p is not help_option]
        return own + self.generated()[0] + ([help_option] if help_option else [])

    def invoke(self, ctx: Any) -> Any:
        """Moves the generated options' values out of the command's arguments into ctx.meta, the
        ones the user gave only (a default is the default preset's, not the chosen one's)."""
        given = {}
        for flag in self.generated()[1]:
            value = ctx.params.pop(flag.param, None)
            source = ctx.get_parameter_source(flag.param)
            if source is not None and source.name not in ("DEFAULT", "DEFAULT_MAP"):
                given[flag.dotted] = value
        ctx.meta[CONFIG_VALUES] = given
        return super().invoke(ctx)


def config_command(options: ConfigOptions) -> type[ConfigCommand]:
    """The command class (for `app.command(cls=...)`) that adds the options of `options`."""
    return type(f"ConfigCommand_{options.config}", (ConfigCommand,), {"options": options, "_built": None})


def apply_config_flags(ctx: Any, base: Any) -> Any:
    """`base` (the chosen preset's config, or a loaded one) with the generated options the user
    gave; each changed config is rebuilt by dataclasses.replace, so its __post_init__ checks the
    values. A refused value raises ConfigError naming the flag and the config's complaint."""
    given = ctx.meta.get(CONFIG_VALUES, {})
    flags = {f.dotted: f for f in type(ctx.command).generated()[1]}
    for dotted, value in given.items():
        problem = out_of_range(flags[dotted].flag, value, flags[dotted].spec.metadata.get("cli_range"))
        if problem:
            raise ConfigError(problem)
    return _replace_nested(base, given, flags)


def _replace_nested(config: Any, values: dict[str, Any], flags: dict[str, ConfigFlag], path: str = "") -> Any:
    """`config` with the dotted `values` (relative to `path`) set, nested configs rebuilt first."""
    changes: dict[str, Any] = {}
    nested: dict[str, dict[str, Any]] = {}
    for dotted, value in values.items():
        head, _, rest = dotted.partition(".")
        if rest:
            nested.setdefault(head, {})[rest] = value
        else:
            changes[head] = value
    for head, inner in nested.items():
        changes[head] = _replace_nested(getattr(config, head), inner, flags, f"{path}{head}.")
    try:
        return dataclasses.replace(config, **changes)
    except ConfigError as exc:
        named = ", ".join(f"{flags[path + k].flag}={_shown(v)}" for k, v in values.items() if "." not in k)
        raise ConfigError(f"{named}: {exc}" if named else str(exc)) from None
