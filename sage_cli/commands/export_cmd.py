"""``sage export WS``: viewer files (3DGS PLY, .splat, compressed PLY), a GaussianAvatars folder, a
web player, meshes, and the animatable avatar bundle.

Outputs accumulate in ``WS/export/`` (a workspace stage with a manifest):

- ``ply/canonical.ply`` (canonical pose), ``ply/frame_{T:05d}.ply`` (dataset timestep T) or
  ``ply/{i:05d}.ply`` (frame i of ``--flame-seq``): INRIA-layout PLY, SH degree 0 from the
  avatar's colours (``f_dc = (rgb − 0.5) / 0.28209479``; ``--sh-degree 3`` zero-pads), thin third
  scale (formats.md §7.1); ``--splat`` / ``--compressed-ply`` write ``.splat`` and
  ``.compressed.ply`` beside them. By default (``--orientation viewer``) the world is turned by
  180° about x into the y-down convention of splat viewers; ``--orientation flame`` keeps sage's
  y-up world;
- ``gaussian_avatars/``: ``point_cloud.ply`` + ``flame_param.npz`` for GaussianAvatars' tools
  (:mod:`sage_core.export.gaussian_avatars`);
- ``web/``: ``index.html`` playing the avatar in a browser (:mod:`sage_core.export.web`);
- ``mesh/sdf_mesh.{ply,obj}``: zero level set of the canonical SDF (canonical space);
  ``mesh/flame_canonical.{ply,obj}`` or ``mesh/flame_frame_{T:05d}.{ply,obj}``: the posed FLAME mesh;
- ``bundle/``: ``avatar.safetensors`` + ``flame_param.npz`` + ``bundle.json`` (formats.md §7.2), loadable by
  ``sage reenact --bundle``.

``WS/export/results.json`` indexes every item with the key of its inputs; a new export keeps the
earlier items whose avatar is unchanged, and an item whose key is unchanged is not redone.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Optional

import typer

from .._common import (
    require_workspace,
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
    splat: Annotated[bool, typer.Option("--splat", help="World-space .splat (32 bytes per splat) for viewers.")] = False,
    compressed_ply: Annotated[bool, typer.Option("--compressed-ply", help="PlayCanvas compressed PLY (.compressed.ply) for SuperSplat/PlayCanvas.")] = False,
    gaussian_avatars: Annotated[bool, typer.Option("--gaussian-avatars", help="GaussianAvatars folder: point_cloud.ply (local Gaussians, binding_0) + flame_param.npz.")] = False,
    web: Annotated[bool, typer.Option("--web", help="Self-contained web page (WebGL2) playing the avatar driven by a FLAME sequence.")] = False,
    formats: Annotated[Optional[list[str]], typer.Option("--format", help="Output to write (repeatable): ply, splat, compressed-ply, gaussian-avatars, web, mesh, bundle.")] = None,
    orientation: Annotated[Optional[str], typer.Option("--orientation", help="World of the viewer files: viewer (y-down, as splat viewers expect; default) or flame (sage's y-up world).")] = None,
    up: Annotated[Optional[str], typer.Option("--up", help="Shorthand for --orientation: -y (viewer) or y (flame).")] = None,
    sh_degree: Annotated[Optional[int], typer.Option("--sh-degree", help="SH degree of the viewer PLY (0, or 3 zero-padded for strict INRIA loaders).")] = None,
    frame: Annotated[Optional[int], typer.Option("--frame", help="Pose the PLY and FLAME mesh at this dataset timestep (default: the canonical pose).")] = None,
    flame_seq: Annotated[Optional[Path], typer.Option("--flame-seq", help="Motion (npz, flame_param folder or capture): one viewer file per frame into export/ply/{i:05d}.*, and the sequence of --gaussian-avatars and --web (default: the avatar's own).")] = None,
    max_frames: Annotated[Optional[int], typer.Option("--max-frames", help="With --flame-seq: only the first N frames.")] = None,
    mesh: Annotated[bool, typer.Option("--mesh", help="Meshes: the SDF zero level set (marching cubes) and the posed FLAME mesh, as PLY and OBJ.")] = False,
    bundle: Annotated[bool, typer.Option("--bundle", help="Self-contained avatar bundle (avatar.safetensors, flame_param.npz, bundle.json).")] = False,
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
    """Export the avatar: viewer files (canonical, a timestep, or a sequence), GaussianAvatars folder, web player, meshes, and an animatable bundle (default: --ply --bundle)."""
    with cli_errors():
        from sage_core.errors import ConfigError

        known = {"ply", "splat", "compressed-ply", "gaussian-avatars", "web", "mesh", "bundle"}
        for f in formats or []:
            if f not in known:
                raise ConfigError(f"--format {f!r}: use one of {', '.join(sorted(known))}")
        fset = set(formats or [])
        ply, splat, compressed_ply = ply or "ply" in fset, splat or "splat" in fset, compressed_ply or "compressed-ply" in fset
        gaussian_avatars, web = gaussian_avatars or "gaussian-avatars" in fset, web or "web" in fset
        mesh, bundle = mesh or "mesh" in fset, bundle or "bundle" in fset
        if up is not None:
            ups = {"-y": "viewer", "y": "flame"}
            if up not in ups:
                raise ConfigError(f"--up {up!r}: use -y (viewer orientation) or y (FLAME's world)")
            if orientation is not None and orientation != ups[up]:
                raise ConfigError(f"--up {up} contradicts --orientation {orientation}")
            orientation = ups[up]
        flags = {"stage": stage, "mc_resolution": mc_resolution, "color_camera": color_camera,
                 "orientation": orientation, "sh_degree": sh_degree, **parse_sets(set_)}  # fmt: skip
        cfg = resolve_stage_config("export", preset, config, flags)
        if frame is not None and flame_seq is not None:
            raise ConfigError("give --frame or --flame-seq, not both")
        if cfg.mc_resolution < 8:
            raise ConfigError(f"--mc-resolution must be >= 8, got {cfg.mc_resolution}")
        if max_frames is not None and max_frames < 1:
            raise ConfigError(f"--max-frames must be >= 1, got {max_frames}")
        viewer = [f for f, on in (("ply", ply), ("splat", splat), ("compressed-ply", compressed_ply)) if on]
        if not (viewer or mesh or bundle or gaussian_avatars or web):
            viewer, bundle = ["ply"], True
        if flame_seq is not None and not (viewer or gaussian_avatars or web):
            raise ConfigError("--flame-seq drives per-frame viewer files, --gaussian-avatars or --web: add one of them")
        require_workspace(ws)
        run_export(ws, cfg, viewer=viewer, mesh=mesh, bundle=bundle, frame=frame, flame_seq=flame_seq, max_frames=max_frames,
                   gaussian_avatars=gaussian_avatars, web=web,
                   opts=StageOptions(ws, preset, config, seed, device, force, verbose))  # fmt: skip


_VIEWER_ITEMS = ("ply:", "splat:", "compressed-ply:")


def _viewer_format(name: str) -> str | None:
    """"ply" / "splat" / "compressed-ply" for a viewer item name, else None."""
    return name.split(":", 1)[0] if name.startswith(_VIEWER_ITEMS) else None


def _item_files(name: str, frame: int | None, n_seq: int = 0) -> list[str]:
    from sage_core.export.avatar_ply import VIEWER_SUFFIX

    pose = "canonical" if frame is None else f"frame_{frame:05d}"
    fmt = _viewer_format(name)
    if fmt is not None and name.endswith(":seq"):
        return [f"ply/{i:05d}{VIEWER_SUFFIX[fmt]}" for i in range(n_seq)]
    if fmt is not None:
        return [f"ply/{pose}{VIEWER_SUFFIX[fmt]}"]
    if name == "gaussian-avatars":
        return ["gaussian_avatars/point_cloud.ply", "gaussian_avatars/flame_param.npz"]
    if name == "web":
        return ["web/index.html"]
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
    viewer: list[str],
    mesh: bool,
    bundle: bool,
    frame: int | None,
    flame_seq: Path | None,
    max_frames: int | None,
    opts: StageOptions,
    gaussian_avatars: bool = False,
    web: bool = False,
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
    seq_key = {"seq": None if flame_seq is None else str(Path(flame_seq).resolve()), "seq_fp": seq_fp, "max_frames": max_frames}
    for fmt in viewer:
        name = f"{fmt}:seq" if flame_seq is not None else f"{fmt}:{pose}"
        wanted[name] = result_key(item=name, **base, color_camera=cfg.color_camera, up_axis=cfg.up_axis,
                                  orientation=cfg.orientation, sh_degree=cfg.sh_degree if fmt != "splat" else 0,
                                  **seq_key)  # fmt: skip
    if gaussian_avatars:
        wanted["gaussian-avatars"] = result_key(item="gaussian-avatars", **base, **seq_key)
    if web:
        wanted["web"] = result_key(item="web", **base, **seq_key, color_camera=cfg.color_camera)
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
        from sage_core.export.gaussian_avatars import write_gaussian_avatars
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
        motion_cache: dict[str, Any] = {}

        def get_motion() -> Any:
            if "m" not in motion_cache:
                from sage_core.export.motion import load_motion
                from sage_core.train.pipeline import check_motion_for_avatar

                assert flame_seq is not None
                motion = load_motion(flame_seq, n_expr=av.params.n_expr)
                if max_frames is not None and max_frames < motion.n_frames:
                    motion.params = motion.params.select(list(range(max_frames)))
                check_motion_for_avatar(av, motion)
                motion_cache["m"] = motion
            return motion_cache["m"]

        def own_params() -> Any:
            p = av.params
            if max_frames is not None and max_frames < p.n_timesteps:
                p = p.select(list(range(max_frames)))
            return p

        view_opts = {"up_axis": cfg.up_axis, "orientation": cfg.orientation}
        for i, name in enumerate(todo):
            progress(i, steps, name)
            extra: dict[str, Any] = {}
            fmt = _viewer_format(name)
            deg = cfg.sh_degree if fmt != "splat" else 0
            if fmt is not None and name.endswith(":seq"):
                from sage_core.train.pipeline import with_identity

                motion = get_motion()
                dropped = 0
                files = _item_files(name, None, motion.n_frames)
                for j in range(motion.n_frames):
                    posed = renderer.posed(with_identity(av, motion.frame_inputs(j, dev)), view_from)
                    r = write_posed_ply(run.work_dir / files[j], posed, comments=[f"sage avatar {av_stage}", f"motion frame {j}"],
                                        sh_degree=deg, fmt=fmt, **view_opts)  # fmt: skip
                    dropped += r.n_dropped
                    progress(i, steps, f"{name} {j + 1}/{motion.n_frames}")
                extra = {"frames": motion.n_frames, "rows_dropped": dropped, "source": str(motion.source)}
            elif fmt is not None:
                files = _item_files(name, frame)
                r = write_posed_ply(run.work_dir / files[0], renderer.posed(inputs, view_from), comments=comments,
                                    sh_degree=deg, fmt=fmt, **view_opts)  # fmt: skip
                extra = {"rows": r.n_rows, "rows_dropped": r.n_dropped}
            elif name == "gaussian-avatars":
                files = _item_files(name, frame)
                params = get_motion().params if flame_seq is not None else None
                ga = write_gaussian_avatars(av, run.work_dir / "gaussian_avatars", params)
                extra = {"gaussians": ga.n_gaussians, "timesteps": ga.n_timesteps, "vertices": ga.n_vertices}
            elif name == "web":
                from sage_core.export.web import write_web_player

                files = _item_files(name, frame)
                params = get_motion().params if flame_seq is not None else own_params()
                fps = float(get_motion().fps) if flame_seq is not None else 25.0
                wp = write_web_player(av, renderer, params, run.work_dir / "web", reference_camera(data, cfg.color_camera),
                                      fps=fps, view_from=view_from, title=f"sage avatar ({av_stage})",
                                      progress=lambda d, t, m: progress(i, steps, f"web {m}"))  # fmt: skip
                extra = {"frames": wp.n_frames, "surfels": wp.n_surfels, "bytes": wp.n_bytes}
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
        if name == "gaussian-avatars":
            rows.append((name, f"{e.get('gaussians', '?')} Gaussians bound to FLAME faces, {e.get('timesteps', '?')} FLAME frames"))
        elif name == "web":
            rows.append((name, f"{e.get('frames', '?')} frames, {e.get('surfels', '?')} surfels; open index.html in a browser"))
        elif _viewer_format(name) is not None:
            if "frames" in e:
                rows.append((name, f"{e['frames']} files, {e['rows_dropped']} rows dropped in all (non-finite or opacity < 1/255)"))
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
