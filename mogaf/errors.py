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
