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

import math
from pathlib import Path
from typing import Annotated, Any, Optional

import typer

from .._common import (
    ConfigOpt,
    DeviceOpt,
    ForceOpt,
    PresetOpt,
    SeedOpt,
    SetOpt,
    VerboseOpt,
    cli_errors,
    console,
    parse_sets,
    resolve_stage_config,
    summary_panel,
)
from .._stage import StageOptions, execute_stage

SPLITS = ("test", "val", "all", "novel")
_LPIPS_HINT = "unavailable: no weights (give --lpips-weights, set $SAGE_LPIPS_WEIGHTS or place ~/.cache/sage/lpips_alex_v0.1.pth)"


def _fmt(v: Any, digits: int) -> str:
    if v is None:
        return "n/a"
    if isinstance(v, str):
        return v
    if isinstance(v, float) and math.isnan(v):
        return "nan"
    return f"{float(v):.{digits}f}"


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
) -> None:
    """Evaluate the avatar: PSNR, SSIM and LPIPS per image, per camera, frontal and overall; results accumulate in WS/eval/<stage>/<split>/."""
    with cli_errors():
        from sage_core.errors import ConfigError, InputError

        flags = {"split": split, "stage": stage, "samples": samples, **parse_sets(set_)}
        cfg = resolve_stage_config("eval", preset, config, flags)
        if cfg.split not in SPLITS:
            raise ConfigError(f"--split must be test, val, all or novel, got {cfg.split!r}")
        if cfg.samples < 0:
            raise ConfigError(f"--samples must be >= 0, got {cfg.samples}")
        if not ws.is_dir():
            raise InputError(ws, "workspace folder not found")
        run_eval(ws, cfg, lpips_weights, StageOptions(ws, preset, config, seed, device, force, verbose))


def run_eval(ws_path: Path, cfg: Any, lpips_weights: Path | None, opts: StageOptions) -> dict[str, Any]:
    """Run (or skip) the evaluation described by an EvalConfig; prints the tables and the panel.

    Returns the results index entries of the evaluated (or already current) (stage, split) pairs.
    """
    import dataclasses

    from sage_core.data.dataset import IngestedData
    from sage_core.errors import ConfigError
    from sage_core.evaluate.lpips import find_lpips_weights
    from sage_core.train.pipeline import fresh_results, resolve_avatar_stage, result_key
    from sage_core.workspace import Workspace, file_fingerprint, read_json

    if cfg.split == "novel":
        return run_eval_novel(ws_path, cfg, lpips_weights, opts)
    ws = Workspace(ws_path)
    ingest_fp = ws.require("ingest", "eval")["fingerprint"]
    av_stage = resolve_avatar_stage(ws, cfg.stage, "eval")
    av_fp = ws.require(av_stage, "eval")["fingerprint"]
    data = IngestedData.open(ws.stage_dir("ingest"))
    wanted = ["val", "test"] if cfg.split == "all" else [cfg.split]
    splits = [s for s in wanted if data.role(s)]
    skipped_empty = [s for s in wanted if s not in splits]
    if not splits:
        raise ConfigError(f"the workspace has no {' or '.join(wanted)} frames to evaluate (regime {data.regime})")
    lp_path = find_lpips_weights(lpips_weights)
    lp_fp = file_fingerprint(lp_path) if lp_path is not None else None
    cfg = dataclasses.replace(cfg, stage=av_stage)
    keys = {
        s: result_key(avatar_stage=av_stage, avatar_fingerprint=av_fp, ingest=ingest_fp, split=s,
                      samples=cfg.samples, psnr_cap=cfg.psnr_cap, lpips=lp_fp)  # fmt: skip
        for s in splits
    }
    existing = fresh_results(ws, "eval")
    todo = [s for s in splits if opts.force or existing.get(f"{av_stage}/{s}", {}).get("key") != keys[s]]
    for s in skipped_empty:
        console.print(f"[yellow]eval[/]: the workspace has no {s} frames; {s} is not evaluated")

    if not todo:
        console.print(f"[green]eval[/]: {av_stage} on {', '.join(splits)} is already evaluated with the same avatar, data and settings; skipping. Use --force to redo it.")
        done = {f"{av_stage}/{s}": existing[f"{av_stage}/{s}"] for s in splits}
        for name in done:
            print_metrics_table(f"{name}", read_json(ws.stage_dir("eval") / name / "metrics.json"))
        return done

    keep = {k: v for k, v in existing.items() if k not in {f"{av_stage}/{s}" for s in todo}}
    requires = ["ingest", *sorted({v["avatar_stage"] for v in keep.values()} | {av_stage})]
    holder: dict[str, Any] = {}

    def body(run, progress) -> None:
        import torch

        from sage_core.evaluate.lpips import LPIPS
        from sage_core.evaluate.protocol import evaluate_frames
        from sage_core.train.pipeline import AvatarRenderer, carry_results, load_stage_avatar
        from sage_core.workspace import atomic_write_json, now_iso

        carry_results(run.ws, "eval", run.work_dir, keep)
        loaded = load_stage_avatar(run.ws, av_stage, data, run.device)
        renderer = AvatarRenderer(loaded.avatar, loaded.render)
        lpips = LPIPS.from_path(lp_path, device=run.device) if lp_path is not None else None
        cache: dict[int, dict[str, torch.Tensor]] = {}

        def render_fn(frame):
            if frame.timestep not in cache:
                cache[frame.timestep] = loaded.avatar.frame_inputs(frame.timestep)
            return renderer.render(frame.camera, cache[frame.timestep])

        total = sum(len(data.role(s)) for s in todo)
        offset = 0
        results = dict(keep)
        reports = {}
        for s in todo:
            frames = data.role(s)
            name = f"{av_stage}/{s}"
            out = run.work_dir / av_stage / s

            def prog(done: int, n: int, message: str = "", _o: int = offset, _s: str = s) -> None:
                progress(_o + done, total, f"{_s}: {message}")

            report = evaluate_frames(render_fn, data, frames, lpips=lpips, out_dir=out, n_samples=cfg.samples,
                                     psnr_cap=cfg.psnr_cap, progress=prog)  # fmt: skip
            offset += len(frames)
            atomic_write_json(out / "config.json", {**dataclasses.asdict(cfg), "split": s, "avatar_stage": av_stage,
                                                    "avatar_fingerprint": loaded.fingerprint, "lpips_weights": None if lp_path is None else str(lp_path)})  # fmt: skip
            results[name] = {
                "key": keys[s],
                "avatar_stage": av_stage,
                "avatar_fingerprint": loaded.fingerprint,
                "split": s,
                "files": [name],
                "finished_at": now_iso(),
                "lpips_available": lpips is not None,
                "overall": report.overall.to_dict(),
                "frontal": None if report.frontal is None else report.frontal.to_dict(),
            }
            reports[name] = report
        atomic_write_json(run.work_dir / "results.json", results)
        for name, entry in results.items():
            for k in ("psnr", "ssim", "lpips"):
                run.metrics[f"{name} {k}"] = entry["overall"][k]
            run.outputs[name] = str(run.ws.stage_dir("eval") / name / "metrics.json")
        holder["results"] = results
        holder["reports"] = reports

    run_opts = StageOptions(opts.ws, opts.preset, opts.config_file, opts.seed, opts.device, True, opts.verbose)
    manifest = execute_stage(
        "eval", run_opts, cfg, body, requires=tuple(requires),
        external_inputs={"lpips_weights": lp_fp or "none"}, title=f"eval {av_stage}", discard_work_on_failure=True,
    )  # fmt: skip
    assert manifest is not None
    results = holder["results"]
    out_dir = ws.stage_dir("eval")
    rows: list[tuple[str, Any]] = [("avatar", f"{av_stage} ({ws.stage_dir(av_stage) / 'avatar.pt'})")]
    paths: list[tuple[str, Path]] = []
    for s in splits:
        name = f"{av_stage}/{s}"
        doc = read_json(out_dir / name / "metrics.json")
        print_metrics_table(f"{name} ({'novel view' if s == 'val' else 'self-reenactment'})", doc)
        o = doc["overall"]
        rows.append((f"{s} PSNR / SSIM / LPIPS", f"{_fmt(o['psnr'], 2)} dB / {_fmt(o['ssim'], 4)} / {_fmt(o['lpips'], 4)}"))
        paths.append((f"{s} metrics", out_dir / name / "metrics.json"))
        paths.append((f"{s} samples", out_dir / name / "images"))
    if lp_path is None:
        rows.append(("LPIPS", _LPIPS_HINT))
    else:
        rows.append(("LPIPS weights", str(lp_path)))
    others = sorted(k for k in results if k not in {f"{av_stage}/{s}" for s in splits})
    if others:
        rows.append(("also in WS/eval", ", ".join(others)))
    rows.append(("PSNR", "standard per image (GA's per-channel mean beside it, labelled)"))
    rows.append(("wall time", f"{manifest['wall_time_s']:.1f} s"))
    summary_panel("sage eval", rows, paths + [("results index", out_dir / "results.json")])
    return {f"{av_stage}/{s}": results[f"{av_stage}/{s}"] for s in splits}


def run_eval_novel(ws_path: Path, cfg: Any, lpips_weights: Path | None, opts: StageOptions) -> dict[str, Any]:
    """``--split novel``: the avatar on the capture's held-out ground truth (``CAPTURE/gt/novel``).

    Same stage, index and skip rules as the other splits (result ``<stage>/novel``); the metrics
    add a visible-region block. InputError, before anything is written, when the capture has no
    ``gt/novel``.
    """
    import dataclasses

    from sage_core.data.dataset import IngestedData
    from sage_core.evaluate.lpips import find_lpips_weights
    from sage_core.evaluate.novel import open_novel_set
    from sage_core.train.pipeline import fresh_results, resolve_avatar_stage, result_key
    from sage_core.workspace import Workspace, file_fingerprint, read_json

    ws = Workspace(ws_path)
    ingest_fp = ws.require("ingest", "eval")["fingerprint"]
    av_stage = resolve_avatar_stage(ws, cfg.stage, "eval")
    av_fp = ws.require(av_stage, "eval")["fingerprint"]
    data = IngestedData.open(ws.stage_dir("ingest"))
    novel = open_novel_set(data)
    novel_fp = [file_fingerprint(p) for p in novel.fingerprint_files()]
    lp_path = find_lpips_weights(lpips_weights)
    lp_fp = file_fingerprint(lp_path) if lp_path is not None else None
    cfg = dataclasses.replace(cfg, stage=av_stage)
    name = f"{av_stage}/novel"
    key = result_key(avatar_stage=av_stage, avatar_fingerprint=av_fp, ingest=ingest_fp, split="novel",
                     samples=cfg.samples, psnr_cap=cfg.psnr_cap, lpips=lp_fp, novel=novel_fp)  # fmt: skip
    existing = fresh_results(ws, "eval")
    out_dir = ws.stage_dir("eval")
    if not opts.force and existing.get(name, {}).get("key") == key:
        console.print(f"[green]eval[/]: {av_stage} on the held-out ground truth is already evaluated with the same avatar, data and settings; skipping. Use --force to redo it.")
        doc = read_json(out_dir / name / "metrics.json")
        print_metrics_table(f"{name} (held-out views and expressions)", doc)
        print_metrics_table(f"{name} visible region", doc["visible_region"])
        return {name: existing[name]}

    keep = {k: v for k, v in existing.items() if k != name}
    requires = ["ingest", *sorted({v["avatar_stage"] for v in keep.values()} | {av_stage})]
    holder: dict[str, Any] = {}

    def body(run, progress) -> None:
        from sage_core.evaluate.lpips import LPIPS
        from sage_core.evaluate.novel import evaluate_novel
        from sage_core.train.pipeline import AvatarRenderer, carry_results, load_stage_avatar
        from sage_core.workspace import atomic_write_json, now_iso

        carry_results(run.ws, "eval", run.work_dir, keep)
        loaded = load_stage_avatar(run.ws, av_stage, data, run.device)
        md = loaded.avatar.model_data
        held = open_novel_set(data, int(md.v_template.shape[0]), int(md.n_base_vertices))
        renderer = AvatarRenderer(loaded.avatar, loaded.render)
        lpips = LPIPS.from_path(lp_path, device=run.device) if lp_path is not None else None
        out = run.work_dir / av_stage / "novel"

        def prog(done: int, n: int, message: str = "") -> None:
            progress(done, n, f"novel: {message}")

        report = evaluate_novel(renderer.render, loaded.avatar, data, held, lpips=lpips, out_dir=out,
                                n_samples=cfg.samples, psnr_cap=cfg.psnr_cap, progress=prog)  # fmt: skip
        atomic_write_json(out / "config.json", {**dataclasses.asdict(cfg), "split": "novel", "avatar_stage": av_stage,
                                                "avatar_fingerprint": loaded.fingerprint, "novel": str(held.root),
                                                "lpips_weights": None if lp_path is None else str(lp_path)})  # fmt: skip
        doc = report.to_dict()
        results = dict(keep)
        results[name] = {
            "key": key,
            "avatar_stage": av_stage,
            "avatar_fingerprint": loaded.fingerprint,
            "split": "novel",
            "files": [name],
            "finished_at": now_iso(),
            "lpips_available": lpips is not None,
            "overall": doc["overall"],
            "frontal": doc["frontal"],
            "visible_region": {"overall": doc["visible_region"]["overall"], "frontal": doc["visible_region"]["frontal"]},
        }
        atomic_write_json(run.work_dir / "results.json", results)
        for entry_name, entry in results.items():
            for k in ("psnr", "ssim", "lpips"):
                run.metrics[f"{entry_name} {k}"] = entry["overall"][k]
            run.outputs[entry_name] = str(run.ws.stage_dir("eval") / entry_name / "metrics.json")
        for k in ("psnr", "ssim", "lpips"):
            run.metrics[f"{name} visible {k}"] = doc["visible_region"]["overall"][k]
        holder["results"] = results

    run_opts = StageOptions(opts.ws, opts.preset, opts.config_file, opts.seed, opts.device, True, opts.verbose)
    manifest = execute_stage(
        "eval", run_opts, cfg, body, requires=tuple(requires),
        external_inputs={"lpips_weights": lp_fp or "none", "novel": ",".join(novel_fp)}, title=f"eval {av_stage} novel",
        discard_work_on_failure=True,
    )  # fmt: skip
    assert manifest is not None
    results = holder["results"]
    doc = read_json(out_dir / name / "metrics.json")
    print_metrics_table(f"{name} (held-out views and expressions)", doc)
    print_metrics_table(f"{name} visible region", doc["visible_region"])
    o, v = doc["overall"], doc["visible_region"]["overall"]
    rows: list[tuple[str, Any]] = [("avatar", f"{av_stage} ({ws.stage_dir(av_stage) / 'avatar.pt'})"),
                                   ("held-out ground truth", str(novel.root)),
                                   ("frontal", f"camera {doc['frontal_camera']} ({doc['frontal_rule']})")]
    rows.append(("all views PSNR / SSIM / LPIPS", f"{_fmt(o['psnr'], 2)} dB / {_fmt(o['ssim'], 4)} / {_fmt(o['lpips'], 4)}"))
    if doc.get("frontal") is not None:
        f = doc["frontal"]
        rows.append(("frontal PSNR / SSIM / LPIPS", f"{_fmt(f['psnr'], 2)} dB / {_fmt(f['ssim'], 4)} / {_fmt(f['lpips'], 4)}"))
    rows.append(("visible region PSNR / SSIM / LPIPS", f"{_fmt(v['psnr'], 2)} dB / {_fmt(v['ssim'], 4)} / {_fmt(v['lpips'], 4)}"))
    rows.append(("LPIPS", _LPIPS_HINT if lp_path is None else str(lp_path)))
    others = sorted(k for k in results if k != name)
    if others:
        rows.append(("also in WS/eval", ", ".join(others)))
    rows.append(("wall time", f"{manifest['wall_time_s']:.1f} s"))
    summary_panel("sage eval", rows, [("novel metrics", out_dir / name / "metrics.json"), ("novel samples", out_dir / name / "images"),
                                      ("results index", out_dir / "results.json")])
    return {name: results[name]}
