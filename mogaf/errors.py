"""User-facing errors: one line that names the file and what is wrong."""

from __future__ import annotations

import os


class MogafError(Exception):
    """An error caused by input or configuration, reported as a single line."""

    def __init__(self, message: str):
        # Keep it to one line: callers print it as is.
        super().__init__(" ".join(str(message).split()))


def input_error(path: str | os.PathLike, problem: str) -> MogafError:
    """Build the canonical `<file>: <what is wrong>` error."""
    return MogafError(f"{os.fspath(path)}: {problem}")


def refuse_unknown_params(section: str, params, known) -> None:
    """A key of `params` not in `known` is most likely a typo: refuse it by name."""
    unknown = sorted(set(params or ()) - set(known))
    if unknown:
        raise MogafError(
            f"{section}: unknown parameter(s) {', '.join(map(str, unknown))} "
            f"(known: {', '.join(sorted(map(str, known)))})"
        )
