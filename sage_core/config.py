"""Per-stage configuration dataclasses, presets, and their load / merge / save / hash.

Precedence (design.md "Stage contract"): preset < config file < command-line flags. A config
file is YAML or JSON; it may hold one section per stage (``ingest:``, ``init_mesh:``, …) or, when
it is given to a single stage, that stage's keys at the top level. Nested fields are addressed
with dots in flags and as nested mappings in files. Unknown keys are errors, never ignored.

Every field carries its documentation in ``metadata["help"]``; the CLI shows it and the docs
list it. This module imports no heavy dependencies.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from .errors import ConfigError

PRESETS = ("tiny", "default")


def _f(default: Any, help: str, **kw: Any) -> Any:
    """A dataclass field with a help text."""
    if isinstance(default, (list, dict)):
        return field(default_factory=lambda d=default: json.loads(json.dumps(d)), metadata={"help": help}, **kw)
    return field(default=default, metadata={"help": help}, **kw)


def _sub(cls: type, help: str) -> Any:
    return field(default_factory=cls, metadata={"help": help})


# --------------------------------------------------------------------------------------------
# Stage configs
# --------------------------------------------------------------------------------------------


@dataclass
class IngestConfig:
    """``sage ingest``: read a VHAP/GaussianAvatars capture into the workspace."""

    regime: str = _f("mv-sf", "Reconstruction regime: mv-sf (one multiview timestep), mv-mf (all training timesteps), sv-hr (one camera, head turns), one-shot (one image).")
    timestep: int | None = _f(None, "Training timestep for mv-sf (default: the train timestep closest to a neutral face with the mouth slightly open).")
    camera: int | None = _f(None, "Camera index for sv-hr and one-shot when the capture has several cameras.")
    height: int | None = _f(None, "Resize images to this height (width keeps the aspect). Exclusive with downsample.")
    downsample: float | None = _f(None, "Divide the image size by this factor. Exclusive with height.")
    background: str = _f("white", "Background of the stored images: white (as exported) or black (recomposited with the mask).")


@dataclass
class HashGridConfig:
    """Multi-resolution hash encoding (instant-ngp conventions)."""

    n_levels: int = _f(16, "Number of levels L.")
    n_features: int = _f(2, "Features per level F.")
    log2_table: int = _f(19, "log2 of the hash table size T per level.")
    base_res: int = _f(16, "Coarsest resolution N_min.")
    max_res: int = _f(2048, "Finest resolution N_max.")


@dataclass
class SDFNetConfig:
    """SDF MLP on [x, enc(x)]."""

    hidden: int = _f(64, "Hidden width of the SDF MLP.")
    n_hidden_layers: int = _f(1, "Number of hidden layers.")
    feature_dim: int = _f(13, "Size of the latent feature vector z passed to the appearance network.")


@dataclass
class PretrainConfig:
    """SDF pretraining on the canonical FLAME mesh (rendering.md §8)."""

    steps: int = _f(3000, "Optimisation steps.")
    batch_size: int = _f(8192, "Sample points per step, split evenly over surface / near-surface / uniform samples.")
    bank_size: int = _f(200000, "Samples precomputed once per kind (surface, near, uniform).")
    lr_grid: float = _f(1e-2, "Adam learning rate of the hash table.")
    lr_mlp: float = _f(1e-3, "Adam learning rate of the MLP.")
    near_sigmas: list[float] = _f([0.005, 0.02], "Near-surface noise std, as fractions of the head size (two values).")
    truncation: float | None = _f(0.1, "Truncate |d| at this fraction of the head size in the value loss (none: no truncation).")
    w_value: float = _f(1.0, "Weight of the L1 signed-distance term.")
    w_normal: float = _f(1.0, "Weight of the normal term (1 - cos between the gradient and the mesh normal) on surface samples.")
    w_eikonal: float = _f(0.1, "Weight of the eikonal term.")
    confidence_band: float = _f(0.25, "Winding-number band around 0.5 over which a sample's sign weight rises from 0 to 1 (open meshes).")
    eval_samples: int = _f(20000, "Surface samples per mesh for the Chamfer distance.")


@dataclass
class InitMeshConfig:
    """``sage init-mesh``: canonical mesh, mouth interior, SDF pretrained on the mesh."""

    mouth_interior: bool = _f(True, "Add the mouth-interior mesh (cavity and teeth) rigged to the jaw.")
    bbox_padding: float = _f(0.25, "The SDF box is a cube around the canonical mesh whose half size is the mesh's largest half size times (1 + bbox_padding).")
    sphere_radius: float = _f(0.8, "Radius of the SDF's initial sphere relative to the box half size.")
    grid: HashGridConfig = _sub(HashGridConfig, "Hash grid of the SDF.")
    sdf: SDFNetConfig = _sub(SDFNetConfig, "SDF network.")
    pretrain: PretrainConfig = _sub(PretrainConfig, "Pretraining schedule.")
    mc_resolution: int = _f(256, "Marching-cubes grid resolution for the extracted zero level set.")
    checkpoint_every: int = _f(500, "Checkpoint interval in steps.")


STAGE_CONFIGS: dict[str, type] = {
    "ingest": IngestConfig,
    "init-mesh": InitMeshConfig,
}

# Preset overrides per stage, as dotted-key mappings applied over the dataclass defaults
# (the dataclass defaults are the ``default`` preset).
PRESET_OVERRIDES: dict[str, dict[str, dict[str, Any]]] = {
    "default": {},
    "tiny": {
        "ingest": {},
        "init-mesh": {
            "grid.n_levels": 8,
            "grid.log2_table": 14,
            "grid.base_res": 16,
            "grid.max_res": 256,
            "pretrain.steps": 600,
            "pretrain.batch_size": 4096,
            "pretrain.bank_size": 60000,
            "mc_resolution": 128,
            "checkpoint_every": 100,
        },
    },
}

T = TypeVar("T")


# --------------------------------------------------------------------------------------------
# Machinery
# --------------------------------------------------------------------------------------------


def section_name(stage: str) -> str:
    """The config-file section of a stage: ``init-mesh`` -> ``init_mesh``."""
    return stage.replace("-", "_")


def to_dict(cfg: Any) -> dict[str, Any]:
    """Plain nested dict of a config dataclass (JSON/YAML-safe)."""
    return dataclasses.asdict(cfg)


def config_hash(cfg: Any) -> str:
    """Stable sha256 (hex, 16 chars) of the canonical JSON form of a config."""
    blob = json.dumps(to_dict(cfg), sort_keys=True, separators=(",", ":")).encode()
    return hashlib.sha256(blob).hexdigest()[:16]


def _field_types(cls: type) -> dict[str, Any]:
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in dataclasses.fields(cls)}


def _coerce(value: Any, tp: Any, key: str) -> Any:
    """Convert a file/flag value to the annotated type, or raise ConfigError naming the key."""
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (typing.Union, getattr(__import__("types"), "UnionType", None)):
        if value is None or (isinstance(value, str) and value.lower() in ("none", "null")):
            if type(None) in args:
                return None
        errors = []
        for a in args:
            if a is type(None):
                continue
            try:
                return _coerce(value, a, key)
            except ConfigError as e:
                errors.append(str(e))
        raise ConfigError(f"{key}: cannot interpret {value!r} as {tp}")
    if origin in (list, tuple):
        if isinstance(value, str):
            value = [v for v in value.split(",") if v.strip()]
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{key}: expected a list, got {value!r}")
        inner = args[0] if args else Any
        return [(_coerce(v, inner, key) if inner is not Any else v) for v in value]
    if tp is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in ("true", "yes", "on", "1"):
            return True
        if isinstance(value, str) and value.lower() in ("false", "no", "off", "0"):
            return False
        if isinstance(value, int) and value in (0, 1):
            return bool(value)
        raise ConfigError(f"{key}: expected true/false, got {value!r}")
    if tp is int:
        if isinstance(value, bool):
            raise ConfigError(f"{key}: expected an integer, got {value!r}")
        try:
            f = float(value)
        except (TypeError, ValueError):
            raise ConfigError(f"{key}: expected an integer, got {value!r}") from None
        if not f.is_integer():
            raise ConfigError(f"{key}: expected an integer, got {value!r}")
        return int(f)
    if tp is float:
        if isinstance(value, bool):
            raise ConfigError(f"{key}: expected a number, got {value!r}")
        try:
            return float(value)
        except (TypeError, ValueError):
            raise ConfigError(f"{key}: expected a number, got {value!r}") from None
    if tp is str:
        if not isinstance(value, (str, int, float)):
            raise ConfigError(f"{key}: expected a string, got {value!r}")
        return str(value)
    return value


def _apply(cfg: Any, key: str, value: Any, where: str) -> None:
    """Set a dotted key on a (nested) config dataclass, with type checks."""
    parts = key.split(".")
    obj = cfg
    for i, p in enumerate(parts):
        types = _field_types(type(obj))
        if p not in types:
            known = ", ".join(sorted(types))
            raise ConfigError(f"{where}: unknown option '{'.'.join(parts[: i + 1])}' for {type(obj).__name__} (known: {known})")
        if i == len(parts) - 1:
            tp = types[p]
            if dataclasses.is_dataclass(tp):
                if not isinstance(value, dict):
                    raise ConfigError(f"{where}: '{key}' is a section; give a mapping")
                for k, v in value.items():
                    _apply(getattr(obj, p), str(k), v, where)
            else:
                setattr(obj, p, _coerce(value, tp, f"{where}: {key}"))
        else:
            obj = getattr(obj, p)
            if not dataclasses.is_dataclass(obj):
                raise ConfigError(f"{where}: '{'.'.join(parts[: i + 1])}' is not a section")


def _flatten(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        out[key] = v
    return out


def load_config_file(path: str | Path) -> dict[str, Any]:
    """Read a YAML or JSON config file into a mapping; errors name the file."""
    from .errors import InputError

    p = Path(path)
    if not p.is_file():
        raise InputError(p, "config file not found")
    text = p.read_text()
    try:
        if p.suffix.lower() == ".json":
            data = json.loads(text)
        else:
            import yaml

            data = yaml.safe_load(text)
    except Exception as e:  # noqa: BLE001 - report any parser failure as an input error
        raise InputError(p, f"cannot parse config: {e}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise InputError(p, "config file must hold a mapping")
    return data


def resolve_config(
    stage: str,
    preset: str = "default",
    file_data: dict[str, Any] | None = None,
    flags: dict[str, Any] | None = None,
    file_label: str = "config file",
) -> Any:
    """Build a stage's config: dataclass defaults < preset < file section < flags.

    Args:
        stage: stage name (key of ``STAGE_CONFIGS``).
        preset: ``tiny`` or ``default``.
        file_data: parsed config file (sectioned by stage, or flat for this stage).
        flags: dotted-key overrides from the command line; ``None`` values are ignored (unset flags).
    """
    if stage not in STAGE_CONFIGS:
        raise ConfigError(f"unknown stage '{stage}'")
    if preset not in PRESETS:
        raise ConfigError(f"unknown preset '{preset}' (choose from {', '.join(PRESETS)})")
    cfg = STAGE_CONFIGS[stage]()
    for k, v in PRESET_OVERRIDES[preset].get(stage, {}).items():
        _apply(cfg, k, v, f"preset {preset}")
    if file_data:
        sections = {section_name(s) for s in STAGE_CONFIGS}
        if any(k in sections for k in file_data):
            unknown = [k for k in file_data if k not in sections]
            if unknown:
                raise ConfigError(f"{file_label}: unknown section(s) {', '.join(map(repr, unknown))} (stages: {', '.join(sorted(sections))})")
            section = file_data.get(section_name(stage)) or {}
        else:
            section = file_data
        if not isinstance(section, dict):
            raise ConfigError(f"{file_label}: section '{section_name(stage)}' must be a mapping")
        for k, v in section.items():
            _apply(cfg, str(k), v, file_label)
    for k, v in (flags or {}).items():
        if v is None:
            continue
        _apply(cfg, k, v, "command line")
    return cfg


def from_dict(cls: type[T], data: dict[str, Any]) -> T:
    """Rebuild a config dataclass from its plain dict (e.g. a saved resolved config)."""
    cfg = cls()
    for k, v in data.items():
        _apply(cfg, k, v, f"saved {cls.__name__}")
    return cfg


def describe(cls: type, prefix: str = "") -> list[tuple[str, str, Any]]:
    """(dotted name, help, default) for every field, for docs and ``--help`` listings."""
    rows: list[tuple[str, str, Any]] = []
    inst = cls()
    for f in dataclasses.fields(cls):
        val = getattr(inst, f.name)
        if dataclasses.is_dataclass(val):
            rows.extend(describe(type(val), prefix=f"{prefix}{f.name}."))
        else:
            rows.append((f"{prefix}{f.name}", f.metadata.get("help", ""), val))
    return rows
