"""The benchmark rows, the two sizes, and the plan of CLI steps that produces every row.

A plan is an ordered list of :class:`Step`: ``sage`` commands run in subprocesses, plus two
in-process steps (copying finished stage folders from a row's base workspace, and writing the
test-split motion for ``sage reenact``). Each step has a unique key; rows list the keys they need,
so steps shared by several rows (the synthetic capture, the SAGE phase-1 avatar) run once.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

SDF_OFF_FROM = 1_000_000_000
"""``sdf_from`` of the GaussianAvatars-style rows: past any iteration count, so phase 1 never adds
L_pt, L_align, NeuS depth/normal/RGB, eikonal or smoothness terms."""

FREE_PHASE1: tuple[str, ...] = (
    "--attributes", "free",
    "--set", f"sdf_from={SDF_OFF_FROM}",
    "--set", "w_normal_consistency=0",
    "--set", "w_distortion=0",
    "--set", "w_mask=0",
    "--set", "shading=none",
    "--set", "relocate.enabled=false",
)  # fmt: skip
"""Phase-1 options of free per-surfel attributes trained on the photometric loss only (no SDF
terms, no 2DGS regularizers, no alpha mask term, no relocation) with colours fixed in head space
(no world light), on SAGE's surfel layout and rebinding: the ``free_mvsf`` row."""

GA_PHASE1: tuple[str, ...] = (
    *FREE_PHASE1,
    "--set", "mouth_prior=false",
    "--set", "init_layout=per_face",
    "--set", "init_opacity=0.1",
    "--set", "rebind_every=0",
    "--set", "densify=true",
    "--set", "w_local_position=0.01",
    "--set", "w_local_scale=1",
)  # fmt: skip
"""Phase-1 options of the GaussianAvatars baseline (Qian et al., CVPR 2024) on 2D surfels: one
surfel per FLAME triangle (teeth included, no mouth cavity: :data:`GA_INIT_MESH`) at GA's initial
opacity 0.1, adaptive density control with binding inheritance and no rebinding, GA's local
position (λ 0.01, threshold 1) and scale (λ 1, threshold 0.6) terms, photometric loss only. The
density-control schedule is the size's (:attr:`Size.densify`, :func:`ga_schedule`); the rest of
the density control (thresholds, opacity reset at the start, the position rate scaled by the scene
extent) is the ``densify`` section's defaults. docs/results.md compares every item with GA's code."""

GA_INIT_MESH: tuple[str, ...] = ("--set", "mouth_cavity=false")
"""init-mesh options of the GaussianAvatars rows: FLAME with teeth, no mouth cavity."""


@dataclass(frozen=True)
class RowSpec:
    """One row of the benchmark.

    capture: the capture kind it trains on (a key of :data:`CAPTURES`: "multiview", "monocular"
    and "oneshot" are tracked captures, "multiview_exact" the exact multiview one).
    regime: ``sage ingest --regime``. base: row whose workspace this row copies ``copy_stages``
    from (None: the row ingests itself). phase1 / phase2: extra options of the row's own phase-1 /
    phase-2 run (None: not run by this row). eval_stage: avatar evaluated. eval_splits: one
    ``sage eval --split`` run each. has_sdf: the row has a trained SDF (geometry metrics).
    reenact: drive the avatar with the test-split motion (needs a test split). init_mesh: extra
    options of the row's own init-mesh run. densify: add the size's density-control schedule to
    the row's phase 1. ceiling: the row is its capture's tracking ceiling
    (:mod:`sage_core.evaluate.ceiling`): nothing is trained, each split of ``eval_splits`` is the
    ground truth's appearance rendered on the tracked FLAME fit of the ingested data.
    """

    id: str
    label: str
    input_type: str
    capture: str
    regime: str
    base: str | None
    copy_stages: tuple[str, ...]
    phase1: tuple[str, ...] | None
    phase2: tuple[str, ...] | None
    eval_stage: str
    eval_splits: tuple[str, ...]
    has_sdf: bool
    reenact: bool
    init_mesh: tuple[str, ...] = ()
    densify: bool = False
    ceiling: bool = False


ROWS: dict[str, RowSpec] = {
    r.id: r
    for r in (
        RowSpec("sage", "SAGE", "MV-SF", "multiview", "mv-sf", None, (), ("--attributes", "mlp"), (), "phase2", ("all",), True, True),
        RowSpec("sage_exact", "SAGE on the exact capture", "MV-SF", "multiview_exact", "mv-sf", None, (), ("--attributes", "mlp"), (),
                "phase2", ("all",), True, True),
        RowSpec("no_mlp", "w/o attribute MLPs", "MV-SF", "multiview", "mv-sf", "sage", ("ingest", "init-mesh"),
                ("--attributes", "free"), (), "phase2", ("all",), True, True),
        RowSpec("no_phase2", "w/o phase 2", "MV-SF", "multiview", "mv-sf", "sage", ("ingest", "init-mesh", "phase1"),
                None, None, "phase1", ("all",), True, True),
        RowSpec("no_correction", "w/o correction", "MV-SF", "multiview", "mv-sf", "sage", ("ingest", "init-mesh", "phase1"),
                None, ("--correction", "off"), "phase2", ("all",), True, True),
        RowSpec("no_wrinkles", "w/o wrinkle shading", "MV-SF", "multiview", "mv-sf", "sage", ("ingest", "init-mesh", "phase1"),
                None, ("--set", "wrinkle_shading=false"), "phase2", ("all",), True, False),
        RowSpec("no_relocation", "w/o relocation", "MV-SF", "multiview", "mv-sf", "sage", ("ingest", "init-mesh"),
                ("--attributes", "mlp", "--set", "relocate.enabled=false"), (), "phase2", ("all",), True, False),
        RowSpec("no_light", "w/o world light (colour in head space)", "MV-SF", "multiview", "mv-sf", "sage", ("ingest", "init-mesh"),
                ("--attributes", "mlp", "--set", "shading=none"), (), "phase2", ("all",), True, False),
        RowSpec("ga_mvsf", "GaussianAvatars (per-face init, densification)", "MV-SF", "multiview", "mv-sf", "sage", ("ingest",),
                GA_PHASE1, None, "phase1", ("all",), False, True, GA_INIT_MESH, True),
        RowSpec("ga_mvmf", "GaussianAvatars (per-face init, densification)", "MV-MF", "multiview", "mv-mf", None, (),
                GA_PHASE1, None, "phase1", ("all",), False, True, GA_INIT_MESH, True),
        RowSpec("free_mvsf", "Free surfels on SAGE's layout (photometric only)", "MV-SF", "multiview", "mv-sf", "sage", ("ingest", "init-mesh"),
                FREE_PHASE1, None, "phase1", ("all",), False, True),
        RowSpec("ceiling", "Ground truth on the tracked FLAME fit (tracking ceiling)", "—", "multiview", "mv-sf", "sage", ("ingest",),
                None, None, "ceiling", ("test",), False, False, ceiling=True),
        RowSpec("sv_hr", "SAGE", "SV-HR", "monocular", "sv-hr", None, (), ("--attributes", "mlp"), (), "phase2", ("novel", "test"), True, True),
        RowSpec("one_shot", "SAGE", "One-shot", "oneshot", "one-shot", None, (), ("--attributes", "mlp"), (), "phase2", ("novel",), True, False),
    )
}  # fmt: skip
"""Every row id, in table order."""

CAPTURES: dict[str, tuple[str, str]] = {
    "multiview": ("multiview", "fitted"),
    "multiview_exact": ("multiview", "exact"),
    "monocular": ("monocular", "fitted"),
    "oneshot": ("oneshot", "fitted"),
}
"""Capture kind -> (``sage synth --regime``, ``--tracking``). Rows train on tracked captures
(FLAME parameters fitted to a truth the written model cannot fully express, plus pose noise);
``multiview_exact`` (the ``sage_exact`` row) is the capture whose parameters are the truth."""

ROW_IDS: tuple[str, ...] = tuple(ROWS)


@dataclass(frozen=True)
class Size:
    """A benchmark size (named after its stage preset): the stage preset, the synthetic capture and per-stage ``--set`` overrides.

    densify: the ``key=value`` density-control schedule of the rows that densify (GaussianAvatars),
    scaled to the preset's phase-1 length. budget: phase-1 ``key=value`` items of the rows that do
    not densify (the surfel count they get, about the one the densifying rows reach). synth_args: extra ``sage synth`` options per regime (shared by the tracked and exact captures). sets: stage -> ``key=value`` items
    added to every run of that stage. motion_steps: frames from one test timestep to the next in
    the reenactment clip.
    """

    name: str
    preset: str
    synth_preset: str
    synth_args: dict[str, tuple[str, ...]]
    sets: dict[str, tuple[str, ...]]
    motion_steps: int
    smoke: bool = False
    densify: tuple[str, ...] = ()
    budget: tuple[str, ...] = ()


def _densify(start: int, every: int, stop: int, reset: int) -> tuple[str, ...]:
    return (f"densify_from={start}", f"densify_every={every}", f"densify_until={stop}", f"opacity_reset_every={reset}")


GA_ITERATIONS = 600_000
"""GaussianAvatars' run length. Its density control starts after step 10,000 (1/60 of the run),
densifies every 2,000 steps (1/300), resets the opacities every 60,000 (1/10) and at the start, and
runs to the end of training."""

MIN_DENSIFY_EVERY = 100
"""Fewest steps between two densifications at any size: 3DGS's interval, and GaussianAvatars' own
fraction (1/300) of the full size's 30,000 steps. The learning rates are GA's per-step rates at every
size, so the optimiser needs as many steps to respond to a densification in a short run as in a long
one; 1/300 of the tiny run would densify every 5 steps."""

MIN_RESET_EVERY = 500
"""Fewest steps between two opacity resets at any size. A reset costs the same number of steps in a
short run as in a long one (the opacity rate is GA's 0.05 per step): on the tiny capture the training
PSNR fell to 21 dB after the reset at step 500 and was back to 34 dB at step 549 and 37 dB near 590,
so 1/10 of the tiny run (150 steps) would spend a third or more of every interval recovering."""


def ga_schedule(iterations: int) -> tuple[str, ...]:
    """GaussianAvatars' density-control schedule scaled to a phase 1 of ``iterations`` steps: its
    start (1/60), interval (1/300) and reset interval (1/10) as fractions of the run, the intervals no
    shorter than :data:`MIN_DENSIFY_EVERY` and :data:`MIN_RESET_EVERY`, densifying to the end."""
    start = round(iterations * 10_000 / GA_ITERATIONS)
    every = max(MIN_DENSIFY_EVERY, round(iterations * 2_000 / GA_ITERATIONS))
    reset = max(MIN_RESET_EVERY, round(iterations * 60_000 / GA_ITERATIONS))
    return _densify(start, every, iterations, reset)


def preset_iterations(preset: str) -> int:
    """Phase 1's iterations of a stage preset."""
    from sage_core.config import resolve_config

    return int(resolve_config("phase1", preset, None, {}).iterations)


TINY_SURFELS = 25_000
"""Surfels of the rows on SAGE's layout at the tiny size (the tiny preset has 6,000): the count the
GaussianAvatars row reached by densification on the tiny tracked capture with the earlier,
3DGS-shaped schedule (25,470), so that the rows compare methods at about one budget. On GA's own
schedule (:func:`ga_schedule`) it ends with 19,875."""

SMALL_SURFELS = 47_000
"""Surfels of the rows that do not densify at the small size (the small preset has 20,000): about the
count the GaussianAvatars row reaches by densification from the preset's count on GA's schedule on
the small detailed capture (47,375 on the first subject), so that the rows compare methods at one
budget, as at the tiny size."""

_PHASE2_EVAL = ("eval_phase1=false", "eval_frames=4")
"""Phase 2's own evaluation is cut to a few frames: the suite's numbers come from ``sage eval``."""

SIZES: dict[str, Size] = {
    "tiny": Size("tiny", "tiny", "tiny", {"multiview": (), "monocular": (), "oneshot": ()},
                 {"phase1": (f"n_surfels={TINY_SURFELS}",), "phase2": _PHASE2_EVAL}, 8, densify=ga_schedule(preset_iterations("tiny"))),
    "small": Size("small", "small", "small", {"multiview": (), "monocular": (), "oneshot": ()}, {"phase2": _PHASE2_EVAL}, 8,
                  densify=ga_schedule(preset_iterations("small")), budget=(f"n_surfels={SMALL_SURFELS}",)),
    "full": Size("full", "default", "default", {"multiview": (), "monocular": (), "oneshot": ()}, {"phase2": _PHASE2_EVAL}, 8,
                 densify=ga_schedule(preset_iterations("default"))),
}
"""Density-control schedules (:func:`ga_schedule`): GaussianAvatars' at ``full`` (after 500, every 100,
to the end of the 30,000 steps, opacity resets at 500 and every 3,000); at ``tiny`` (1,500 steps) after
25, every 100, resets at 25, 500 and 1,000; at ``small`` (4,000) after 67, every 100, resets at 67 and
every 500."""

SMOKE_SETS: dict[str, tuple[str, ...]] = {
    "init-mesh": ("pretrain.steps=20", "pretrain.bank_size=4000", "pretrain.batch_size=1024", "pretrain.eval_samples=2000", "mc_resolution=32"),
    "phase1": ("iterations=4", "n_surfels=800", "eval_every=0", "mc_resolution=32", "rays_per_step=64", "neus_samples=8", "neus_importance=8"),
    "phase2": ("iterations=2", "rays_per_step=64", "neus_samples=8", "neus_importance=8", *_PHASE2_EVAL),
    "eval": ("samples=1",),
}
"""``--smoke``: a machinery check with a few steps per stage (numbers are not representative)."""


def smoke_size(size: Size) -> Size:
    """The smoke-test variant of a size: tiny preset, a 9-camera 64x94 capture, a few steps."""
    small = {"multiview": ("--cameras", "9", "--test-timesteps", "2", "--width", "64", "--height", "94"),
             "monocular": ("--width", "64", "--height", "94"), "oneshot": ("--width", "64", "--height", "94")}  # fmt: skip
    return Size(size.name, "tiny", "tiny", small, dict(SMOKE_SETS), 2, smoke=True, densify=_densify(1, 1, 4, 2))


@dataclass
class Step:
    """One step of the plan.

    kind: "synth" | "track" | "cli" | "copy" | "motion" | "ceiling". key: unique id (e.g.
    ``sage:phase1``; a further subject's keys start with ``seed<S>/``). argv: the arguments after
    ``sage`` ("synth", "track" and "cli"). row: the row whose workspace the step writes (None:
    shared). stage: the workspace stage it writes (manifest to read), if any. deps: keys of the
    steps it needs. src / dst / stages: the copy. capture / out: the capture "synth" and "track"
    write, the motion's, or the ceiling's capture and workspace. split /
    lpips_weights: the ceiling's split and LPIPS weights. subject: index of the synthetic subject
    (:attr:`Settings.subjects`) the step belongs to.
    """

    kind: str
    key: str
    argv: list[str] = field(default_factory=list)
    row: str | None = None
    stage: str | None = None
    deps: list[str] = field(default_factory=list)
    src: Path | None = None
    dst: Path | None = None
    stages: tuple[str, ...] = ()
    capture: Path | None = None
    out: Path | None = None
    steps: int = 8
    split: str = "test"
    lpips_weights: Path | None = None
    subject: int = 0


HEADS: tuple[str, ...] = ("detailed", "smooth", "photo")
"""``--head``: the synthetic captures' appearance: ``sage synth --appearance detailed`` or
``smooth``, or "photo": the detailed heads with a real photograph's face as their skin
(``sage synth --set skin_photo=CAPTURE``, the capture ``sage track`` makes of :data:`PHOTO_FILE`)."""

PHOTO_FILE = "astronaut.png"
"""The photograph of the photo head: scikit-image's ``data.astronaut()`` (a real person, shipped
inside the scikit-image wheel), written into the suite's ``photo/`` folder."""


@dataclass
class Settings:
    """What every command of one suite run shares.

    head: appearance of the synthetic subjects ("detailed", "smooth": the head of earlier
    versions, or "photo": the detailed heads with the photograph's face, :data:`HEADS`);
    subjects: how many subjects (capture seeds ``seed``, ``seed + 1``, …) every row runs on; subject: the subject this copy of the settings addresses (:meth:`for_subject`). The first
    subject keeps the plain paths and step keys; a further one appends ``_seed<S>`` to its capture,
    workspace and motion paths and prefixes its step keys with ``seed<S>/``. Every stage uses
    ``seed`` whatever the subject.
    """

    size: Size
    out: Path
    device: str = "auto"
    seed: int = 0
    lpips_weights: Path | None = None
    overrides: dict[str, tuple[str, ...]] = field(default_factory=dict)
    head: str = "detailed"
    subjects: int = 2
    subject: int = 0

    def for_subject(self, k: int) -> "Settings":
        """These settings addressing subject ``k``."""
        return replace(self, subject=k)

    @property
    def detailed(self) -> bool:
        """The subjects have the detailed appearance (the photo head is a detailed head)."""
        return self.head in ("detailed", "photo")

    @property
    def photo_dir(self) -> Path:
        """The photo head's folder: the photograph, the FLAME-format model it is tracked with
        (``model_head``: a one-shot capture of the size's head grid) and its capture (``capture``)."""
        return self.out / "photo" / self.size.synth_preset

    @property
    def capture_seed(self) -> int:
        """``sage synth --seed`` of this subject."""
        return self.seed + self.subject

    @property
    def subject_seeds(self) -> list[int]:
        return [self.seed + k for k in range(self.subjects)]

    def _suffix(self) -> str:
        return "" if self.subject == 0 else f"_seed{self.capture_seed}"

    def key(self, key: str) -> str:
        """A step key of this subject."""
        return key if self.subject == 0 else f"seed{self.capture_seed}/{key}"

    def capture_dir(self, kind: str) -> Path:
        return self.out / "captures" / f"{kind}{self._suffix()}"

    def ws(self, row: str) -> Path:
        return self.out / "ws" / f"{row}{self._suffix()}"

    def motion_path(self, kind: str) -> Path:
        return self.out / "motions" / f"{kind}{self._suffix()}_test.npz"


def parse_overrides(items: list[str] | None) -> dict[str, tuple[str, ...]]:
    """``["phase1:iterations=10", "phase2:iterations=2"]`` -> {"phase1": ("iterations=10",), ...}."""
    out: dict[str, list[str]] = {}
    for item in items or []:
        stage, sep, kv = item.partition(":")
        if not sep or "=" not in kv or not stage:
            raise ValueError(f"--override expects STAGE:key=value, got {item!r}")
        out.setdefault(stage.strip(), []).append(kv.strip())
    return {k: tuple(v) for k, v in out.items()}


def _sets(st: Settings, stage: str) -> list[str]:
    out: list[str] = []
    for kv in (*st.size.sets.get(stage, ()), *st.overrides.get(stage, ())):
        out += ["--set", kv]
    return out


def _common(st: Settings, stage: str) -> list[str]:
    return ["--preset", st.size.preset, *_sets(st, stage), "--seed", str(st.seed), "--device", st.device, "--quiet"]


def stage_argv(st: Settings, row: RowSpec, stage: str) -> list[str]:
    """The ``sage`` arguments of one of the row's own stage runs (ingest, init-mesh, phase1, phase2)."""
    ws = str(st.ws(row.id))
    if stage == "ingest":
        cap = st.capture_dir(row.capture)
        return ["ingest", str(cap), ws, "--flame-model", str(cap / "model" / "synth_flame.pkl"), "--regime", row.regime, *_common(st, stage)]
    if stage == "init-mesh":
        return ["init-mesh", ws, *row.init_mesh, *_common(st, stage)]
    if stage == "phase1":
        assert row.phase1 is not None
        schedule = [a for kv in (st.size.densify if row.densify else st.size.budget) for a in ("--set", kv)]
        return ["phase1", ws, *row.phase1, *schedule, *_common(st, stage)]
    if stage == "phase2":
        assert row.phase2 is not None
        return ["phase2", ws, *row.phase2, *_common(st, stage)]
    raise ValueError(f"unknown stage {stage!r}")


def eval_argv(st: Settings, row: RowSpec, split: str) -> list[str]:
    """``sage eval`` arguments of one split of a row."""
    argv = ["eval", str(st.ws(row.id)), "--stage", row.eval_stage, "--split", split]
    if st.lpips_weights is not None:
        argv += ["--lpips-weights", str(st.lpips_weights)]
    return argv + _common(st, "eval")


def reenact_argv(st: Settings, row: RowSpec) -> list[str]:
    """``sage reenact`` arguments: the row's avatar driven by its capture's test-split motion,
    frontal (val) camera, PNG frames, no video; the render-only FPS is read from reenact.json."""
    return ["reenact", str(st.ws(row.id)), "--flame-seq", str(st.motion_path(row.capture)), "--stage", row.eval_stage,
            "--name", "bench", "--no-video", "--device", st.device, "--quiet"]  # fmt: skip


def synth_argv(st: Settings, kind: str) -> list[str]:
    """``sage synth`` arguments of a capture kind for the settings' subject (``--force`` is added
    when an older capture is replaced)."""
    regime, tracking = CAPTURES[kind]
    photo = ["--set", f"skin_photo={st.photo_dir / 'capture'}"] if st.head == "photo" else []
    return ["synth", str(st.capture_dir(kind)), "--regime", regime, "--tracking", tracking,
            "--appearance", "detailed" if st.detailed else st.head, "--preset", st.size.synth_preset,
            *st.size.synth_args.get(regime, ()), *photo, "--seed", str(st.capture_seed), "--quiet"]  # fmt: skip


def photo_steps(st: Settings) -> list[Step]:
    """The photo head's two shared steps (no subject's: every subject takes the same photo): a
    one-shot capture whose FLAME-format model has the size's head grid, then ``sage track`` of the
    photograph with that model. Empty for the other heads."""
    if st.head != "photo":
        return []
    model = ["synth", str(st.photo_dir / "model_head"), "--regime", "oneshot", "--tracking", "fitted", "--appearance", "detailed",
             "--preset", st.size.synth_preset, "--seed", str(st.seed), "--quiet"]  # fmt: skip
    track = ["track", str(st.photo_dir / PHOTO_FILE), str(st.photo_dir / "capture"), "--flame-model",
             str(st.photo_dir / "model_head" / "model" / "synth_flame.npz"), "--seed", str(st.seed), "--quiet"]  # fmt: skip
    return [Step("synth", "photo:model", model, capture=st.photo_dir / "model_head"),
            Step("track", "photo:track", track, deps=["photo:model"], capture=st.photo_dir / "capture")]


def synth_steps(st: Settings, kind: str) -> list[Step]:
    """The steps that write a capture kind for the settings' subject: the photo head's shared
    steps (:func:`photo_steps`), then ``sage synth``."""
    pre = photo_steps(st)
    return [*pre, Step("synth", st.key(f"synth:{kind}"), synth_argv(st, kind), capture=st.capture_dir(kind), subject=st.subject,
                       deps=[s.key for s in pre[-1:]])]  # fmt: skip


def row_eval_splits(st: Settings, row: RowSpec) -> tuple[str, ...]:
    """The splits ``row`` is evaluated on: its own, and ``novel`` for a trained row on a detailed
    multiview capture (whose ``gt/novel`` holds held-out views of the training timestep)."""
    if row.ceiling or not row.capture.startswith("multiview") or not st.detailed or "novel" in row.eval_splits:
        return row.eval_splits
    return (*row.eval_splits, "novel")


def own_stages(row: RowSpec) -> list[str]:
    """The workspace stages a row runs itself, in order (none for the tracking ceiling: it renders
    the capture's ground truth on the ingested data it copies)."""
    if row.ceiling:
        return []
    out = [s for s in ("ingest", "init-mesh") if s not in row.copy_stages]
    if row.phase1 is not None:
        out.append("phase1")
    if row.phase2 is not None:
        out.append("phase2")
    return out


def row_steps(st: Settings, row: RowSpec) -> list[Step]:
    """Every step a row needs for the settings' subject, prerequisites (its base row's stages, the
    capture) first."""
    k, sub = st.key, st.subject
    steps: list[Step] = []
    deps: list[str] = []
    if row.base is not None:
        base = ROWS[row.base]
        for s in base_steps(st, base, row.copy_stages):
            steps.append(s)
        deps = [k(f"{base.id}:{row.copy_stages[-1]}")]
        steps.append(Step("copy", k(f"{row.id}:copy"), row=row.id, deps=deps, src=st.ws(base.id), dst=st.ws(row.id), stages=row.copy_stages,
                          subject=sub))  # fmt: skip
        deps = [k(f"{row.id}:copy")]
    else:
        steps += synth_steps(st, row.capture)
        deps = [k(f"synth:{row.capture}")]
    for stage in own_stages(row):
        key = k(f"{row.id}:{stage}")
        steps.append(Step("cli", key, stage_argv(st, row, stage), row=row.id, stage=stage, deps=deps, subject=sub))
        deps = [key]
    last = deps
    for split in row_eval_splits(st, row):
        key = k(f"{row.id}:eval:{split}")
        if row.ceiling:
            steps.append(Step("ceiling", key, row=row.id, deps=last, capture=st.capture_dir(row.capture), out=st.ws(row.id), split=split,
                              lpips_weights=st.lpips_weights, subject=sub))
        else:
            steps.append(Step("cli", key, eval_argv(st, row, split), row=row.id, stage="eval", deps=last, subject=sub))
    if row.reenact:
        mkey = k(f"motion:{row.capture}")
        steps.append(Step("motion", mkey, deps=[k(f"synth:{row.capture}")], capture=st.capture_dir(row.capture),
                          out=st.motion_path(row.capture), steps=st.size.motion_steps, subject=sub))  # fmt: skip
        steps.append(Step("cli", k(f"{row.id}:reenact"), reenact_argv(st, row), row=row.id, deps=[*last, mkey], subject=sub))
    return steps


def base_steps(st: Settings, base: RowSpec, stages: tuple[str, ...]) -> list[Step]:
    """The steps of ``base`` up to and including the last of ``stages`` (its capture first), for the
    settings' subject."""
    k, sub = st.key, st.subject
    steps = synth_steps(st, base.capture)
    deps = [k(f"synth:{base.capture}")]
    for stage in own_stages(base):
        if stage not in stages:
            break
        key = k(f"{base.id}:{stage}")
        steps.append(Step("cli", key, stage_argv(st, base, stage), row=base.id, stage=stage, deps=deps, subject=sub))
        deps = [key]
    return steps


def plan(st: Settings, rows: list[str]) -> tuple[list[Step], dict[str, list[str]]]:
    """The deduplicated steps of ``rows`` for every subject (the first subject's rows in row order,
    then the next subject's; each step where first needed) and, per row, the keys of the steps it
    needs over all subjects."""
    unknown = [r for r in rows if r not in ROWS]
    if unknown:
        raise ValueError(f"unknown row(s) {', '.join(unknown)} (choose from {', '.join(ROW_IDS)})")
    order: list[Step] = []
    seen: set[str] = set()
    needs: dict[str, list[str]] = {rid: [] for rid in rows}
    for sub in range(st.subjects):
        sk = st.for_subject(sub)
        for rid in rows:
            steps = row_steps(sk, ROWS[rid])
            needs[rid] += [s.key for s in steps if s.key not in needs[rid]]  # the photo head's steps are every subject's
            for s in steps:
                if s.key not in seen:
                    seen.add(s.key)
                    order.append(s)
    return order, needs
