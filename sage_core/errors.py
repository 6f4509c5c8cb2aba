"""Exceptions shared by the engine and mapped to exit codes by the CLI."""

from __future__ import annotations

from pathlib import Path


class SageError(Exception):
    """Base class for errors the CLI reports as one clear line and a non-zero exit."""

    exit_code: int = 1


class InputError(SageError):
    """A user-supplied file or folder is missing, unreadable or malformed.

    Attributes:
        path: the offending file or folder.
        problem: what is wrong with it, in one sentence.
    """

    exit_code = 2

    def __init__(self, path: str | Path, problem: str) -> None:
        self.path = Path(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")


class ConfigError(SageError):
    """A configuration value or combination of options is invalid."""

    exit_code = 3


class StageError(SageError):
    """A stage cannot run: a missing, failed or stale earlier stage, or a locked workspace."""

    exit_code = 4


class UnsafeFileError(InputError):
    """A file in a format whose loading could run code (an old pickle-based sage file); it is
    refused without being loaded. The message says how to convert a trusted one."""

    exit_code = 2


class WorkspaceError(InputError):
    """The workspace folder cannot be used: its path is a file or lies under a file, or it is not
    writable."""

    exit_code = 2


def require_file(path: str | Path, what: str) -> None:
    """InputError unless ``path`` is an existing regular file: a folder, a device or a pipe is named
    as such, a missing path as "<what> not found"."""
    p = Path(path)
    if p.is_dir():
        raise InputError(p, f"is a folder, expected a {what}")
    if p.exists() and not p.is_file():
        raise InputError(p, f"is not a regular file (a device or pipe), expected a {what}")
    if not p.is_file():
        raise InputError(p, f"{what} not found")
