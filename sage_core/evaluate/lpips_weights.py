"""Assemble sage's LPIPS weights file (:mod:`sage_core.evaluate.lpips`) from the two published
sources, for ``sage lpips-weights``.

The file holds 15 tensors: torchvision's ImageNet AlexNet trunk ``features.{0,3,6,8,10}.*`` and
the LPIPS v0.1 linear heads ``lin.{0..4}.weight``. They come from

- the heads: ``lpips/weights/v0.1/alex.pth`` of the ``lpips`` 0.1.4 wheel (BSD-2-Clause), keyed
  ``lin{i}.model.1.weight``; given as that file, as the wheel, or fetched with ``pip download``;
- the trunk: torchvision's checkpoint ``alexnet-owt-7be5be79.pth`` (BSD-3-Clause), keyed
  ``features.*`` and ``classifier.*`` (the classifier is left out), which torchvision keeps in
  ``$TORCH_HOME/hub/checkpoints/`` (``~/.cache/torch/hub/checkpoints/``).

Every input is read with ``torch.load(..., weights_only=True)``; its keys and shapes are checked,
then its SHA-256 (the v0.0 heads and other AlexNets have the same keys and shapes). The merged
state dict is written atomically (default: the cache file :func:`~.lpips.find_lpips_weights`
searches) and loaded back through :meth:`~.lpips.LPIPS.from_path`. The bytes depend only on the
values, not on the output's name.
"""

from __future__ import annotations

import hashlib
import io
import os
import pickle
import shutil
import tempfile
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from ..atomic import atomic_write_bytes
from ..errors import InputError, require_file
from ..pip_fetch import download_wheel as pip_download
from ..workspace import file_sha256
from .lpips import DEFAULT_CACHE_PATH, ENV_VAR, EXPECTED_SHAPES, LPIPS, LPIPS_ALEX_SHA256, default_weights_path

HEADS_REQUIREMENT = "lpips==0.1.4"
HEADS_PACKAGE = "lpips 0.1.4"
HEADS_WHEEL_PATH = "lpips/weights/v0.1/alex.pth"
HEADS_SHA256 = "df73285e35b22355a2df87cdb6b70b343713b667eddbda73e1977e0c860835c0"
"""SHA-256 of ``lpips/weights/v0.1/alex.pth`` in the ``lpips`` 0.1.4 wheel."""
HEADS_KEYS: dict[str, str] = {f"lin{i}.model.1.weight": f"lin.{i}.weight" for i in range(5)}
"""Key in the lpips package's file -> key in sage's file."""

ALEXNET_FILE = "alexnet-owt-7be5be79.pth"
ALEXNET_URL = "https://download.pytorch.org/models/alexnet-owt-7be5be79.pth"
ALEXNET_SHA256 = "7be5be791159472b1fbf3c69796f7cb30dca7ad8466c2df70058c37116cdee02"
"""SHA-256 of torchvision's ImageNet AlexNet checkpoint (``AlexNet_Weights.IMAGENET1K_V1``)."""
ALEXNET_KEYS: dict[str, str] = {k: k for k in EXPECTED_SHAPES if k.startswith("features.")}
"""The trunk's keys, the same in torchvision's checkpoint and in sage's file."""

ALEXNET_HINT = (f"download {ALEXNET_URL} (233 MB) and pass it with --alexnet, or let torchvision fetch it "
                "once with `python -c \"import torchvision; torchvision.models.alexnet(weights='DEFAULT')\"`")

_LOAD_ERRORS = (RuntimeError, OSError, EOFError, ValueError, TypeError, AttributeError, KeyError,
                IndexError, pickle.UnpicklingError, zipfile.BadZipFile)
"""What ``torch.load`` raises on a file that is not a readable checkpoint."""


@dataclass(frozen=True)
class LpipsWeightsFile:
    """The file :func:`build_lpips_weights` wrote.

    path: where it was written. sha256: its SHA-256. heads, alexnet: where the two inputs came
    from. reference: whether its bytes are those of :data:`~.lpips.LPIPS_ALEX_SHA256`. eval_finds:
    how ``sage eval`` finds it (one phrase).
    """

    path: Path
    sha256: str
    heads: str
    alexnet: str
    reference: bool
    eval_finds: str

    def rows(self) -> list[tuple[str, str]]:
        """(label, value) rows of the command's closing panel."""
        digest = self.sha256 + (" (sage's reference LPIPS weights)" if self.reference else "")
        return [("linear heads", f"{self.heads}, keys, shapes and SHA-256 checked"),
                ("AlexNet", f"{self.alexnet}, keys, shapes and SHA-256 checked"),
                ("self-check", "loaded back by sage's LPIPS loader, 15 tensors equal"),
                ("sha256", digest),
                ("sage eval", self.eval_finds)]


def default_alexnet_path() -> Path:
    """Where torchvision keeps the checkpoint: ``<torch.hub.get_dir()>/checkpoints/alexnet-owt-7be5be79.pth``
    (``$TORCH_HOME/hub``, by default ``~/.cache/torch/hub``)."""
    return Path(torch.hub.get_dir()).expanduser() / "checkpoints" / ALEXNET_FILE


def resolve_alexnet(explicit: str | Path | None = None) -> Path:
    """The AlexNet checkpoint to read: ``explicit`` (``--alexnet``), else torchvision's cached copy.

    Raises InputError naming the file when the one named is not a file, or when nothing was named
    and torchvision's copy is absent (saying where to get it).
    """
    if explicit is not None and str(explicit) != "":
        p = Path(explicit).expanduser()
        require_file(p, "torchvision AlexNet checkpoint (--alexnet)")
        return p
    p = default_alexnet_path()
    if not p.is_file():
        raise InputError(p, f"torchvision's AlexNet checkpoint not found (no --alexnet given); {ALEXNET_HINT}")
    return p


def _load(source: Path | bytes, path: Path, what: str) -> Any:
    """``torch.load(..., weights_only=True)`` of a file or of bytes; InputError naming ``path`` otherwise."""
    try:
        return torch.load(io.BytesIO(source) if isinstance(source, bytes) else source,
                          map_location="cpu", weights_only=True)
    except _LOAD_ERRORS as e:
        raise InputError(path, f"{what} cannot be read as a PyTorch checkpoint ({e})") from e


def _take(sd: Any, keys: dict[str, str], path: Path, what: str, expected: str) -> dict[str, torch.Tensor]:
    """The tensors ``keys`` of ``sd`` under sage's names, float32 and compact, after checking that
    they are all there, floating point and of sage's shapes; other keys are ignored."""
    if not isinstance(sd, dict):
        raise InputError(path, f"{what}: expected a state dict, found {type(sd).__name__} ({expected})")
    missing = [k for k in keys if k not in sd]
    if missing:
        raise InputError(path, f"{what}: missing keys {missing} ({expected})")
    out: dict[str, torch.Tensor] = {}
    for src, dst in keys.items():
        v = sd[src]
        if not isinstance(v, torch.Tensor) or not v.is_floating_point():
            raise InputError(path, f"{what}: entry {src!r} is not a floating-point tensor")
        if tuple(v.shape) != EXPECTED_SHAPES[dst]:
            raise InputError(path, f"{what}: entry {src!r} has shape {tuple(v.shape)}, expected {EXPECTED_SHAPES[dst]}")
        out[dst] = v.detach().to(torch.float32).contiguous().clone()
    return out


def _check_sha256(digest: str, expected: str, path: Path, what: str, hint: str) -> None:
    if digest != expected:
        raise InputError(path, f"{what} has SHA-256 {digest[:16]}…, expected {expected[:16]}… ({hint})")


def read_heads(path: str | Path) -> dict[str, torch.Tensor]:
    """The five LPIPS v0.1 heads as ``lin.{i}.weight``, from ``alex.pth`` or from an ``lpips`` wheel
    (a ``.whl`` file, from which :data:`HEADS_WHEEL_PATH` is read).

    Raises InputError naming the file when it is missing or unreadable, lacks a key, has a wrong
    shape, or is not the lpips 0.1.4 file (SHA-256).
    """
    path = Path(path).expanduser()
    require_file(path, "LPIPS heads file (--heads)")
    expected = f"expected the lpips package's {HEADS_WHEEL_PATH}"
    if path.suffix.lower() == ".whl":
        try:
            with zipfile.ZipFile(path) as zf:
                if HEADS_WHEEL_PATH not in zf.namelist():
                    raise InputError(path, f"the wheel holds no {HEADS_WHEEL_PATH} (is it {HEADS_PACKAGE}?)")
                data = zf.read(HEADS_WHEEL_PATH)
        except (zipfile.BadZipFile, OSError) as e:
            raise InputError(path, f"not a wheel (zip) archive: {e}") from None
        what, digest = HEADS_WHEEL_PATH, hashlib.sha256(data).hexdigest()
        sd = _load(data, path, what)
    else:
        what, digest = "LPIPS heads file", file_sha256(path)
        sd = _load(path, path, what)
    heads = _take(sd, HEADS_KEYS, path, what, expected)
    _check_sha256(digest, HEADS_SHA256, path, what,
                  f"not {HEADS_PACKAGE}'s {HEADS_WHEEL_PATH}; the v0.0 heads have the same keys and shapes")
    return heads


def read_alexnet(path: str | Path) -> dict[str, torch.Tensor]:
    """The AlexNet trunk ``features.{0,3,6,8,10}.{weight,bias}`` of torchvision's checkpoint (its
    ``classifier.*`` left out).

    Raises InputError naming the file when it is missing or unreadable, lacks a key, has a wrong
    shape, or is not ``alexnet-owt-7be5be79.pth`` (SHA-256).
    """
    path = Path(path).expanduser()
    require_file(path, "torchvision AlexNet checkpoint (--alexnet)")
    what = "AlexNet checkpoint"
    trunk = _take(_load(path, path, what), ALEXNET_KEYS, path, what, f"expected torchvision's {ALEXNET_FILE}")
    _check_sha256(file_sha256(path), ALEXNET_SHA256, path, what, f"not torchvision's {ALEXNET_FILE}; {ALEXNET_HINT}")
    return trunk


def merge_state_dicts(heads: dict[str, torch.Tensor], trunk: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """sage's state dict: the 15 tensors in the order of :data:`~.lpips.EXPECTED_SHAPES`."""
    both = {**trunk, **heads}
    return {k: both[k] for k in EXPECTED_SHAPES}


def serialize(state: dict[str, torch.Tensor]) -> bytes:
    """``torch.save`` bytes of ``state``, written under the cache file's name so that the archive's
    inner folder, and so the bytes, do not depend on where the file goes."""
    with tempfile.TemporaryDirectory(prefix="sage-lpips-") as tmp:
        p = Path(tmp) / DEFAULT_CACHE_PATH.name
        torch.save(state, p)
        return p.read_bytes()


def download_wheel(folder: str | Path, pip: list[str] | None = None) -> Path:
    """Fetch the lpips 0.1.4 wheel with ``pip download`` into ``folder``; returns the wheel's path.

    pip: the command that runs pip (default: this interpreter's ``-m pip``). Raises InputError with
    pip's last lines when the download fails (no network, no index).
    """
    return pip_download(HEADS_REQUIREMENT, folder, "lpips-*.whl", ("--only-binary=:all:",), pip,
                        hint="fetch the wheel elsewhere and pass it with --heads")


def _eval_finds(out: Path) -> str:
    """How ``sage eval`` finds ``out`` without --lpips-weights, or what it takes to make it."""
    env = os.environ.get(ENV_VAR, "")
    if env:
        if Path(env).expanduser().resolve() == out.resolve():
            return f"finds it through ${ENV_VAR}"
        return f"${ENV_VAR} names {env}, which it reads instead; pass --lpips-weights {out}"
    if default_weights_path().resolve() == out.resolve():
        return "finds it in its cache folder"
    return f"pass --lpips-weights {out} or set ${ENV_VAR}"


def build_lpips_weights(
    heads: str | Path | None = None,
    alexnet: str | Path | None = None,
    out: str | Path | None = None,
    force: bool = False,
    pip: list[str] | None = None,
) -> LpipsWeightsFile:
    """Merge the lpips heads and torchvision's AlexNet trunk into sage's LPIPS weights file.

    heads: ``alex.pth`` or an ``lpips`` wheel; None fetches the wheel with :func:`download_wheel`
    (``pip``) into a temporary folder, removed after. alexnet: torchvision's checkpoint (default
    :func:`default_alexnet_path`). out: the file to write (default the cache file
    ``~/.cache/sage/lpips_alex_v0.1.pth``); an existing one is replaced only with ``force``.

    Every input is checked before anything is written; the file is written atomically and loaded
    back through :meth:`LPIPS.from_path`. Raises InputError naming the file at fault.
    """
    target = Path(out).expanduser() if out is not None and str(out) != "" else default_weights_path()
    if target.is_dir():
        raise InputError(target, "is a folder, expected the path of the LPIPS weights file to write (--out)")
    if target.exists() and not force:
        raise InputError(target, "already exists; pass --force to replace it")
    alexnet_path = resolve_alexnet(alexnet)
    if heads is not None and str(heads) != "":
        heads_sd, heads_from = read_heads(heads), str(Path(heads).expanduser())
    else:
        tmp = Path(tempfile.mkdtemp(prefix="sage-lpips-"))
        try:
            heads_sd, heads_from = read_heads(download_wheel(tmp, pip)), f"{HEADS_PACKAGE} wheel (pip download)"
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    state = merge_state_dicts(heads_sd, read_alexnet(alexnet_path))
    atomic_write_bytes(target, serialize(state))
    back = LPIPS.from_path(target).state_dict()
    if any(not torch.equal(back[k], v) for k, v in state.items()):
        raise InputError(target, "reads back different values from those written (a damaged disk or file system?)")
    digest = file_sha256(target)
    return LpipsWeightsFile(target, digest, heads_from, str(alexnet_path), digest == LPIPS_ALEX_SHA256, _eval_finds(target))
