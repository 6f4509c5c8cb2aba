"""Reading ``.npz`` archives (FLAME models, parameter and motion files) and naming array shapes in
the error messages about them."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .errors import InputError


def shape_str(shape: tuple[int, ...]) -> str:
    """An array shape as error messages write it: ``(5023,3)``."""
    return "(" + ",".join(str(s) for s in shape) + ")"


def read_npz(path: Path, what: str = "npz file") -> dict[str, np.ndarray]:
    """Every array of the ``.npz`` at ``path`` (no pickled objects), read into memory.

    what: names the file in the InputError when it is missing (``"<what> not found"``); a file that
    cannot be read as an npz archive raises InputError("cannot read npz (...)").
    """
    if not path.is_file():
        raise InputError(path, f"{what} not found")
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except Exception as exc:  # OSError, ValueError, EOFError, zipfile.BadZipFile from a corrupt archive
        raise InputError(path, f"cannot read npz ({type(exc).__name__}: {exc})") from None
