"""Typed stage settings: each default written once, with its source.

A stage's settings are a frozen dataclass whose fields are made by
`setting(default, source, ...)`: the default, where the value comes from
(paper section, Shape-of-Motion, CPU budget) and its constraints. From that
one definition come

- `defaults(cls)`: the plain dict the stages hash into artefact digests;
- `check(cls, section, params)`: defaults <- params, unknown keys refused,
  types and ranges checked, one line naming the section and key;
- `load(cls, section, params)`: the same as a frozen instance (attribute access);
- `section_schema(cls)`: the JSON-schema fragment the workflow validates
  config/config.yaml against (config/schema.yaml holds only what is not a
  stage setting);
- `describe(cls)`: the rows of config/README.md.
"""

from __future__ import annotations

import dataclasses
import functools
import numbers
import types
import typing
from collections.abc import Mapping
from typing import Any, Literal, get_args, get_origin

from .errors import MogafError

_KINDS = {bool: "boolean", int: "integer", float: "number", str: "string"}


def setting(
    default: Any,
    source: str = "",
    *,
    minimum: float | None = None,
    maximum: float | None = None,
    exclusive_minimum: float | None = None,
    exclusive_maximum: float | None = None,
    schema: Mapping[str, Any] | None = None,
    injected: bool = False,
) -> Any:
    """A settings field. `source`: where the default comes from (paper
    section, SoM, CPU: a smaller value so a CPU run fits its budget) and, when
    useful, what it does. `schema`: extra JSON-schema keys for structured
    values (lists, mappings). `injected`: set by the workflow from the
    config's top level (seed, device), not written in the stage's section."""
    meta = {
        "source": source,
        "minimum": minimum,
        "maximum": maximum,
        "exclusive_minimum": exclusive_minimum,
        "exclusive_maximum": exclusive_maximum,
        "schema": dict(schema or {}),
        "injected": injected,
    }
    if isinstance(default, (list, dict)):
        return dataclasses.field(default_factory=lambda: _copy(default), metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def _copy(value: Any) -> Any:
    if isinstance(value, list):
        return [_copy(v) for v in value]
    if isinstance(value, dict):
        return {k: _copy(v) for k, v in value.items()}
    return value


def _fields(cls: type) -> tuple[dataclasses.Field, ...]:
    if not dataclasses.is_dataclass(cls):
        raise TypeError(f"{cls!r} is not a settings dataclass")
    return dataclasses.fields(cls)


@functools.cache
def _hints(cls: type) -> dict[str, Any]:
    """The class's resolved annotations (evaluated once: check() runs at every stage call)."""
    return typing.get_type_hints(cls)


def _annotation(cls: type, f: dataclasses.Field) -> Any:
    return _hints(cls)[f.name]


def _parts(annotation: Any) -> tuple[Any, bool]:
    """(the type without None, whether None is allowed)."""
    args = get_args(annotation)
    if get_origin(annotation) in (typing.Union, types.UnionType) and type(None) in args:
        rest = [a for a in args if a is not type(None)]
        return (rest[0] if len(rest) == 1 else typing.Union[tuple(rest)]), True  # noqa: UP007 (built at run time)
    return annotation, False


def defaults(cls: type) -> dict[str, Any]:
    """Every field's default, in definition order (a fresh copy)."""
    return {f.name: (f.default_factory() if f.default is dataclasses.MISSING else f.default) for f in _fields(cls)}


def _field_schema(cls: type, f: dataclasses.Field) -> dict[str, Any]:
    kind, nullable = _parts(_annotation(cls, f))
    out: dict[str, Any] = {}
    if get_origin(kind) is Literal:
        out["enum"] = list(get_args(kind))
    elif kind in _KINDS:
        out["type"] = _KINDS[kind]
    elif kind in (list, tuple) or get_origin(kind) in (list, tuple):
        out["type"] = "array"
    elif get_origin(kind) is dict or kind is dict:
        out["type"] = "object"
    meta = f.metadata
    if "anyOf" in (meta.get("schema") or {}):  # the alternatives carry their own types
        out.pop("type", None)
    for key, name in (
        ("minimum", "minimum"),
        ("maximum", "maximum"),
        ("exclusive_minimum", "exclusiveMinimum"),
        ("exclusive_maximum", "exclusiveMaximum"),
    ):
        if meta.get(key) is not None:
            out[name] = meta[key]
    out.update(meta.get("schema") or {})
    if nullable:
        if "type" in out:
            out["type"] = [out["type"], "null"]
        if "enum" in out:
            out["enum"] = [*out["enum"], None]
    if meta.get("source"):
        out["description"] = meta["source"]
    return out


def section_schema(cls: type) -> dict[str, Any]:
    """JSON schema of a config section holding `cls`'s settings (each optional)."""
    return {
        "type": "object",
        "additionalProperties": False,
        "properties": {f.name: _field_schema(cls, f) for f in _fields(cls) if not f.metadata.get("injected")},
    }


def _is_number(value: Any) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def _checked(section: str, key: str, kind: Any, value: Any) -> Any:
    """`value` as `kind`, or a MogafError naming the section and key."""
    where = f"{section} param '{key}'"
    if get_origin(kind) is Literal:
        choices = get_args(kind)
        if value not in choices or isinstance(value, bool) != any(isinstance(c, bool) for c in choices if c == value):
            raise MogafError(f"{where} must be one of {', '.join(map(str, choices))}, got {value!r}")
        return value
    if kind is bool:
        if not isinstance(value, bool):
            raise MogafError(f"{where} must be true or false, got {value!r}")
        return value
    if kind is int:
        if not _is_number(value) or int(value) != value:
            raise MogafError(f"{where} must be an integer, got {value!r}")
        return int(value)
    if kind is float:
        if not _is_number(value):
            raise MogafError(f"{where} must be a number, got {value!r}")
        return float(value)
    if kind is str:
        if not isinstance(value, str):
            raise MogafError(f"{where} must be a string, got {value!r}")
        return value
    origin = get_origin(kind) or kind
    if origin in (list, tuple) and not isinstance(value, (list, tuple)):  # their items: the schema's business
        raise MogafError(f"{where} must be a list, got {value!r}")
    if origin is dict and not isinstance(value, Mapping):
        raise MogafError(f"{where} must be a mapping, got {value!r}")
    return value


def check(
    cls: type, section: str, params: Mapping[str, Any] | None, base: Mapping[str, Any] | None = None
) -> dict[str, Any]:
    """Defaults (or `base`, values of cls's fields) <- params, each given value
    checked against its field; unknown keys refused."""
    if params is not None and not isinstance(params, Mapping):
        raise MogafError(f"{section}: the settings must be a mapping, got {type(params).__name__}")
    params = dict(params or {})
    names = [f.name for f in _fields(cls)]
    unknown = sorted(set(params) - set(names), key=str)
    if unknown:
        raise MogafError(
            f"{section}: unknown parameter(s) {', '.join(map(str, unknown))} (known: {', '.join(sorted(names))})"
        )
    out = defaults(cls) if base is None else dict(base)
    for f in _fields(cls):
        if f.name not in params:
            continue
        value = params[f.name]
        kind, nullable = _parts(_annotation(cls, f))
        if value is None and nullable:
            out[f.name] = None
            continue
        value = _checked(section, f.name, kind, value)
        meta = f.metadata
        if meta.get("minimum") is not None and value < meta["minimum"]:
            raise MogafError(f"{section} param '{f.name}' must be at least {meta['minimum']}, got {value!r}")
        if meta.get("maximum") is not None and value > meta["maximum"]:
            raise MogafError(f"{section} param '{f.name}' must be at most {meta['maximum']}, got {value!r}")
        if meta.get("exclusive_minimum") is not None and value <= meta["exclusive_minimum"]:
            raise MogafError(
                f"{section} param '{f.name}' must be greater than {meta['exclusive_minimum']}, got {value!r}"
            )
        if meta.get("exclusive_maximum") is not None and value >= meta["exclusive_maximum"]:
            raise MogafError(f"{section} param '{f.name}' must be less than {meta['exclusive_maximum']}, got {value!r}")
        out[f.name] = value
    return out


def load(cls: type, section: str, params: Any):
    """check(), as a frozen `cls` instance (an instance of `cls` is returned as it is)."""
    if isinstance(params, cls):
        return params
    return cls(**check(cls, section, params))


def as_dict(settings: Any) -> dict[str, Any]:
    """A settings instance as the plain dict artefacts record and hash."""
    return {f.name: getattr(settings, f.name) for f in _fields(type(settings))}


def describe(cls: type) -> list[tuple[str, Any, str]]:
    """(name, default, source) per field, for documentation."""
    d = defaults(cls)
    return [(f.name, d[f.name], f.metadata.get("source", "")) for f in _fields(cls)]


# ------------------------------------------------------------------ the config's stage sections
# config path -> (settings class, the schema definition config/schema.yaml refers to)
def _stage_sections() -> dict[str, tuple[str, str]]:
    """The stages' own config sections, from their specs (mogaf.registry)."""
    from .registry import STAGES

    out: dict[str, tuple[str, str]] = {}
    for spec in STAGES:
        if spec.settings and spec.settings_class:
            out.setdefault(spec.settings, (spec.settings_class, spec.settings))
    return out


# config section -> (its settings dataclass, its definition in the config schema)
SECTIONS: dict[str, tuple[str, str]] = {
    **_stage_sections(),
    # the forecasters' sections inside `forecast` (mogaf.forecast.params: the method table)
    "forecast.mogaf": ("mogaf.forecast.params:MogafSettings", "forecast_mogaf"),
    "forecast.mogaf.structured": ("mogaf.forecast.params:StructuredSettings", ""),  # nested in forecast_mogaf
    "forecast.gcn": ("mogaf.forecast.baseline_params:GCNSettings", "forecast_gcn"),
    "forecast.ode": ("mogaf.forecast.baseline_params:ODESettings", "forecast_ode"),
    # one entry per scene name, over its preset: no defaults of its own in the config tree
    "synthetic.<scene>": ("mogaf.synth.params:SyntheticSettings", "synthetic_scene"),
}
PER_NAME = "<scene>"  # a path part standing for any key (the config's scene names)


def section_class(path: str) -> type:
    """The settings dataclass of config section `path` (e.g. 'forecast.gcn')."""
    import importlib

    module, name = SECTIONS[path][0].split(":")
    return getattr(importlib.import_module(module), name)


def section_defaults() -> dict[str, Any]:
    """Every stage section's defaults as a config tree (injected keys left out)."""
    tree: dict[str, Any] = {}
    for path, (_, name) in SECTIONS.items():
        if not name or PER_NAME in path:  # nested in another section, or one entry per name
            continue
        cls = section_class(path)
        node = tree
        *parents, last = path.split(".")
        for part in parents:
            node = node.setdefault(part, {})
        node[last] = {
            f.name: value for f, value in zip(_fields(cls), defaults(cls).values()) if not f.metadata.get("injected")
        }
    return tree


def workflow_schema(schema: Mapping[str, Any]) -> dict[str, Any]:
    """config/schema.yaml with the stage sections' definitions generated from their settings."""
    out = dict(schema)
    out["definitions"] = {
        **dict(schema.get("definitions") or {}),
        **{name: section_schema(section_class(path)) for path, (_, name) in SECTIONS.items() if name},
    }
    if "forecast" in (schema.get("properties") or {}):  # the pipeline config's schema, not the ablations'
        out["properties"] = _config_properties(schema["properties"])
    # a synthetic scene names its preset besides the generator settings
    scene = out["definitions"]["synthetic_scene"]
    scene["properties"] = {
        "preset": {"type": "string", "description": "mogaf.synth.params.PRESETS"},
        **scene["properties"],
    }
    return out


def _config_properties(given: Mapping[str, Any]) -> dict[str, Any]:
    """The config schema's top level plus what its tables give: each stage's
    section (from its spec), and the forecast method names and sections (the
    method table), so that neither is written in config/schema.yaml."""
    from .forecast.params import JOB_LAYOUTS, METHOD_TABLE, METHODS

    properties = dict(given)
    for path, (_, name) in SECTIONS.items():
        if name and "." not in path:
            properties.setdefault(path, {"$ref": f"#/definitions/{name}"})
    forecast = dict(properties["forecast"])
    fields = dict(forecast["properties"])
    method_name = {"type": "string", "enum": list(METHODS)}
    fields["methods"] = {**fields["methods"], "items": method_name}
    fields["jobs"] = {"type": "string", "enum": list(JOB_LAYOUTS)}
    fields["start_first"] = {"type": "array", "uniqueItems": True, "items": method_name}
    for m in METHOD_TABLE:  # each method's section (none of its own for one reading another's)
        if not m.section:
            definition = SECTIONS[f"forecast.{m.name}"][1] if m.settings is not None else "no_params"
            fields[m.name] = {"$ref": f"#/definitions/{definition}"}
    forecast["properties"] = fields
    with_params = [m.name for m in METHOD_TABLE if m.settings is not None]
    forecast["then"] = {"properties": {"methods": {"items": {"enum": with_params}}}}
    properties["forecast"] = forecast
    return properties


def markdown() -> str:
    """config/README.md: every stage setting with its default and source."""
    import json

    out = [
        "# Settings",
        "",
        "Generated by `python -m mogaf.settings --markdown > config/README.md` from the stages'",
        "settings dataclasses (tests/test_settings.py checks that it is current); do not edit by hand.",
        "",
        "`config/config.yaml` writes out only the settings a user is expected to change. Every",
        "setting below may be set in it or in a file layered over it (`--configfile config/config.yaml",
        "my.yaml`); one left out keeps its default here, an unknown one is refused. Sources: the",
        'paper\'s section ("Supp." = supplementary), "SoM" = official Shape-of-Motion',
        'implementation, "Gaga", GSPred\'s and ODE-GS\'s official code, "ours" where the paper is',
        'silent, "CPU" where a smaller value fits a CPU budget. `seed` and `device` are set once at',
        "the top level of the config and passed to the stages that take them.",
        "",
    ]
    for path in SECTIONS:
        cls = section_class(path)
        out += [
            f"## `{path}`",
            "",
            (cls.__doc__ or "").strip(),
            "",
            "| setting | default | source and meaning |",
            "|---|---|---|",
        ]
        for f, default in zip(_fields(cls), defaults(cls).values()):
            if f.metadata.get("injected"):
                continue
            shown = json.dumps(default) if not isinstance(default, str) else default
            if f.name == "structured":  # its own section follows
                shown = "see below"
            out.append(f"| `{f.name}` | `{shown}` | {f.metadata['source'].replace('|', chr(92) + '|')} |")
        out.append("")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    import argparse

    parser = argparse.ArgumentParser(prog="python -m mogaf.settings", description="the stages' settings")
    parser.add_argument("--markdown", action="store_true", help="print config/README.md")
    parser.add_argument("--schema", action="store_true", help="print the stage sections' JSON schema")
    args = parser.parse_args(argv)
    if args.schema:
        import json

        print(json.dumps({path: section_schema(section_class(path)) for path in SECTIONS}, indent=1))
    else:
        print(markdown())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
