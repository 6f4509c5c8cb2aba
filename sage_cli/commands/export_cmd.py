"""``sage export WS``: world-space 3DGS PLY for viewers, meshes, and the animatable avatar bundle.

Outputs accumulate in ``WS/export/`` (a workspace stage with a manifest):

- ``ply/canonical.ply`` (canonical pose), ``ply/frame_{T:05d}.ply`` (dataset timestep T) or
  ``ply/{i:05d}.ply`` (frame i of ``--flame-seq``): INRIA-layout PLY, SH degree 0 from the
  avatar's colours (``f_dc = (rgb − 0.5) / 0.28209479``), thin third scale (formats.md §7.1);
- ``mesh/sdf_mesh.{ply,obj}``: zero level set of the canonical SDF (canonical space);
  ``mesh/flame_canonical.{ply,obj}`` or ``mesh/flame_frame_{T:05d}.{ply,obj}``: the posed FLAME mesh;
- ``bundle/``: ``avatar.pt`` + ``flame_param.npz`` + ``bundle.json`` (formats.md §7.2), loadable by
  ``sage reenact --bundle``.

``WS/export/results.json`` indexes every item with the key of its inputs; a new export keeps the
earlier items whose avatar is unchanged, and an item whose key is unchanged is not redone.
"""

from __future__ import annotations

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


def export(
    ws: Annotated[Path, typer.Argument(help="Workspace folder with a trained avatar.")],
    ply: Annotated[bool, typer.Option("--ply", help="World-space 3DGS PLY (INRIA layout) for viewers.")] = False,
    frame: Annotated[Optional[int], typer.Option("--frame", help="Pose the PLY and FLAME mesh at this dataset timestep (default: the canonical pose).")] = None,
    flame_seq: Annotated[Optional[Path], typer.Option("--flame-seq", help="Write one PLY per frame of this motion (npz, flame_param folder or capture) into export/ply/{i:05d}.ply.")] = None,
    max_frames: Annotated[Optional[int], typer.Option("--max-frames", help="With --flame-seq: only the first N frames.")] = None,
    mesh: Annotated[bool, typer.Option("--mesh", help="Meshes: the SDF zero level set (marching cubes) and the posed FLAME mesh, as PLY and OBJ.")] = False,
    bundle: Annotated[bool, typer.Option("--bundle", help="Self-contained avatar bundle (avatar.pt, flame_param.npz, bundle.json).")] = False,
    stage: Annotated[Optional[str], typer.Option("--stage", help="Avatar: auto (latest finished of phase2, phase1), phase1 or phase2.")] = None,
    mc_resolution: Annotated[Optional[int], typer.Option("--mc-resolution", help="Marching-cubes resolution of the SDF mesh.")] = None,
    color_camera: Annotated[Optional[int], typer.Option("--color-camera", help="Bake view-dependent colours as seen from this capture camera (default: each surfel seen along its normal).")] = None,
    preset: PresetOpt = "default",
    config: ConfigOpt = None,
    set_: SetOpt = None,
    seed: SeedOpt = 0,
    device: DeviceOpt = "auto",
    force: ForceOpt = False,
    verbose: VerboseOpt = True,
) -> None:
    """Export the avatar: viewer PLY (canonical, a timestep, or a sequence), meshes, and an animatable bundle (default: --ply --bundle)."""
    with cli_errors():
        from sage_core.errors import ConfigError, InputError

        flags = {"stage": stage, "mc_resolution": mc_resolution, "color_camera": color_camera, **parse_sets(set_)}
        cfg = resolve_stage_config("export", preset, config, flags)
        if frame is not None and flame_seq is not None:
            raise ConfigError("give --frame or --flame-seq, not both")
        if cfg.mc_resolution < 8:
            raise ConfigError(f"--mc-resolution must be >= 8, got {cfg.mc_resolution}")
        if max_frames is not None and max_frames < 1:
            raise ConfigError(f"--max-frames must be >= 1, got {max_frames}")
        if not (ply or mesh or bundle):
            ply = bundle = True
        if flame_seq is not None and not ply:
            raise ConfigError("--flame-seq writes per-frame PLY files: add --ply")
        if not ws.is_dir():
            raise InputError(ws, "workspace folder not found")
        run_export(ws, cfg, ply=ply, mesh=mesh, bundle=bundle, frame=frame, flame_seq=flame_seq, max_frames=max_frames,
                   opts=StageOptions(ws, preset, config, seed, device, force, verbose))  # fmt: skip


def _item_files(name: str, frame: int | None, n_seq: int = 0) -> list[str]:
    pose = "canonical" if frame is None else f"frame_{frame:05d}"
    if name == "ply:seq":
        return [f"ply/{i:05d}.ply" for i in range(n_seq)]
    if name.startswith("ply:"):
        return [f"ply/{pose}.ply"]
    if name == "mesh:sdf":
        return ["mesh/sdf_mesh.ply", "mesh/sdf_mesh.obj"]
    if name.startswith("mesh:flame"):
        return [f"mesh/flame_{pose}.ply", f"mesh/flame_{pose}.obj"]
    if name == "bundle":
        return ["bundle"]
    raise ValueError(name)


def run_export(
    ws_path: Path,
    cfg: Any,
    *,
    ply: bool,
    mesh: bool,
    bundle: bool,
    frame: int | None,
    flame_seq: Path | None,
    max_frames: int | None,
    opts: StageOptions,
) -> dict[str, Any]:
    """The body of ``sage export`` (options already checked). Returns the results index entries of
    the requested items."""
    import dataclasses

    from sage_core.data.dataset import IngestedData
    from sage_core.errors import InputError
    from sage_core.train.pipeline import fresh_results, resolve_avatar_stage, result_key
    from sage_core.workspace import Workspace, file_fingerprint

    ws = Workspace(ws_path)
    ingest_fp = ws.require("ingest", "export")["fingerprint"]
    av_stage = resolve_avatar_stage(ws, cfg.stage, "export")
    av_fp = ws.require(av_stage, "export")["fingerprint"]
    data = IngestedData.open(ws.stage_dir("ingest"))
    cfg = dataclasses.replace(cfg, stage=av_stage)
    if frame is not None and frame not in {int(t) for t in data.params.timesteps}:
        raise InputError(data.root / "flame_params.npz", f"no FLAME parameters for timestep {frame} "
                         f"(timesteps: {sorted(int(t) for t in data.params.timesteps)})")
    if cfg.color_camera is not None and cfg.color_camera not in data.cameras:
        raise InputError(data.root / "cameras.json", f"no camera {cfg.color_camera} (cameras: {sorted(data.cameras)})")
    seq_fp = None
    if flame_seq is not None:
        if not Path(flame_seq).exists():
            raise InputError(Path(flame_seq), "motion source not found")
        seq_fp = file_fingerprint(flame_seq)

    base = {"avatar_stage": av_stage, "avatar_fingerprint": av_fp, "ingest": ingest_fp}
    pose = "canonical" if frame is None else f"frame{frame}"
    wanted: dict[str, str] = {}
    if ply:
        name = "ply:seq" if flame_seq is not None else f"ply:{pose}"
        wanted[name] = result_key(item=name, **base, color_camera=cfg.color_camera, up_axis=cfg.up_axis,
                                  seq=None if flame_seq is None else str(Path(flame_seq).resolve()), seq_fp=seq_fp,
                                  max_frames=max_frames)  # fmt: skip
    if mesh:
        wanted["mesh:sdf"] = result_key(item="mesh:sdf", **base, mc_resolution=cfg.mc_resolution)
        wanted[f"mesh:flame-{pose}"] = result_key(item=f"mesh:flame-{pose}", **base)
    if bundle:
        wanted["bundle"] = result_key(item="bundle", **base, up_axis=cfg.up_axis)
    existing = fresh_results(ws, "export")
    todo = [k for k in wanted if opts.force or existing.get(k, {}).get("key") != wanted[k]]
    out_dir = ws.stage_dir("export")
    if not todo:
        console.print("[green]export[/]: every requested item is already exported from the same avatar with the same settings; skipping. Use --force to redo it.")
        _panel(out_dir, {k: existing[k] for k in wanted}, av_stage, None)
        return {k: existing[k] for k in wanted}

    # a new sequence replaces the files of an earlier one
    keep = {k: v for k, v in existing.items() if k not in todo}
    requires = ["ingest", *sorted({v["avatar_stage"] for v in keep.values()} | {av_stage})]
    holder: dict[str, Any] = {}

    def body(run, progress) -> None:
        import torch

        from sage_core.export.avatar_ply import write_posed_ply
        from sage_core.export.bundle import write_bundle
        from sage_core.export.meshes import posed_mesh, sdf_mesh, write_mesh
        from sage_core.flame.canonical import canonical_inputs
        from sage_core.train.pipeline import AvatarRenderer, carry_results, head_center, load_stage_avatar, reference_camera
        from sage_core.workspace import atomic_write_json, now_iso

        carry_results(run.ws, "export", run.work_dir, keep)
        loaded = load_stage_avatar(run.ws, av_stage, data, run.device)
        av = loaded.avatar
        dev = av.device
        renderer = AvatarRenderer(av, loaded.render, backend=cfg.render_backend)
        if frame is None:
            inputs = canonical_inputs(av.params, av.canonical_timestep, dev)
        else:
            inputs = av.frame_inputs(frame)
        view_from = None
        if cfg.color_camera is not None:
            centre = torch.as_tensor(data.cameras[cfg.color_camera].center, dtype=torch.float32, device=dev)
            if frame is None:  # the canonical pose has the canonical timestep's global motion removed
                rigid = av.rigid_transform(av.frame_inputs(av.canonical_timestep))
                if rigid is not None:
                    R0, t = rigid
                    centre = (centre - t - av.root_joint) @ R0 + av.root_joint
            view_from = centre
        comments = [f"sage avatar {av_stage}", f"pose {'canonical' if frame is None else f'timestep {frame}'}",
                    "colours: SH degree 0 baked " + ("along each surfel normal" if cfg.color_camera is None else f"for camera {cfg.color_camera}")]  # fmt: skip
        results = dict(keep)
        stats: dict[str, Any] = {}
        steps = len(todo)
        for i, name in enumerate(todo):
            progress(i, steps, name)
            extra: dict[str, Any] = {}
            if name == "ply:seq":
                from sage_core.export.motion import load_motion
                from sage_core.train.pipeline import check_motion_for_avatar, with_identity

                assert flame_seq is not None
                motion = load_motion(flame_seq, n_expr=av.params.n_expr)
                if max_frames is not None and max_frames < motion.n_frames:
                    motion.params = motion.params.select(list(range(max_frames)))
                check_motion_for_avatar(av, motion)
                dropped = 0
                for j in range(motion.n_frames):
                    posed = renderer.posed(with_identity(av, motion.frame_inputs(j, dev)), view_from)
                    r = write_posed_ply(run.work_dir / "ply" / f"{j:05d}.ply", posed,
                                        comments=[f"sage avatar {av_stage}", f"motion frame {j}"], up_axis=cfg.up_axis)  # fmt: skip
                    dropped += r.n_dropped
                    progress(i, steps, f"{name} {j + 1}/{motion.n_frames}")
                files = _item_files(name, None, motion.n_frames)
                extra = {"frames": motion.n_frames, "rows_dropped": dropped, "source": str(motion.source)}
            elif name.startswith("ply:"):
                files = _item_files(name, frame)
                r = write_posed_ply(run.work_dir / files[0], renderer.posed(inputs, view_from), comments=comments, up_axis=cfg.up_axis)
                extra = {"rows": r.n_rows, "rows_dropped": r.n_dropped}
            elif name == "mesh:sdf":
                files = _item_files(name, frame)
                v, f = sdf_mesh(av, cfg.mc_resolution)
                for rel in files:
                    write_mesh(run.work_dir / rel, v, f)
                extra = {"vertices": int(v.shape[0]), "faces": int(f.shape[0]), "space": "canonical"}
            elif name.startswith("mesh:flame"):
                files = _item_files(name, frame)
                v, f = posed_mesh(av, inputs)
                for rel in files:
                    write_mesh(run.work_dir / rel, v, f)
                extra = {"vertices": int(v.shape[0]), "faces": int(f.shape[0])}
            else:
                files = _item_files(name, frame)
                write_bundle(av, run.work_dir / "bundle", loaded.render, reference_camera=reference_camera(data),
                             head_center=head_center(data), up_axis=cfg.up_axis,
                             source={"workspace": str(run.ws.root), "stage": av_stage, "fingerprint": loaded.fingerprint})  # fmt: skip
            results[name] = {"key": wanted[name], "avatar_stage": av_stage, "avatar_fingerprint": loaded.fingerprint,
                             "files": files, "finished_at": now_iso(), **extra}  # fmt: skip
            stats[name] = extra
        progress(steps, steps, "done")
        atomic_write_json(run.work_dir / "results.json", results)
        for name, entry in results.items():
            if "rows_dropped" in entry:
                run.metrics[f"{name} rows_dropped"] = entry["rows_dropped"]
            run.outputs[name] = str(run.ws.stage_dir("export") / entry["files"][0]) if entry["files"] else ""
        holder["results"] = results
        holder["stats"] = stats

    run_opts = StageOptions(opts.ws, opts.preset, opts.config_file, opts.seed, opts.device, True, opts.verbose)
    external = {"flame_seq": seq_fp} if seq_fp is not None else None
    manifest = execute_stage("export", run_opts, cfg, body, requires=tuple(requires), external_inputs=external,
                             title=f"export {av_stage}", discard_work_on_failure=True)  # fmt: skip
    assert manifest is not None
    results = holder["results"]
    _panel(out_dir, {k: results[k] for k in wanted}, av_stage, manifest)
    return {k: results[k] for k in wanted}


def _panel(out_dir: Path, items: dict[str, Any], av_stage: str, manifest: dict[str, Any] | None) -> None:
    rows: list[tuple[str, Any]] = [("avatar", av_stage)]
    paths: list[tuple[str, Path]] = []
    for name, e in items.items():
        if name.startswith("ply:"):
            if "frames" in e:
                rows.append((name, f"{e['frames']} PLY files, {e['rows_dropped']} rows dropped in all (non-finite or opacity < 1/255)"))
                paths.append((name, out_dir / "ply"))
                continue
            rows.append((name, f"{e.get('rows', '?')} surfels written, {e.get('rows_dropped', '?')} rows dropped (non-finite or opacity < 1/255)"))
        elif name.startswith("mesh:"):
            rows.append((name, f"{e.get('vertices', '?')} vertices, {e.get('faces', '?')} faces" + (" (canonical space)" if name == "mesh:sdf" else "")))
        for rel in e["files"]:
            paths.append((name, out_dir / rel))
    if "bundle" in items:
        rows.append(("bundle", "drive it with `sage reenact --bundle " + str(out_dir / "bundle") + " --flame-seq SEQ --orbit`"))
    if manifest is not None:
        rows.append(("wall time", f"{manifest['wall_time_s']:.1f} s"))
    summary_panel("sage export", rows, paths)
