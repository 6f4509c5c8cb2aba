"""Configuration of a synthetic capture: resolution of the procedural head, cameras, timesteps."""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path
from typing import Any

from ...config import parse_bool
from ...errors import ConfigError

REGIMES = ("multiview", "monocular", "oneshot")
TRACKING_MODES = ("exact", "fitted")
APPEARANCES = ("detailed", "smooth")
NOVEL_AROUND_DEFAULT = 8
"""Held-out views all around the head that :func:`preset` gives detailed monocular and one-shot captures."""
MULTIVIEW_AROUND_DEFAULT = 6
"""Held-out views around the head that :func:`preset` gives detailed multiview captures (beside their
``novel_views`` off-arc views)."""
TRACKED_FIELDS = ("expr_keep", "corrective_scale", "crease_depth_mm", "specular", "pose_noise_deg", "trans_noise_mm",
                  "fit_iterations")
"""Fields that only matter for ``tracking="fitted"`` (left out of :meth:`SynthConfig.to_dict` for exact captures)."""


@dataclass(frozen=True)
class SynthConfig:
    """Everything that determines a synthetic capture (same config ⇒ byte-identical files).

    Attributes:
        regime: "multiview" (16 cameras, train/val/test like a NeRSemble export), "monocular"
            (one fixed camera, head turns, neutral expression) or "oneshot" (one frontal image).
        seed: identity, texture and expression sampling.
        width, height: image size in pixels (NeRSemble exports are 550×802).
        n_cameras: cameras on the arc in front of the head (multiview; camera 8 is frontal).
        train_timesteps: timesteps with mild expressions (train/val); monocular: head-turn
            frames of the training part of the clip; oneshot: exactly 1.
        test_timesteps: held-out timesteps after the training ones: novel (also strong)
            expressions on all cameras; monocular: later frames with novel yaw/pitch; oneshot: 0
            (its held-out views and expressions go to gt/novel/).
        head_rows, head_cols: grid resolution of the head surface (rows top→neck, columns around);
            tiny (56×72) gives ≈ 4.3k vertices, default (80×104) ≈ 8.9k.
        eye_rows, eye_cols: grid resolution of each eyeball.
        supersample: per-axis supersampling of the ground-truth renderer (anti-aliased edges and a
            fractional matte); 1 disables it.
        camera_distance: metres from the head centre to every multiview camera.
        view_height_m: vertical extent (metres) seen at the head centre by the multiview cameras.
        mono_focal: normalised monocular focal length (fl = mono_focal·max(w, h), docs/formats.md §1.6).
        novel_views: cameras of the held-out ground truth written to gt/ (monocular, oneshot).
        novel_expressions: held-out expressions of that ground truth (monocular, oneshot).
        tracking: "exact" — the written FLAME-format model and parameters are the ground truth;
            "fitted" — the ground truth deforms with more than the written model can express and
            the written parameters are a tracker-like least-squares fit plus pose noise.
        expr_keep: (fitted) fraction of the expression components kept in the written model
            (the leading ones; at least one).
        corrective_scale: (fitted) scale of the truth's non-linear correctives (lip roll, lip
            thinning with the jaw, cheek bulge, brow bunching); 0 disables them.
        crease_depth_mm: (fitted) inward displacement of the truth's expression creases at full
            compression (forehead lines, glabella, nasolabial folds), in millimetres.
        specular: (fitted) scale of the truth's Blinn-Phong highlights on skin and eyes; 0 = none.
        pose_noise_deg: (fitted) standard deviation of the tracker's rotation noise per axis of the
            head rotation, in degrees.
        trans_noise_mm: (fitted) typical length of the tracker's translation error in millimetres
            (per-axis standard deviation ``trans_noise_mm / √3``).
        fit_iterations: (fitted) Gauss–Newton iterations of the fit of the written model.
        appearance: "detailed" — pixel-scale skin detail (pores, freckles, moles, fine lines,
            optional stubble), brows, lashes and scalp hair as oriented strands, and hair volume
            off the scalp (fringe, bob or bun), all varying with the seed (docs/synthetic.md);
            "smooth" — the smooth head of earlier versions (same seed ⇒ the same bytes as they wrote).
        novel_around: (monocular, oneshot) held-out views added all around the head (sides, back,
            above) to the ``novel_views`` arc in front; 0 = the arc only (earlier versions).
            (multiview, with ``novel_multiview``) the views around the head added to its off-arc views.
        novel_multiview: (multiview) also write held-out ground truth to gt/novel/: the first training
            timestep, exactly as trained on (its written parameters too), seen by ``novel_views``
            cameras off the training arc (between its cameras, above and below it) and the
            ``novel_around`` views around the head; no held-out expressions (the test split has them).
            False = no gt/novel/ (earlier versions).
        skin_photo: (detailed) a one-photo capture of ``sage track`` (its folder) whose photograph
            becomes the face's skin (:mod:`.photo_skin`); the photo must be tracked with a
            FLAME-format model of the same head grid (``sage synth --preset`` of the same size).
            None: the procedural skin.
        skin_photo_model: that FLAME-format model (None: the one the capture's track report names).
    """

    regime: str = "multiview"
    seed: int = 0
    width: int = 550
    height: int = 802
    n_cameras: int = 16
    train_timesteps: int = 6
    test_timesteps: int = 8
    head_rows: int = 80
    head_cols: int = 104
    eye_rows: int = 12
    eye_cols: int = 20
    supersample: int = 2
    camera_distance: float = 1.0
    view_height_m: float = 0.42
    mono_focal: float = 2.6
    novel_views: int = 8
    novel_expressions: int = 4
    tracking: str = "exact"
    expr_keep: float = 0.6
    corrective_scale: float = 1.0
    crease_depth_mm: float = 2.0
    specular: float = 1.0
    pose_noise_deg: float = 0.4
    trans_noise_mm: float = 1.2
    fit_iterations: int = 3
    appearance: str = "smooth"
    novel_around: int = 0
    novel_multiview: bool = False
    skin_photo: str | None = None
    skin_photo_model: str | None = None

    def validate(self) -> "SynthConfig":
        """Raise ConfigError for impossible values; returns self."""
        if self.regime not in REGIMES:
            raise ConfigError(f"regime must be one of {', '.join(REGIMES)}, got '{self.regime}'")
        if self.width < 16 or self.height < 16:
            raise ConfigError(f"image size {self.width}x{self.height} is too small (at least 16x16)")
        if self.regime == "multiview" and not 1 <= self.n_cameras <= 64:
            raise ConfigError(f"cameras must be 1..64, got {self.n_cameras}")
        if self.train_timesteps < 1:
            raise ConfigError(f"train timesteps must be at least 1, got {self.train_timesteps}")
        if self.test_timesteps < 0:
            raise ConfigError(f"test timesteps must be >= 0, got {self.test_timesteps}")
        if self.regime == "oneshot" and (self.train_timesteps != 1 or self.test_timesteps != 0):
            raise ConfigError("the oneshot regime has exactly one training image (train 1, test 0)")
        if self.regime == "monocular" and self.train_timesteps < 2:
            raise ConfigError("the monocular regime needs at least 2 timesteps")
        if self.head_rows < 24 or self.head_cols < 32:
            raise ConfigError("head grid too coarse: need head_rows >= 24 and head_cols >= 32")
        if self.eye_rows < 4 or self.eye_cols < 6:
            raise ConfigError("eyeball grid too coarse: need eye_rows >= 4 and eye_cols >= 6")
        if not 1 <= self.supersample <= 4:
            raise ConfigError(f"supersample must be 1..4, got {self.supersample}")
        if self.camera_distance <= 0.3 or self.view_height_m <= 0.05 or self.mono_focal <= 0:
            raise ConfigError("camera_distance, view_height_m and mono_focal must be positive and sensible")
        if self.novel_views < 1 or self.novel_expressions < 1:
            raise ConfigError("novel_views and novel_expressions must be at least 1")
        if self.tracking not in TRACKING_MODES:
            raise ConfigError(f"tracking must be one of {', '.join(TRACKING_MODES)}, got '{self.tracking}'")
        if not 0.0 < self.expr_keep <= 1.0:
            raise ConfigError(f"expr_keep must be in (0, 1], got {self.expr_keep}")
        if min(self.corrective_scale, self.crease_depth_mm, self.specular, self.pose_noise_deg, self.trans_noise_mm) < 0:
            raise ConfigError("corrective_scale, crease_depth_mm, specular, pose_noise_deg and trans_noise_mm must be >= 0")
        if not 1 <= self.fit_iterations <= 50:
            raise ConfigError(f"fit_iterations must be 1..50, got {self.fit_iterations}")
        if self.appearance not in APPEARANCES:
            raise ConfigError(f"appearance must be one of {', '.join(APPEARANCES)}, got '{self.appearance}'")
        if not 0 <= self.novel_around <= 64:
            raise ConfigError(f"novel_around must be 0..64, got {self.novel_around}")
        if self.skin_photo is not None and self.appearance != "detailed":
            raise ConfigError("skin_photo needs the detailed appearance (--appearance detailed)")
        if self.skin_photo_model is not None and self.skin_photo is None:
            raise ConfigError("skin_photo_model is given without skin_photo")
        return self

    def to_dict(self) -> dict[str, Any]:
        """Plain-data form (JSON-safe). Exact captures leave out the fitted-only fields (and the
        mode), smooth ones the appearance and captures without views around the head
        ``novel_around``, so their files stay those of captures written before these existed."""
        d = asdict(self)
        if self.tracking == "exact":
            for k in ("tracking", *TRACKED_FIELDS):
                d.pop(k)
        if self.appearance == "smooth":
            d.pop("appearance")
        if self.novel_around == 0:
            d.pop("novel_around")
        if not self.novel_multiview:
            d.pop("novel_multiview")
        for k in ("skin_photo", "skin_photo_model"):
            if d[k] is None:
                d.pop(k)
            else:  # the folder's name: a capture carries no path of the machine that wrote it
                d[k] = Path(d[k]).name
        return d

    @staticmethod
    def from_dict(d: dict[str, Any]) -> "SynthConfig":
        """Inverse of :meth:`to_dict`; unknown keys raise ConfigError."""
        names = {f.name for f in fields(SynthConfig)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise ConfigError(f"unknown synth config key(s): {', '.join(unknown)}")
        return SynthConfig(**d).validate()

    def with_overrides(self, **kw: Any) -> "SynthConfig":
        """A copy with the given fields replaced (None values are ignored), validated."""
        kw = {k: v for k, v in kw.items() if v is not None}
        return replace(self, **kw).validate()


def parse_sets(items: list[str] | None) -> dict[str, Any]:
    """``["crease_depth_mm=3", "tracking=exact"]`` -> {"crease_depth_mm": 3.0, "tracking": "exact"},
    typed by the :class:`SynthConfig` field; unknown keys and bad values raise ConfigError."""
    types = {f.name: f.type for f in fields(SynthConfig)}
    out: dict[str, Any] = {}
    for item in items or []:
        key, sep, val = item.partition("=")
        key, val = key.strip(), val.strip()
        if not sep or key not in types:
            raise ConfigError(f"--set expects FIELD=VALUE with a synth config field ({', '.join(types)}), got '{item}'")
        tp = {"int": int, "float": float, "str": str, "bool": parse_bool, "str | None": str}[str(types[key])]
        try:
            out[key] = tp(val)
        except ValueError:
            raise ConfigError(f"--set {key}: '{val}' is not a valid {'bool (true or false)' if tp is parse_bool else tp.__name__}") from None
    return out


PRESETS: dict[str, SynthConfig] = {
    "tiny": SynthConfig(
        width=128,
        height=186,
        n_cameras=16,
        train_timesteps=2,
        test_timesteps=4,
        head_rows=56,
        head_cols=72,
        eye_rows=8,
        eye_cols=12,
        supersample=2,
        novel_views=6,
        novel_expressions=3,
    ),
    "small": SynthConfig(
        width=256,
        height=372,
        n_cameras=16,
        train_timesteps=2,
        test_timesteps=4,
        head_rows=64,
        head_cols=84,
        eye_rows=10,
        eye_cols=16,
        supersample=2,
        novel_views=6,
        novel_expressions=3,
    ),
    "default": SynthConfig(),
}


# Clip lengths that make sense per regime (applied before explicit overrides).
_REGIME_DEFAULTS: dict[tuple[str, str], dict[str, int]] = {
    ("tiny", "monocular"): {"train_timesteps": 8, "test_timesteps": 3},
    ("default", "monocular"): {"train_timesteps": 42, "test_timesteps": 18},
    ("tiny", "oneshot"): {"train_timesteps": 1, "test_timesteps": 0},
    ("small", "monocular"): {"train_timesteps": 8, "test_timesteps": 3},
    ("small", "oneshot"): {"train_timesteps": 1, "test_timesteps": 0},
    ("default", "oneshot"): {"train_timesteps": 1, "test_timesteps": 0},
}


def preset(name: str, regime: str = "multiview", **overrides: Any) -> SynthConfig:
    """A named preset ("tiny", "small" or "default") for a regime, with optional field overrides
    (None ignored). Detailed monocular and one-shot captures get :data:`NOVEL_AROUND_DEFAULT`
    held-out views around the head unless ``novel_around`` is given; detailed multiview captures
    get held-out views of their first training timestep (``novel_multiview``, with
    :data:`MULTIVIEW_AROUND_DEFAULT` views around the head) unless ``novel_multiview`` is given."""
    if name not in PRESETS:
        raise ConfigError(f"unknown synth preset '{name}' (choose from {', '.join(PRESETS)})")
    if regime not in REGIMES:
        raise ConfigError(f"regime must be one of {', '.join(REGIMES)}, got '{regime}'")
    base = replace(PRESETS[name], regime=regime, **_REGIME_DEFAULTS.get((name, regime), {}))
    cfg = base.with_overrides(**overrides)
    if cfg.appearance == "detailed" and regime != "multiview" and overrides.get("novel_around") is None:
        cfg = replace(cfg, novel_around=NOVEL_AROUND_DEFAULT).validate()
    if cfg.appearance == "detailed" and regime == "multiview" and overrides.get("novel_multiview") is None:
        cfg = replace(cfg, novel_multiview=True,
                      novel_around=MULTIVIEW_AROUND_DEFAULT if overrides.get("novel_around") is None else cfg.novel_around).validate()
    return cfg
