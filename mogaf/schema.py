"""The config schema check (config/schema.yaml), as one line naming the config
file and the key, for the CLI and the workflow alike.

jsonschema's own report (and Snakemake's, which prints it) quotes the failing
part of the schema and of the config: for a wrong section that is a page of
YAML. Here it is `<file>: <key>: <what is wrong>`, where <file> is the config
file that sets the key (the last one that does, of those given in order of
precedence), so a layered config (`--configfile a.yaml b.yaml`) names the
layer to fix.
"""

from __future__ import annotations

import os
import re
from collections.abc import Mapping, Sequence
from typing import Any

from .config import depth_set, load_yaml
from .errors import MogafError
from .settings import workflow_schema

MAX_MESSAGE = 240  # characters of jsonschema's message kept (it may quote a whole section)


def setting_source(keys: Sequence[Any], layers: Sequence[tuple[str, Mapping[str, Any]]]) -> str:
    """The layer (name, contents; lowest precedence first) that sets the
    deepest part of `keys`, the last such one; every layer's name when none
    sets any of it (e.g. a required key missing everywhere)."""
    best, depth = None, 0
    for name, contents in layers:
        d = depth_set(contents, keys)
        if d and d >= depth:
            best, depth = name, d
    return best if best is not None else " + ".join(name for name, _ in layers)


def schema_problem(config: Mapping[str, Any], schema: Mapping[str, Any]) -> tuple[list[Any], str] | None:
    """(key path, one-line message) of the most relevant schema violation, or None."""
    import jsonschema

    validator_class = jsonschema.validators.validator_for(schema)
    error = jsonschema.exceptions.best_match(validator_class(schema).iter_errors(config))
    if error is None:
        return None
    message = " ".join(error.message.split())
    if len(message) > MAX_MESSAGE:
        message = message[: MAX_MESSAGE - 3] + "..."
    hint = error.schema.get("description") if isinstance(error.schema, Mapping) else None
    if hint and error.validator in ("pattern", "propertyNames"):
        message += f" ({hint})"
    keys = list(error.absolute_path)
    if error.validator == "additionalProperties" and isinstance(error.instance, Mapping):
        # the unexpected key itself, so the file that sets it is named (not every layer)
        allowed = set(error.schema.get("properties", {}))
        patterns = list(error.schema.get("patternProperties", {}))
        extra = [k for k in error.instance if k not in allowed and not any(re.search(p, str(k)) for p in patterns)]
        if extra:
            keys.append(extra[0])
    return keys, message


def config_error(
    config: Mapping[str, Any], schema: Mapping[str, Any], layers: Sequence[tuple[str, Mapping[str, Any]]]
) -> MogafError | None:
    """The one-line error for `config` against `schema`, naming the layer
    that sets the failing key and the key; None if the config is valid."""
    found = schema_problem(config, schema)
    if found is None:
        return None
    keys, message = found
    where = ".".join(str(k) for k in keys) or "top level"
    return MogafError(f"{setting_source(keys, layers)}: {where}: {message}")


def file_layers(paths: Sequence[str | os.PathLike]) -> list[tuple[str, Mapping[str, Any]]]:
    """(path, contents) of config files, in the order given (lowest precedence first)."""
    return [(os.fspath(p), load_yaml(p)) for p in paths]


def load_config_schema(path: str | os.PathLike) -> dict[str, Any]:
    """config/schema.yaml with the stage sections' definitions generated from
    their settings dataclasses (mogaf.settings): the schema every config is checked against."""
    return workflow_schema(load_yaml(path))
