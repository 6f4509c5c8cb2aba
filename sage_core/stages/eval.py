"""The eval stage: PSNR / SSIM / LPIPS of the avatar on the evaluation splits (docs/formats.md §8).

Every frame of a split is rendered with that frame's FLAME parameters and camera on the dataset
background and compared with its ground truth. ``WS/eval/`` accumulates results: each (avatar
stage, split) pair has its own folder ``WS/eval/<stage>/<split>/`` with ``metrics.json``,
``config.json`` and sample strips in ``images/``; ``WS/eval/results.json`` indexes them (key of the
inputs, avatar stage and fingerprint, overall means). Split ``novel`` scores the avatar on the
capture's held-out ground truth (``CAPTURE/gt/novel``) over the full image and over the region the
training view(s) saw (:mod:`sage_core.evaluate.novel`). A new run copies the earlier results whose
avatar stage is unchanged and drops those whose avatar was re-trained since; re-running a (stage,
split) whose avatar, data, settings and LPIPS weights are unchanged skips it.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from ..config import EvalConfig
from ..workspace import Workspace
from ._runner import StageResult, StageSettings, as_workspace, execute_stage, finish_result
from .events import Emitter, EventFn


@dataclass
class EvalResult(StageResult):
    """:class:`StageResult` of eval.

    avatar_stage: the avatar evaluated. names: the results of this call (``<stage>/<split>``), in
    order. entries: their results-index entries. index: the whole results index after the call.
    documents: each name's ``metrics.json``. lpips_weights: the weights used (None: LPIPS
    unavailable). missing: requested splits the workspace has no frames for. novel_root: the
    held-out ground truth folder (split ``novel``).
    """

    avatar_stage: str = ""
    names: list[str] = field(default_factory=list)
    entries: dict[str, Any] = field(default_factory=dict)
    index: dict[str, Any] = field(default_factory=dict)
    documents: dict[str, Any] = field(default_factory=dict)
    lpips_weights: Path | None = None
    missing: list[str] = field(default_factory=list)
    novel_root: Path | None = None


@dataclass
class _Target:
    """What one eval run scores: the avatar stage, the ingested data, the LPIPS weights and the
    results already in ``WS/eval/`` that are still fresh."""

    ws: Workspace
    data: Any
    av_stage: str
    cfg: EvalConfig
    selection: Any
    lp_path: Path | None
    lp_fp: str | None
    key_parts: dict[str, Any]
    existing: dict[str, Any]

    def key(self, split: str, **extra: Any) -> str:
        """The result key of ``split`` (inputs, avatar, settings, LPIPS weights and ``extra``)."""
        from .results import result_key

        return result_key(**self.key_parts, split=split, **extra)

    def is_current(self, name: str, key: str, force: bool) -> bool:
        """Whether result ``name`` is in the index with ``key`` (and not forced to re-run)."""
        return not force and self.existing.get(name, {}).get("key") == key


def _target(w: Workspace, cfg: EvalConfig, lpips_weights: Path | None, select: Callable[[Any], Any]) -> _Target:
    """Resolve the avatar stage; ``select(data)`` picks (and checks) what to evaluate before the
    LPIPS weights are looked up."""
    from ..data.dataset import IngestedData
    from ..evaluate.lpips import find_lpips_weights
    from .avatars import resolve_avatar_stage
    from .results import fresh_results
    from ..workspace import file_fingerprint

    ingest_fp = w.require("ingest", "eval")["fingerprint"]
    av_stage = resolve_avatar_stage(w, cfg.stage, "eval")
    av_fp = w.require(av_stage, "eval")["fingerprint"]
    data = IngestedData.open(w.stage_dir("ingest"))
    selection = select(data)
    lp_path = find_lpips_weights(lpips_weights)
    lp_fp = file_fingerprint(lp_path) if lp_path is not None else None
    key_parts = {"avatar_stage": av_stage, "avatar_fingerprint": av_fp, "ingest": ingest_fp, "samples": cfg.samples,
                 "psnr_cap": cfg.psnr_cap, "lpips": lp_fp}  # fmt: skip
    return _Target(w, data, av_stage, dataclasses.replace(cfg, stage=av_stage), selection, lp_path, lp_fp, key_parts,
                   fresh_results(w, "eval"))  # fmt: skip


EvaluateFn = Callable[..., tuple[dict[str, dict[str, Any]], dict[str, float]]]
"""``evaluate(run, loaded, renderer, lpips, progress) -> (entries, extra_metrics)``: the split-specific
fields of each new result (``key``, ``split``, then the metric blocks) and extra manifest metrics."""


def _run(t: _Target, settings: StageSettings, emitter: Emitter, todo: list[str], evaluate: EvaluateFn,
         external: dict[str, str]) -> tuple[dict[str, Any], Any]:  # fmt: skip
    """Run the eval stage for the results named in ``todo``; the other fresh results are carried
    over. Returns the new results index and the run's outcome."""
    keep = {k: v for k, v in t.existing.items() if k not in set(todo)}
    requires = ["ingest", *sorted({v["avatar_stage"] for v in keep.values()} | {t.av_stage})]
    holder: dict[str, Any] = {}

    def body(run, progress) -> None:
        from ..evaluate.lpips import LPIPS
        from .avatars import AvatarRenderer, load_stage_avatar
        from .results import carry_results
        from ..workspace import atomic_write_json, now_iso

        carry_results(run.ws, "eval", run.work_dir, keep)
        loaded = load_stage_avatar(run.ws, t.av_stage, t.data, run.device)
        renderer = AvatarRenderer(loaded.avatar, loaded.render, backend=t.cfg.render_backend)
        lpips = LPIPS.from_path(t.lp_path, device=run.device) if t.lp_path is not None else None
        entries, extra_metrics = evaluate(run, loaded, renderer, lpips, progress)
        results = dict(keep)
        for name, e in entries.items():
            results[name] = {"key": e["key"], "avatar_stage": t.av_stage, "avatar_fingerprint": loaded.fingerprint, "split": e["split"],
                             "files": [name], "finished_at": now_iso(), "lpips_available": lpips is not None,
                             **{k: v for k, v in e.items() if k not in ("key", "split")}}  # fmt: skip
        atomic_write_json(run.work_dir / "results.json", results)
        for name, entry in results.items():
            for k in ("psnr", "ssim", "lpips"):
                run.metrics[f"{name} {k}"] = entry["overall"][k]
            run.outputs[name] = str(run.ws.stage_dir("eval") / name / "metrics.json")
        run.metrics.update(extra_metrics)
        holder["results"] = results

    outcome = execute_stage("eval", t.ws, t.cfg, body, dataclasses.replace(settings, force=True), emitter,
                            requires=tuple(requires), external_inputs={"lpips_weights": t.lp_fp or "none", **external},
                            discard_work_on_failure=True)  # fmt: skip
    assert outcome.manifest is not None
    return holder["results"], outcome


def _write_result_config(t: _Target, out: Path, split: str, loaded: Any, **extra: Any) -> None:
    """``<result>/config.json``: the eval settings, the split, the avatar and the LPIPS weights used."""
    from ..workspace import atomic_write_json

    atomic_write_json(out / "config.json", {**dataclasses.asdict(t.cfg), "split": split, "avatar_stage": t.av_stage,
                                            "avatar_fingerprint": loaded.fingerprint, **extra,
                                            "lpips_weights": None if t.lp_path is None else str(t.lp_path)})  # fmt: skip


def _documents(t: _Target, names: list[str]) -> dict[str, Any]:
    from ..workspace import read_json

    return {name: read_json(t.ws.stage_dir("eval") / name / "metrics.json") for name in names}


def eval_stage(
    ws: str | Path | Workspace,
    cfg: EvalConfig,
    lpips_weights: str | Path | None = None,
    settings: StageSettings = StageSettings(),
    on_event: EventFn | None = None,
) -> EvalResult:
    """Evaluate the avatar (``cfg.stage``: auto, phase1, phase2) on ``cfg.split`` (test, val, all,
    novel); results accumulate in ``WS/eval/<stage>/<split>/``.

    lpips_weights: LPIPS AlexNet weights (None: ``$SAGE_LPIPS_WEIGHTS``, then the cache; without
    them LPIPS is reported unavailable). A (stage, split) already evaluated with the same avatar,
    data, settings and weights is skipped (``skipped`` event; the result still lists it).
    """
    from ..errors import ConfigError

    t0 = time.time()
    emitter = Emitter("eval", on_event)
    emitter.emit("started")
    w = as_workspace(ws)
    lp = None if lpips_weights is None else Path(lpips_weights)
    if cfg.split == "novel":
        return _eval_novel(w, cfg, lp, settings, emitter, t0)
    wanted = ["val", "test"] if cfg.split == "all" else [cfg.split]

    def select(data: Any) -> list[str]:
        splits = [s for s in wanted if data.role(s)]
        if not splits:
            raise ConfigError(f"the workspace has no {' or '.join(wanted)} frames to evaluate (regime {data.regime})")
        return splits

    t = _target(w, cfg, lp, select)
    splits: list[str] = t.selection
    data, av_stage = t.data, t.av_stage
    names = {s: f"{av_stage}/{s}" for s in splits}
    keys = {s: t.key(s) for s in splits}
    todo = [s for s in splits if not t.is_current(names[s], keys[s], settings.force)]
    missing = [s for s in wanted if s not in splits]
    for s in missing:
        emitter.note(f"the workspace has no {s} frames; {s} is not evaluated", level="notice")
    result = EvalResult("eval", w.root, avatar_stage=av_stage, names=list(names.values()), lpips_weights=t.lp_path, missing=missing)

    if not todo:
        emitter.emit("skipped", message=f"{av_stage} on {', '.join(splits)} is already evaluated with the same avatar, data and settings; "
                                        "skipping. Use --force to redo it.")  # fmt: skip
        return _done(result, t, {names[s]: t.existing[names[s]] for s in splits}, t.existing, None, emitter, t0)

    def evaluate(run, loaded, renderer, lpips, progress) -> tuple[dict[str, dict[str, Any]], dict[str, float]]:
        import torch

        from ..evaluate.protocol import evaluate_frames

        cache: dict[int, dict[str, torch.Tensor]] = {}

        def render_fn(frame):
            if frame.timestep not in cache:
                cache[frame.timestep] = loaded.avatar.frame_inputs(frame.timestep)
            return renderer.render(frame.camera, cache[frame.timestep])

        total = sum(len(data.role(s)) for s in todo)
        offset = 0
        entries: dict[str, dict[str, Any]] = {}
        for s in todo:
            frames = data.role(s)
            out = run.work_dir / av_stage / s

            def prog(done: int, n: int, message: str = "", _o: int = offset, _s: str = s) -> None:
                progress(_o + done, total, f"{_s}: {message}")

            report = evaluate_frames(render_fn, data, frames, lpips=lpips, out_dir=out, n_samples=t.cfg.samples,
                                     psnr_cap=t.cfg.psnr_cap, progress=prog)  # fmt: skip
            offset += len(frames)
            _write_result_config(t, out, s, loaded)
            entries[names[s]] = {"key": keys[s], "split": s, "overall": report.overall.to_dict(),
                                 "frontal": None if report.frontal is None else report.frontal.to_dict()}  # fmt: skip
        return entries, {}

    emitter.title = f"eval {av_stage}"
    results, outcome = _run(t, settings, emitter, [names[s] for s in todo], evaluate, {})
    return _done(result, t, {names[s]: results[names[s]] for s in splits}, results, outcome, emitter, t0)


def _done(result: EvalResult, t: _Target, entries: dict[str, Any], index: dict[str, Any], outcome: Any, emitter: Emitter,
          t0: float) -> EvalResult:  # fmt: skip
    """Fill the result (a skip when ``outcome`` is None) and emit ``finished``."""
    result.entries, result.index = entries, index
    result.documents = _documents(t, result.names)
    if outcome is None:
        result.skipped = True
        result.fill(t.ws.manifest("eval"), t0)
        emitter.emit("finished", result=result)
        return result
    return finish_result(result, outcome, t.ws, emitter, t0)  # type: ignore[return-value]


def _eval_novel(w: Workspace, cfg: EvalConfig, lpips_weights: Path | None, settings: StageSettings, emitter: Emitter,
                t0: float) -> EvalResult:  # fmt: skip
    """Split ``novel``: the avatar on the capture's held-out ground truth (``CAPTURE/gt/novel``).

    Same stage, index and skip rules as the other splits (result ``<stage>/novel``); the metrics add
    a visible-region block. InputError, before anything is written, when the capture has no
    ``gt/novel``.
    """
    from ..evaluate.novel import open_novel_set
    from ..workspace import file_fingerprint

    t = _target(w, cfg, lpips_weights, open_novel_set)
    novel = t.selection
    novel_fp = [file_fingerprint(p) for p in novel.fingerprint_files()]
    av_stage = t.av_stage
    name = f"{av_stage}/novel"
    key = t.key("novel", novel=novel_fp)
    result = EvalResult("eval", w.root, avatar_stage=av_stage, names=[name], lpips_weights=t.lp_path, novel_root=Path(novel.root))

    if t.is_current(name, key, settings.force):
        emitter.emit("skipped", message=f"{av_stage} on the held-out ground truth is already evaluated with the same avatar, data and "
                                        "settings; skipping. Use --force to redo it.")  # fmt: skip
        return _done(result, t, {name: t.existing[name]}, t.existing, None, emitter, t0)

    def evaluate(run, loaded, renderer, lpips, progress) -> tuple[dict[str, dict[str, Any]], dict[str, float]]:
        from ..evaluate.novel import evaluate_novel

        md = loaded.avatar.model_data
        held = open_novel_set(t.data, int(md.v_template.shape[0]), int(md.n_base_vertices))
        out = run.work_dir / av_stage / "novel"

        def prog(done: int, n: int, message: str = "") -> None:
            progress(done, n, f"novel: {message}")

        report = evaluate_novel(renderer.render, loaded.avatar, t.data, held, lpips=lpips, out_dir=out,
                                n_samples=t.cfg.samples, psnr_cap=t.cfg.psnr_cap, progress=prog)  # fmt: skip
        _write_result_config(t, out, "novel", loaded, novel=str(held.root))
        doc = report.to_dict()
        vis = doc["visible_region"]
        entry = {"key": key, "split": "novel", "overall": doc["overall"], "frontal": doc["frontal"],
                 "visible_region": {"overall": vis["overall"], "frontal": vis["frontal"]}}  # fmt: skip
        if "view_groups" in doc:
            entry["view_groups"] = {g: {"overall": v["overall"]} for g, v in doc["view_groups"].items()}
        return {name: entry}, {f"{name} visible {k}": vis["overall"][k] for k in ("psnr", "ssim", "lpips")}

    emitter.title = f"eval {av_stage} novel"
    results, outcome = _run(t, settings, emitter, [name], evaluate, {"novel": ",".join(novel_fp)})
    return _done(result, t, {name: results[name]}, results, outcome, emitter, t0)
