"""Exceptions shared by the engine and mapped to exit codes by the CLI."""

from __future__ import annotations

import errno
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


EXIT_INTERRUPTED = 130
"""Exit code of a run stopped by Ctrl-C or SIGTERM (it resumes from its last checkpoint)."""
EXIT_OUT_OF_MEMORY = 5
"""Exit code of a run that ran out of host or device memory."""

FILE_SYSTEM_ERRNOS: frozenset[int] = frozenset(
    (errno.EACCES, errno.EPERM, errno.EROFS, errno.ENOTDIR, errno.EISDIR, errno.EEXIST, errno.ENOSPC)
)
"""errno values of file-system refusals (permissions, read-only, a file where a folder belongs, a
full disk) that end a run with exit code 2 like an input error."""


def is_out_of_memory(e: BaseException) -> bool:
    """Whether ``e`` says the host or a device ran out of memory."""
    return isinstance(e, MemoryError) or (isinstance(e, RuntimeError) and "out of memory" in str(e).lower())


def exit_code_of(e: BaseException) -> int:
    """The exit code a run ends with when ``e`` stops it: a SageError's own code, 130 for an
    interrupt, 5 for out of memory, 2 for a file-system refusal, 1 for anything else."""
    if isinstance(e, SageError):
        return e.exit_code
    if isinstance(e, KeyboardInterrupt):
        return EXIT_INTERRUPTED
    if is_out_of_memory(e):
        return EXIT_OUT_OF_MEMORY
    if isinstance(e, OSError) and e.errno in FILE_SYSTEM_ERRNOS:
        return 2
    if isinstance(e, SystemExit):
        return e.code if isinstance(e.code, int) else 1
    return 1


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
