"""sage engine: animatable 2D Gaussian surfel head avatars (SAGE).

The engine never prints; it reports progress through callbacks. Heavy dependencies (torch) are
imported by the modules that need them, so importing :mod:`sage_core` itself is cheap: the names
below are loaded on first use (PEP 562).

A small flat API (``import sage_core as sage``; ``examples/python_api.py`` shows it at work):

* ``sage.load_avatar(path, stage="auto", device="cpu")`` -> :class:`Avatar` from a workspace, a bundle
  folder or an avatar file, with the render settings its stage trained with;
* ``avatar.pose(flame=None, row=0, *, view_from=None, **overrides)`` -> :class:`PosedSurfels`
  (means (N, 3), quats (N, 4) wxyz, scales (N, 2), opacities (N,), colors (N, 3), vertices (V, 3));
* ``sage.render_avatar(avatar, camera, flame=None, row=0, *, background=None, backend="auto",
  **overrides)`` -> :class:`RenderOutput` (image (H, W, 3), alpha (H, W), depth (H, W), normal
  (H, W, 3)); not ``sage.render``, which is the rasterizer package :mod:`sage_core.render`;
* ``sage.load_cameras(path)`` -> {index: :class:`Camera`}, ``sage.reference_camera(path)`` -> Camera;
  ``sage.RenderCamera`` (torch tensors, unbatched or batched);
* ``sage.FlameParams``, ``sage.load_flame_params(path)`` (a motion ``.npz``, a folder of per-frame
  files or a capture);
* ``sage.load_config(path)`` (YAML/JSON mapping), ``sage.resolve_config(stage, preset, file_data,
  flags)`` (the CLI's config resolution), ``sage.PRESETS``, ``sage.STAGE_CONFIGS``;
* ``sage.run_pipeline(capture, ws, flame_model, preset=..., config_file=...)`` (what ``sage run``
  does), ``sage.StageSettings`` (seed, device, force, threads), ``sage.StageEvent`` (the progress
  events stages report), ``sage.workspace_regime(ws)``; one function per stage in
  :mod:`sage_core.stages` (``phase1_stage(ws, cfg, settings)``, ...);
* ``sage.read_image(path)`` -> (H, W, C) float32 [0, 1], ``sage.write_image(path, image)`` (atomic);
* errors: ``sage.SageError`` and its subclasses ``InputError``, ``ConfigError``, ``StageError``.

FLAME parameters (overrides): ``expr`` (E,), ``rotation``, ``neck_pose``, ``jaw_pose``,
``translation`` (3,) (axis-angle radians, metres), ``eyes_pose`` (6,).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from ._version import __version__

_EXPORTS: dict[str, tuple[str, str]] = {
    # avatars
    "load_avatar": ("sage_core.api", "load_avatar"),
    "render_avatar": ("sage_core.api", "render_avatar"),
    "RenderOutput": ("sage_core.api", "RenderOutput"),
    "Avatar": ("sage_core.avatar.model", "Avatar"),
    "PosedSurfels": ("sage_core.avatar.posing", "PosedSurfels"),
    # cameras
    "Camera": ("sage_core.data.cameras", "Camera"),
    "RenderCamera": ("sage_core.render._camera", "RenderCamera"),
    "load_cameras": ("sage_core.api", "load_cameras"),
    "reference_camera": ("sage_core.api", "reference_camera"),
    # FLAME parameters
    "FlameParams": ("sage_core.flame.params", "FlameParams"),
    "load_flame_params": ("sage_core.api", "load_flame_params"),
    # configuration
    "load_config": ("sage_core.config", "load_config_file"),
    "resolve_config": ("sage_core.config", "resolve_config"),
    "PRESETS": ("sage_core.config", "PRESETS"),
    "STAGE_CONFIGS": ("sage_core.config", "STAGE_CONFIGS"),
    # stages (sage_core.stages has one function per stage: ingest_stage, phase1_stage, ...)
    "StageSettings": ("sage_core.stages", "StageSettings"),
    "StageEvent": ("sage_core.stages", "StageEvent"),
    "run_pipeline": ("sage_core.stages", "run_pipeline"),
    "workspace_regime": ("sage_core.stages", "workspace_regime"),
    # images
    "read_image": ("sage_core.data.imageio", "read_image"),
    "write_image": ("sage_core.data.imageio", "write_image"),
    # errors
    "SageError": ("sage_core.errors", "SageError"),
    "InputError": ("sage_core.errors", "InputError"),
    "ConfigError": ("sage_core.errors", "ConfigError"),
    "StageError": ("sage_core.errors", "StageError"),
}

__all__ = ["__version__", *sorted(_EXPORTS)]


def __getattr__(name: str) -> Any:
    """Load a name of the flat API on first use (module attributes are looked up here only when
    they are not defined yet)."""
    target = _EXPORTS.get(name)
    if target is None:
        raise AttributeError(f"module 'sage_core' has no attribute {name!r}")
    value = getattr(importlib.import_module(target[0]), target[1])
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))


if TYPE_CHECKING:
    from .api import RenderOutput, load_avatar, load_cameras, load_flame_params, reference_camera, render_avatar
    from .avatar.model import Avatar
    from .avatar.posing import PosedSurfels
    from .config import PRESETS, STAGE_CONFIGS, resolve_config
    from .config import load_config_file as load_config
    from .data.cameras import Camera
    from .data.imageio import read_image, write_image
    from .errors import ConfigError, InputError, SageError, StageError
    from .flame.params import FlameParams
    from .render._camera import RenderCamera
    from .stages import StageEvent, StageSettings, run_pipeline, workspace_regime
