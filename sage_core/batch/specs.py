"""The job of one batch subject: the chain's arguments as plain data, and the key of its results."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

from ..errors import InputError
from .subjects import Subject


def subject_spec(subject: Subject, root: Path, opts: dict[str, Any], subjects_file: Path) -> dict[str, Any]:
    """The :func:`sage_core.stages.run_pipeline` arguments of one subject (plain JSON data: the job
    file its worker reads) with its ``run_key``.

    opts: the batch defaults (``flame_model``, ``flame_masks``, ``regime``, ``downsample``,
    ``height``, ``background``, ``sets``, ``skip_phase2``, ``lpips_weights``, ``preset``, ``config``,
    ``seed``, ``force``); the subject's own fields win. ``run_key`` hashes everything that decides the
    results (options, stages, fingerprints of the capture's transforms, config file and FLAME files),
    so a subject whose key is unchanged and whose stages are complete is not run again. InputError
    naming ``subjects_file`` when the subject has no FLAME model.
    """
    from ..stages import pipeline_stages, split_sets

    flame_model = subject.flame_model or opts["flame_model"]
    if flame_model is None:
        raise InputError(subjects_file, f"subject {subject.id!r}: no FLAME model (give --flame-model or a flame_model field)")
    flame_masks = subject.flame_masks or opts["flame_masks"]
    ingest_flags = {
        "regime": subject.regime or opts["regime"],
        "timestep": subject.timestep,
        "camera": subject.camera,
        "downsample": opts["downsample"],
        "height": opts["height"],
        "background": opts["background"],
    }
    sets = split_sets([*(opts["sets"] or []), *subject.sets])
    spec: dict[str, Any] = {
        "id": subject.id,
        "dataset": str(Path(subject.capture).resolve()),
        "ws": str((root / subject.id).resolve()),
        "flame_model": str(Path(flame_model).resolve()),
        "flame_masks": None if flame_masks is None else str(Path(flame_masks).resolve()),
        "ingest_flags": ingest_flags,
        "skip_phase2": opts["skip_phase2"],
        "lpips_weights": None if opts["lpips_weights"] is None else str(Path(opts["lpips_weights"]).resolve()),
        "preset": opts["preset"],
        "config": None if opts["config"] is None else str(Path(opts["config"]).resolve()),
        "sets": sets,
        "seed": opts["seed"],
        "stages": pipeline_stages(opts["skip_phase2"]),
    }
    spec["fingerprints"] = _input_fingerprints(spec)
    spec["run_key"] = hashlib.sha256(json.dumps(spec, sort_keys=True).encode()).hexdigest()[:16]
    spec["force"] = opts["force"]
    return spec


def _input_fingerprints(spec: dict[str, Any]) -> dict[str, str]:
    """Fingerprints of the files a subject's run reads besides its workspace: the capture's
    transforms*.json and the config file (content), the FLAME model and masks (size and time)."""
    from ..workspace import file_fingerprint

    out: dict[str, str] = {}
    dataset = Path(spec["dataset"])
    for p in sorted(dataset.glob("transforms*.json")):
        out[p.name] = file_fingerprint(p)
    if spec["config"] is not None:
        out["config"] = file_fingerprint(spec["config"])
    for key in ("flame_model", "flame_masks"):
        if spec[key] is not None:
            out[key] = file_fingerprint(spec[key], content=False)
    return out
