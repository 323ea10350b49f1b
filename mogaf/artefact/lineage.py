"""Artefact lineage: the inputs a stage declares (`stage_inputs`) must share
one lineage (`check_lineage`), every artefact written inside the block
records their lineage digests, and `check_made_from` checks a direct one."""

from __future__ import annotations

import contextlib
import contextvars
import os
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path

from ..errors import input_error
from .header import (
    ATTR_INPUTS,
    ATTR_LINEAGE,
    ATTR_STAGE,
    _attr_value,
    _check_header,
    _decode_attr,
    _open,
    config_digest,
)


@dataclass(frozen=True)
class Lineage:
    path: Path
    stage: str
    digest: str  # "" when the file predates lineage records
    inputs: Mapping[str, tuple[str, ...]]  # input stage -> lineage digests of the inputs it was made from


_STAGE_INPUTS: contextvars.ContextVar[tuple[Lineage, ...]] = contextvars.ContextVar("mogaf_stage_inputs", default=())


def read_lineage(path: str | os.PathLike) -> Lineage:
    p = Path(path)
    with _open(p) as fh:
        _check_header(fh, p, None, None)
        inputs = _decode_attr(fh.attrs.get(ATTR_INPUTS, "json:{}"))
        digest = _decode_attr(fh.attrs.get(ATTR_LINEAGE, ""))
        if not (
            isinstance(inputs, dict)
            and all(isinstance(v, list) and all(isinstance(d, str) for d in v) for v in inputs.values())
            and isinstance(digest, str)
        ):
            raise input_error(
                p, f"attributes {ATTR_INPUTS} / {ATTR_LINEAGE} are malformed; rerun the stage that wrote it"
            )
        return Lineage(p, _decode_attr(fh.attrs[ATTR_STAGE]), digest, {str(k): tuple(v) for k, v in inputs.items()})


def check_lineage(artefacts: Iterable[Lineage]) -> None:
    """Inputs read together must come from one lineage of settings: an
    artefact made from another upstream artefact than the one given (other
    settings, a split of another scene, groups of another reconstruction) is
    refused with one line naming both files. Files that record no lineage
    (written outside a stage, or before lineage existed) are not checked."""
    given = list(artefacts)
    for a in given:
        for b in given:
            made_from = a.inputs.get(b.stage)
            if b is a or made_from is None or not b.digest:
                continue
            if b.digest not in made_from:
                raise input_error(
                    a.path,
                    f"was made from another '{b.stage}' artefact than {b.path} "
                    "(other settings or inputs); rerun the stages after it",
                )


def check_made_from(derived: str | os.PathLike, source: str | os.PathLike) -> None:
    """`derived` must have been made from `source` itself, not merely from
    something of one lineage with it (e.g. a measurement of recon.h5 where
    refined.h5 is meant). Files that record no lineage are not checked."""
    made, src = read_lineage(derived), read_lineage(source)
    if not made.digest or not src.digest:
        return
    if src.digest not in made.inputs.get(src.stage, ()):
        made_of = ", ".join(f"'{stage}'" for stage in sorted(made.inputs)) or "nothing recorded"
        raise input_error(
            made.path,
            f"was not made from {src.path} (a '{src.stage}' artefact; it was made from "
            f"{made_of}); rerun the stage that writes it",
        )


def _is_file(path: str | os.PathLike) -> bool:
    try:
        return Path(path).is_file()
    except OSError as exc:  # e.g. a name longer than the file system allows
        raise input_error(path, f"cannot be opened ({exc.strerror or exc})") from None


@contextlib.contextmanager
def stage_inputs(*paths: str | os.PathLike | None) -> Iterator[tuple[Lineage, ...]]:
    """Declare the artefacts a stage reads. They are checked to share one
    lineage, and every artefact written inside the block records them."""
    found = tuple(read_lineage(p) for p in paths if p is not None and _is_file(p))
    check_lineage(found)
    token = _STAGE_INPUTS.set(found)
    try:
        yield found
    finally:
        _STAGE_INPUTS.reset(token)


def _lineage_attrs(stage: str, digest: str, content: str) -> dict[str, str]:
    inputs: dict[str, list[str]] = {}
    for item in _STAGE_INPUTS.get():
        inputs.setdefault(item.stage, []).append(item.digest)
    inputs = {k: sorted(v) for k, v in sorted(inputs.items())}
    lineage = config_digest({"stage": stage, "config": digest, "inputs": inputs, "content": content})
    return {ATTR_LINEAGE: lineage, ATTR_INPUTS: _attr_value(inputs)}
