"""Reading ``.npz`` archives (FLAME models, parameter and motion files) and naming array shapes in
the error messages about them."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .errors import InputError, require_file


def shape_str(shape: tuple[int, ...]) -> str:
    """An array shape as error messages write it: ``(5023,3)``."""
    return "(" + ",".join(str(s) for s in shape) + ")"


def read_npz(path: Path, what: str = "npz file") -> dict[str, np.ndarray]:
    """Every array of the ``.npz`` at ``path`` (plain arrays only), read into memory.

    The file must be a zip archive of ``.npy`` arrays: anything else (a pickle, a text file) is
    refused before numpy looks at it, and an array of Python objects is refused by name.
    what: names the file in the InputError ("<what> not found", "is a folder, expected a <what>").
    """
    require_file(path, what)
    try:
        with open(path, "rb") as fh:
            magic = fh.read(4)
    except OSError as exc:
        raise InputError(path, f"cannot read {what} ({exc.strerror or exc})") from None
    if not magic.startswith(b"PK"):
        raise InputError(path, f"is not an npz archive (a zip of numpy arrays), so it cannot be the {what}")
    out: dict[str, np.ndarray] = {}
    try:
        with np.load(path, allow_pickle=False) as z:
            for k in z.files:
                try:
                    out[k] = z[k]
                except ValueError as exc:
                    if "allow_pickle" in str(exc) or "pickled" in str(exc):
                        raise InputError(path, f"array '{k}' holds Python objects, which sage does not load") from None
                    raise
    except InputError:
        raise
    except Exception as exc:  # OSError, ValueError, EOFError, zipfile.BadZipFile from a corrupt archive
        raise InputError(path, f"cannot read npz ({type(exc).__name__}: {exc})") from None
    return out
