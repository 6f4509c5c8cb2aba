"""Synthetic FLAME-format heads and captures with ground truth (``sage synth``).

A procedural head is written in FLAME's own file layout (pickle, npz, region masks), posed with the
project's FLAME LBS, shaded with a procedural albedo and rendered by an independent z-buffer
rasterizer into a VHAP/GaussianAvatars-layout capture (docs/formats.md §1–2). ``tracking="exact"``
writes the truth's own parameters; ``"fitted"`` a truth beyond the written model with tracker-like
parameters (:mod:`.truth`, :mod:`.tracking`). ``appearance="detailed"`` adds prefiltered skin and
hair detail at the pixel scale (:mod:`.detail`, :mod:`.detail_render`) and a hair volume off the
scalp (:mod:`.hair`); ``"smooth"`` is the head of earlier versions.
"""

from __future__ import annotations

from pathlib import Path

from .appearance import Appearance, Render, Specular, crease_weights, render_head, sample_appearance
from .capture import Progress, canonical_vertices, make_subject, neck_line_mask, write_capture
from .config import PRESETS, REGIMES, TRACKING_MODES, SynthConfig, preset
from .head import EXPRESSION_NAMES, IDENTITY_NAMES, HeadModel, build_head
from .mesh_render import Fragments, rasterize, vertex_normals
from .model_files import MASKS_NAME, NPZ_NAME, PICKLE_NAME, flame_model_data, flame_pickle_dict, write_model_files


class CapturePath(type(Path())):  # type: ignore[misc]
    """The folder of a synthetic capture (a ``Path``) that also knows its model files."""

    @property
    def capture_dir(self) -> Path:
        """The capture folder as a plain Path."""
        return Path(self)

    @property
    def model_path(self) -> Path:
        """The FLAME-format model (project npz) written with the capture."""
        return capture_model_path(self, "npz")

    @property
    def masks_path(self) -> Path:
        """The capture's FLAME_masks.pkl."""
        return capture_model_path(self, "masks")


def make_capture(out_dir: str | Path, config: SynthConfig, progress: Progress | None = None) -> CapturePath:
    """Write a synthetic capture for ``config`` into ``out_dir`` (replacing it) and return the folder.

    progress(done, total, what) is called after every rendered image. The returned path also has
    ``model_path`` and ``masks_path``.
    """
    return CapturePath(write_capture(out_dir, config, progress=progress, force=True))


def capture_model_path(capture_dir: str | Path, kind: str = "npz") -> Path:
    """The FLAME-format model file of a synthetic capture: kind "npz", "pickle" or "masks"."""
    names = {"npz": NPZ_NAME, "pickle": PICKLE_NAME, "masks": MASKS_NAME}
    if kind not in names:
        raise ValueError(f"kind must be one of {', '.join(names)}, got {kind!r}")
    return Path(capture_dir) / "model" / names[kind]


__all__ = [
    "EXPRESSION_NAMES",
    "IDENTITY_NAMES",
    "PRESETS",
    "REGIMES",
    "TRACKING_MODES",
    "Appearance",
    "CapturePath",
    "Fragments",
    "HeadModel",
    "Progress",
    "Render",
    "Specular",
    "SynthConfig",
    "build_head",
    "capture_model_path",
    "canonical_vertices",
    "crease_weights",
    "flame_model_data",
    "flame_pickle_dict",
    "make_capture",
    "make_subject",
    "neck_line_mask",
    "preset",
    "rasterize",
    "render_head",
    "sample_appearance",
    "vertex_normals",
    "write_capture",
    "write_model_files",
]
