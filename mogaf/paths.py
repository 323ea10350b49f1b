"""Where mogaf keeps its cache (compiled kernels, converted LPIPS weights),
and where a stage may write (`check_outputs`).

The workflow sets MOGAF_CACHE_DIR to `<workdir>/.cache/mogaf` (config key
`cache_dir`), so a pipeline run writes only under results/ and that folder.
Library users without the variable get ~/.cache/mogaf.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Mapping
from pathlib import Path

from .errors import input_error

ENV_CACHE = "MOGAF_CACHE_DIR"
NAME_MAX = 255  # bytes in one file or folder name (Linux, macOS, Windows file systems)


def cache_dir(*parts: str, create: bool = True) -> Path:
    base = os.environ.get(ENV_CACHE) or os.path.join(os.path.expanduser("~"), ".cache", "mogaf")
    path = Path(base, *parts)
    if create:
        path.mkdir(parents=True, exist_ok=True)
    return path


def use_cache_dir(default: str | os.PathLike) -> Path:
    """Make `default` the cache folder unless MOGAF_CACHE_DIR is already set,
    and keep matplotlib's font cache in it too (it would go under ~/.cache).
    Called by the workflow, so that a run writes only under results/ and here."""
    if not os.environ.get(ENV_CACHE):
        os.environ[ENV_CACHE] = str(Path(default).resolve())
    base = Path(os.environ[ENV_CACHE])
    if not os.environ.get("MPLCONFIGDIR"):
        os.environ["MPLCONFIGDIR"] = str(base / "matplotlib")
    return base


# ------------------------------------------------------------------ outputs
# Files whose presence marks a dataset folder (D-NeRF; DyCheck iPhone and the
# synthetic scenes): no stage writes inside one.
DATASET_MARKERS = ("transforms_train.json", os.path.join("splits", "train.json"))


def _resolved(path: str | os.PathLike) -> Path:
    return Path(path).expanduser().resolve()


def _same_file(a: Path, b: Path) -> bool:
    """Whether `a` and `b` name one file (also through links)."""
    if a == b:
        return True
    try:
        return a.exists() and b.exists() and os.path.samefile(a, b)
    except OSError:
        return False


def holding_dataset_folder(path: str | os.PathLike) -> Path | None:
    """The nearest folder above `path` that holds a dataset, if any."""
    for parent in _resolved(path).parents:
        if any((parent / marker).is_file() for marker in DATASET_MARKERS):
            return parent
    return None


def _inside(path: Path, folder: Path) -> bool:
    return path != folder and path.is_relative_to(folder)


def check_outputs(
    outputs: Mapping[str, str | os.PathLike | None],
    inputs: Iterable[str | os.PathLike | None] = (),
    *,
    folders: Iterable[str | os.PathLike] = (),
    directories: Iterable[str] = (),
) -> None:
    """Refuse, before anything is opened for writing, outputs that would
    overwrite or delete what a stage reads, with one line naming the output.

    `outputs` maps a role (out, checkpoint, ...) to its path; the roles in
    `directories` are folders the stage replaces whole. An output may not be
    an input, another output, an existing directory where a file goes, or
    lie inside a dataset folder (one of `folders`, or any folder holding a
    dataset marker); a replaced folder may hold no input.
    """
    for p in outputs.values():
        if p is not None and any(len(os.fsencode(part)) > NAME_MAX for part in Path(p).parts):
            raise input_error(p, f"has a file or folder name longer than {NAME_MAX} bytes; give a shorter path")
    given = {role: _resolved(p) for role, p in outputs.items() if p is not None}
    sources = [(p, _resolved(p)) for p in inputs if p is not None]
    dataset_folders = [_resolved(f) for f in folders]
    seen: dict[Path, str] = {}
    for role, out in given.items():
        name = outputs[role]
        for raw, src in sources:
            if _same_file(out, src):
                which = "" if str(raw) == str(name) else f" ({raw})"
                raise input_error(
                    name,
                    f"is also an input of this stage{which}; refusing to overwrite an input, "
                    "write the output elsewhere",
                )
            if role in directories and _inside(src, out):
                raise input_error(
                    name, f"holds the input {raw}; this stage replaces the whole folder, write the output elsewhere"
                )
        if out in seen:
            raise input_error(name, f"is given as both the {seen[out]} and the {role} output; give each its own path")
        seen[out] = role
        if role not in directories and out.is_dir():
            raise input_error(name, "is an existing directory; the output must be a file path")
        folder = next((f for f in dataset_folders if out == f or _inside(out, f)), None) or holding_dataset_folder(out)
        if folder is not None:
            raise input_error(
                name,
                f"lies inside the dataset folder {folder}; no stage writes into a dataset, "
                "write the output elsewhere (e.g. under results/)",
            )


def check_results_folder(results: str | os.PathLike, dataset_folders: Iterable[str | os.PathLike] = ()) -> None:
    """Refuse a results folder that is, or lies inside, a dataset folder (a
    link into one included), before the workflow creates anything in it."""
    resolved = _resolved(results)
    inside = [f for f in map(_resolved, dataset_folders) if f.is_dir() and (resolved == f or _inside(resolved, f))]
    folder = inside[0] if inside else holding_dataset_folder(resolved / "_")
    if folder is not None:
        link = f" (it links to {resolved})" if Path(results).is_symlink() else ""
        raise input_error(
            results,
            f"lies inside the dataset folder {folder}{link}; no stage writes into a dataset, "
            "make results/ a folder of its own",
        )


def unwritable_folder(path: str | os.PathLike) -> tuple[Path, str] | None:
    """(folder, reason) where `path` cannot be created or replaced: the
    nearest existing folder above it is read-only or not ours to write."""
    folder = Path(path).absolute().parent
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    if not folder.is_dir():
        return folder, "a file, not a folder"
    if os.access(folder, os.W_OK | os.X_OK):
        return None
    try:
        read_only = bool(os.statvfs(folder).f_flag & os.ST_RDONLY)
    except OSError:
        read_only = False
    return folder, "a read-only file system" if read_only else "no write permission"


def read_text_file(path: str | os.PathLike) -> str:
    """A UTF-8 text file's contents; a missing, unreadable or non-UTF-8 file is one line naming it."""
    p = Path(path)
    if not p.is_file():
        raise input_error(p, "no such file")
    try:
        return p.read_text(encoding="utf-8")
    except OSError as exc:
        raise input_error(p, f"cannot be read ({exc.strerror or exc})") from None
    except UnicodeDecodeError as exc:
        raise input_error(p, f"is not UTF-8 text (byte {exc.start})") from None


def check_writable(path: str | os.PathLike) -> None:
    """Refuse, before a long run, an output file that could not be written at its end:
    an existing folder, or a path whose nearest existing parent is not a writable folder."""
    p = Path(path)
    if p.is_dir():
        raise input_error(p, "is an existing directory; the output must be a file path")
    found = unwritable_folder(p)
    if found is not None:
        raise input_error(p, f"cannot be written: {found[0]} is not writable ({found[1]})")
