"""``sage eval WS``: PSNR / SSIM / LPIPS of the avatar on the evaluation splits (formats.md §8).

Every frame of a split is rendered with that frame's FLAME parameters and camera on the dataset
background and compared with its ground truth. ``WS/eval/`` is a workspace stage that accumulates
results: each (avatar stage, split) pair has its own folder ``WS/eval/<stage>/<split>/`` with
``metrics.json``, ``config.json`` and sample strips in ``images/``; ``WS/eval/results.json`` indexes
them (key of the inputs, avatar stage and fingerprint, overall means). ``--split novel`` scores the
avatar on the capture's held-out ground truth (``CAPTURE/gt/novel``: novel views and expressions)
over the full image and over the region the training view(s) saw (``sage_core.evaluate.novel``).
A new run copies the earlier
results whose avatar stage is unchanged into the new stage folder and drops those whose avatar was
re-trained since; the manifest lists every result's means. Re-running a (stage, split) whose avatar,
data, settings and LPIPS weights are unchanged skips it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Callable, Optional

import typer

from .._common import (
    require_workspace,
    ConfigOpt,
    DeviceOpt,
    ForceOpt,
    PresetOpt,
    SeedOpt,
    SetOpt,
    RenderBackendOpt,
    ThreadsOpt,
    VerboseOpt,
    cli_errors,
    console,
    fmt_metric,
    parse_sets,
    resolve_stage_config,
    summary_panel,
)
from .._stage import StageOptions, execute_stage

_LPIPS_HINT = "unavailable: no weights (give --lpips-weights, set $SAGE_LPIPS_WEIGHTS or place ~/.cache/sage/lpips_alex_v0.1.pth)"


def _fmt(v: Any, digits: int) -> str:
    """A metric with ``digits`` decimals; a string as it is; the dash where there is no value."""
    if isinstance(v, str):
        return v
    return fmt_metric(v, f".{digits}f")


def metrics_rows(doc: dict[str, Any]) -> list[tuple[str, ...]]:
    """Table rows (group, images, PSNR, PSNR (GA), SSIM, LPIPS) from a ``metrics.json`` document:
    one per camera, then the frontal camera and all images."""

    def row(name: str, m: dict[str, Any]) -> tuple[str, ...]:
        return (name, str(m["count"]), _fmt(m["psnr"], 2), _fmt(m["psnr_ga"], 2), _fmt(m["ssim"], 4), _fmt(m["lpips"], 4))

    out = [row(f"camera {c}", m) for c, m in sorted(doc["per_camera"].items(), key=lambda kv: int(kv[0]))]
    if doc.get("frontal") is not None:
        out.append(row(f"frontal (cam {doc.get('frontal_camera', 8)})", doc["frontal"]))
    out.append(row("all", doc["overall"]))
    return out


def print_metrics_table(title: str, doc: dict[str, Any]) -> None:
    """A rich table of one split's metrics (per camera, frontal, all)."""
    from rich.table import Table

    t = Table(title=title, show_lines=False)
    for c in ("group", "images", "PSNR", "PSNR (GA)", "SSIM", "LPIPS"):
        t.add_column(c, justify="left" if c == "group" else "right")
    for r in metrics_rows(doc):
        t.add_row(*r, style="bold" if r[0] == "all" else None)
    console.print(t)


def eval_(
    ws: Annotated[Path, typer.Argument(help="Workspace folder (after `sage phase1` or `sage phase2`).")],
    split: Annotated[Optional[str], typer.Option("--split", help="test (self-reenactment), val (novel view), all (both) or novel (the capture's held-out gt/novel views and expressions).")] = None,
    stage: Annotated[Optional[str], typer.Option("--stage", help="Avatar to evaluate: auto (latest finished of phase2, phase1), phase1 or phase2.")] = None,
    lpips_weights: Annotated[Optional[Path], typer.Option("--lpips-weights", help="LPIPS AlexNet v0.1 weights (default: $SAGE_LPIPS_WEIGHTS, then ~/.cache/sage/lpips_alex_v0.1.pth; without them LPIPS is reported unavailable).")] = None,
    samples: Annotated[Optional[int], typer.Option("--samples", help="Sample strips (GT | render | error) written per split.")] = None,
    preset: PresetOpt = "default",
    config: ConfigOpt = None,
    set_: SetOpt = None,
    seed: SeedOpt = 0,
    device: DeviceOpt = "auto",
    force: ForceOpt = False,
    verbose: VerboseOpt = True,
    threads: ThreadsOpt = None,
    render_backend: RenderBackendOpt = None,
) -> None:
    """Evaluate the avatar: PSNR, SSIM and LPIPS per image, per camera, frontal and overall; results accumulate in WS/eval/<stage>/<split>/."""
    with cli_errors():

        flags = {"split": split, "stage": stage, "samples": samples, "render_backend": render_backend, **parse_sets(set_)}
        cfg = resolve_stage_config("eval", preset, config, flags)
        require_workspace(ws)
        run_eval(ws, cfg, lpips_weights, StageOptions(ws, preset, config, seed, device, force, verbose, threads))


@dataclass
class _Target:
    """What one ``sage eval`` run scores: the avatar stage, the ingested data, the LPIPS weights and
    the results already in ``WS/eval/`` that are still fresh."""

    ws: Any
    data: Any
    av_stage: str
    cfg: Any
    selection: Any
    lp_path: Path | None
    lp_fp: str | None
    key_parts: dict[str, Any]
    existing: dict[str, Any]

    def key(self, split: str, **extra: Any) -> str:
        """The result key of ``split`` (inputs, avatar, settings, LPIPS weights and ``extra``)."""
        from sage_core.train.pipeline import result_key

        return result_key(**self.key_parts, split=split, **extra)

    def is_current(self, name: str, key: str, force: bool) -> bool:
        """Whether result ``name`` is in the index with ``key`` (and not forced to re-run)."""
        return not force and self.existing.get(name, {}).get("key") == key


def _target(ws_path: Path, cfg: Any, lpips_weights: Path | None, select: Callable[[Any], Any]) -> _Target:
    """Open the workspace and resolve the avatar stage; ``select(data)`` picks (and checks) what to
    evaluate before the LPIPS weights are looked up."""
    import dataclasses

    from sage_core.data.dataset import IngestedData
    from sage_core.evaluate.lpips import find_lpips_weights
    from sage_core.train.pipeline import fresh_results, resolve_avatar_stage
    from sage_core.workspace import Workspace, file_fingerprint

    ws = Workspace(ws_path)
    ingest_fp = ws.require("ingest", "eval")["fingerprint"]
    av_stage = resolve_avatar_stage(ws, cfg.stage, "eval")
    av_fp = ws.require(av_stage, "eval")["fingerprint"]
    data = IngestedData.open(ws.stage_dir("ingest"))
    selection = select(data)
    lp_path = find_lpips_weights(lpips_weights)
    lp_fp = file_fingerprint(lp_path) if lp_path is not None else None
    key_parts = {"avatar_stage": av_stage, "avatar_fingerprint": av_fp, "ingest": ingest_fp, "samples": cfg.samples,
                 "psnr_cap": cfg.psnr_cap, "lpips": lp_fp}  # fmt: skip
    return _Target(ws, data, av_stage, dataclasses.replace(cfg, stage=av_stage), selection, lp_path, lp_fp, key_parts,
                   fresh_results(ws, "eval"))  # fmt: skip


EvaluateFn = Callable[..., tuple[dict[str, dict[str, Any]], dict[str, float]]]
"""``evaluate(run, loaded, renderer, lpips, progress) -> (entries, extra_metrics)``: the split-specific
fields of each new result (``key``, ``split``, then the metric blocks) and extra manifest metrics."""


def _run_stage(t: _Target, opts: StageOptions, todo: list[str], evaluate: EvaluateFn, external: dict[str, str],
               title: str) -> tuple[dict[str, Any], dict[str, Any]]:  # fmt: skip
    """Run the eval stage for the results named in ``todo``; the other fresh results are carried over.

    Returns the new results index and the stage manifest.
    """
    keep = {k: v for k, v in t.existing.items() if k not in set(todo)}
    requires = ["ingest", *sorted({v["avatar_stage"] for v in keep.values()} | {t.av_stage})]
    holder: dict[str, Any] = {}

    def body(run, progress) -> None:
        from sage_core.evaluate.lpips import LPIPS
        from sage_core.train.pipeline import AvatarRenderer, carry_results, load_stage_avatar
        from sage_core.workspace import atomic_write_json, now_iso

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

    run_opts = StageOptions(opts.ws, opts.preset, opts.config_file, opts.seed, opts.device, True, opts.verbose, opts.threads)
    manifest = execute_stage(
        "eval", run_opts, t.cfg, body, requires=tuple(requires),
        external_inputs={"lpips_weights": t.lp_fp or "none", **external}, title=title, discard_work_on_failure=True,
    )  # fmt: skip
    assert manifest is not None
    return holder["results"], manifest


def _write_result_config(t: _Target, out: Path, split: str, loaded: Any, **extra: Any) -> None:
    """``<result>/config.json``: the eval settings, the split, the avatar and the LPIPS weights used."""
    import dataclasses

    from sage_core.workspace import atomic_write_json

    atomic_write_json(out / "config.json", {**dataclasses.asdict(t.cfg), "split": split, "avatar_stage": t.av_stage,
                                            "avatar_fingerprint": loaded.fingerprint, **extra,
                                            "lpips_weights": None if t.lp_path is None else str(t.lp_path)})  # fmt: skip


def _means(m: dict[str, Any]) -> str:
    return f"{_fmt(m['psnr'], 2)} dB / {_fmt(m['ssim'], 4)} / {_fmt(m['lpips'], 4)}"


def _panel(t: _Target, results: dict[str, Any], names: list[str], manifest: dict[str, Any], rows: list[tuple[str, Any]],
           paths: list[tuple[str, Path]], lpips_label: str, notes: list[tuple[str, Any]]) -> None:  # fmt: skip
    """The closing panel: avatar, ``rows``, LPIPS, the other results in the index, ``notes``, wall time."""
    out_dir = t.ws.stage_dir("eval")
    rows = [("avatar", f"{t.av_stage} ({t.ws.stage_dir(t.av_stage) / 'avatar.pt'})"), *rows]
    rows.append(("LPIPS", _LPIPS_HINT) if t.lp_path is None else (lpips_label, str(t.lp_path)))
    others = sorted(k for k in results if k not in set(names))
    if others:
        rows.append(("also in WS/eval", ", ".join(others)))
    rows += notes
    rows.append(("wall time", f"{manifest['wall_time_s']:.1f} s"))
    summary_panel("sage eval", rows, paths + [("results index", out_dir / "results.json")])


def run_eval(ws_path: Path, cfg: Any, lpips_weights: Path | None, opts: StageOptions) -> dict[str, Any]:
    """Run (or skip) the evaluation described by an EvalConfig; prints the tables and the panel.

    Returns the results index entries of the evaluated (or already current) (stage, split) pairs.
    """
    from sage_core.errors import ConfigError
    from sage_core.workspace import read_json

    if cfg.split == "novel":
        return run_eval_novel(ws_path, cfg, lpips_weights, opts)
    wanted = ["val", "test"] if cfg.split == "all" else [cfg.split]

    def select(data: Any) -> list[str]:
        splits = [s for s in wanted if data.role(s)]
        if not splits:
            raise ConfigError(f"the workspace has no {' or '.join(wanted)} frames to evaluate (regime {data.regime})")
        return splits

    t = _target(ws_path, cfg, lpips_weights, select)
    splits: list[str] = t.selection
    data, av_stage = t.data, t.av_stage
    names = {s: f"{av_stage}/{s}" for s in splits}
    keys = {s: t.key(s) for s in splits}
    todo = [s for s in splits if not t.is_current(names[s], keys[s], opts.force)]
    for s in wanted:
        if s not in splits:
            console.print(f"[yellow]eval[/]: the workspace has no {s} frames; {s} is not evaluated")

    out_dir = t.ws.stage_dir("eval")
    if not todo:
        console.print(f"[green]eval[/]: {av_stage} on {', '.join(splits)} is already evaluated with the same avatar, data and settings; skipping. Use --force to redo it.")
        for name in names.values():
            print_metrics_table(name, read_json(out_dir / name / "metrics.json"))
        return {names[s]: t.existing[names[s]] for s in splits}

    def evaluate(run, loaded, renderer, lpips, progress) -> tuple[dict[str, dict[str, Any]], dict[str, float]]:
        import torch

        from sage_core.evaluate.protocol import evaluate_frames

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

    results, manifest = _run_stage(t, opts, [names[s] for s in todo], evaluate, {}, f"eval {av_stage}")
    rows: list[tuple[str, Any]] = []
    paths: list[tuple[str, Path]] = []
    for s in splits:
        name = names[s]
        doc = read_json(out_dir / name / "metrics.json")
        print_metrics_table(f"{name} ({'novel view' if s == 'val' else 'self-reenactment'})", doc)
        rows.append((f"{s} PSNR / SSIM / LPIPS", _means(doc["overall"])))
        paths.append((f"{s} metrics", out_dir / name / "metrics.json"))
        paths.append((f"{s} samples", out_dir / name / "images"))
    _panel(t, results, list(names.values()), manifest, rows, paths, "LPIPS weights",
           [("PSNR", "standard per image (GA's per-channel mean beside it, labelled)")])  # fmt: skip
    return {names[s]: results[names[s]] for s in splits}


def run_eval_novel(ws_path: Path, cfg: Any, lpips_weights: Path | None, opts: StageOptions) -> dict[str, Any]:
    """``--split novel``: the avatar on the capture's held-out ground truth (``CAPTURE/gt/novel``).

    Same stage, index and skip rules as the other splits (result ``<stage>/novel``); the metrics
    add a visible-region block. InputError, before anything is written, when the capture has no
    ``gt/novel``.
    """
    from sage_core.evaluate.novel import open_novel_set
    from sage_core.workspace import file_fingerprint, read_json

    t = _target(ws_path, cfg, lpips_weights, open_novel_set)
    novel = t.selection
    novel_fp = [file_fingerprint(p) for p in novel.fingerprint_files()]
    av_stage = t.av_stage
    name = f"{av_stage}/novel"
    key = t.key("novel", novel=novel_fp)
    out_dir = t.ws.stage_dir("eval")

    def print_tables() -> dict[str, Any]:
        doc = read_json(out_dir / name / "metrics.json")
        print_metrics_table(f"{name} (held-out views and expressions)", doc)
        print_metrics_table(f"{name} visible region", doc["visible_region"])
        return doc

    if t.is_current(name, key, opts.force):
        console.print(f"[green]eval[/]: {av_stage} on the held-out ground truth is already evaluated with the same avatar, data and settings; skipping. Use --force to redo it.")
        print_tables()
        return {name: t.existing[name]}

    def evaluate(run, loaded, renderer, lpips, progress) -> tuple[dict[str, dict[str, Any]], dict[str, float]]:
        from sage_core.evaluate.novel import evaluate_novel

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
        return {name: entry}, {f"{name} visible {k}": vis["overall"][k] for k in ("psnr", "ssim", "lpips")}

    results, manifest = _run_stage(t, opts, [name], evaluate, {"novel": ",".join(novel_fp)}, f"eval {av_stage} novel")
    doc = print_tables()
    rows: list[tuple[str, Any]] = [("held-out ground truth", str(novel.root)),
                                   ("frontal", f"camera {doc['frontal_camera']} ({doc['frontal_rule']})"),
                                   ("all views PSNR / SSIM / LPIPS", _means(doc["overall"]))]  # fmt: skip
    if doc.get("frontal") is not None:
        rows.append(("frontal PSNR / SSIM / LPIPS", _means(doc["frontal"])))
    rows.append(("visible region PSNR / SSIM / LPIPS", _means(doc["visible_region"]["overall"])))
    paths = [("novel metrics", out_dir / name / "metrics.json"), ("novel samples", out_dir / name / "images")]
    _panel(t, results, [name], manifest, rows, paths, "LPIPS", [])
    return {name: results[name]}
