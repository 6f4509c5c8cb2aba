"""``sage export WS``: viewer files (3DGS PLY, .splat, compressed PLY), a GaussianAvatars folder, a
web player, meshes, and the animatable avatar bundle.

Outputs accumulate in ``WS/export/`` (a workspace stage with a manifest):

- ``ply/canonical.ply`` (canonical pose), ``ply/frame_{T:05d}.ply`` (dataset timestep T) or
  ``ply/seq_<motion>/{i:05d}.ply`` (frame i of ``--flame-seq``, one motion per folder):
  INRIA-layout PLY, SH degree 0 from the avatar's colours (``f_dc = (rgb − 0.5) / 0.28209479``;
  ``--sh-degree 3`` zero-pads), thin third scale (docs/formats.md §7.1); ``--splat`` /
  ``--compressed-ply`` write ``.splat`` and ``.compressed.ply`` beside them. By default
  (``--orientation viewer``) the world is turned by 180° about x into the y-down convention of
  splat viewers; ``--orientation flame`` keeps sage's y-up world and tags the names ``-flame``;
- ``gaussian_avatars/``: ``point_cloud.ply`` + ``flame_param.npz`` in GaussianAvatars' FLAME
  topology (:mod:`sage_core.export.gaussian_avatars`);
- ``web/``: ``index.html``, ``player.js``, ``avatar.js``: a page playing the avatar in a browser
  (:mod:`sage_core.export.web`);
- ``mesh/sdf_mesh.{ply,obj}``: zero level set of the canonical SDF (canonical space);
  ``mesh/flame_canonical.{ply,obj}`` or ``mesh/flame_frame_{T:05d}.{ply,obj}``: the posed FLAME mesh;
- ``bundle/``: ``avatar.safetensors`` + ``flame_param.npz`` + ``bundle.json`` (docs/formats.md §7.2), loadable by
  ``sage reenact --bundle``.

``WS/export/results.json`` indexes every item with the key of its inputs; a new export keeps the
earlier items whose avatar is unchanged, and an item whose key is unchanged is not redone.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Optional

import typer

from .._common import (
    require_workspace,
    ConfigOpt,
    DeviceOpt,
    ForceOpt,
    SeedOpt,
    SetOpt,
    RenderBackendOpt,
    ThreadsOpt,
    VerboseOpt,
    cli_errors,
    parse_sets,
    resolve_stage_config,
    summary_panel,
)
from .._stage import StageDisplay

if TYPE_CHECKING:
    from sage_core.stages import ExportResult


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
    frame: Annotated[Optional[int], typer.Option("--frame", help="Pose the viewer files and FLAME mesh at this dataset timestep (default: the canonical pose); --web and --gaussian-avatars then hold that timestep alone.")] = None,
    flame_seq: Annotated[Optional[Path], typer.Option("--flame-seq", help="Motion (npz, flame_param folder or capture): one viewer file per frame into export/ply/seq_<motion>/, and the sequence of --gaussian-avatars and --web (default: the avatar's own).")] = None,
    max_frames: Annotated[Optional[int], typer.Option("--max-frames", help="Only the first N frames of the sequence: --flame-seq's, or the avatar's own played by --web / --gaussian-avatars.")] = None,
    mesh: Annotated[bool, typer.Option("--mesh", help="Meshes: the SDF zero level set (marching cubes) and the posed FLAME mesh, as PLY and OBJ.")] = False,
    bundle: Annotated[bool, typer.Option("--bundle", help="Avatar bundle (avatar.safetensors, flame_param.npz, bundle.json); it names the FLAME model file it needs instead of carrying it.")] = False,
    include_flame_model: Annotated[bool, typer.Option("--include-flame-model", help="Put the (licensed) FLAME model into the bundle, so that it loads without the model file; only for bundles you do not share.")] = False,
    stage: Annotated[Optional[str], typer.Option("--stage", help="Avatar: auto (latest finished of phase2, phase1), phase1 or phase2.")] = None,
    mc_resolution: Annotated[Optional[int], typer.Option("--mc-resolution", help="Marching-cubes resolution of the SDF mesh.")] = None,
    color_camera: Annotated[Optional[int], typer.Option("--color-camera", help="Bake view-dependent colours as seen from this capture camera (default: each surfel seen along its normal).")] = None,
    preset: Annotated[Optional[str], typer.Option("--preset", help="Settings preset: tiny, small or default (default: the one the workspace's avatar was trained with).")] = None,
    config: ConfigOpt = None,
    set_: SetOpt = None,
    seed: SeedOpt = 0,
    device: DeviceOpt = "auto",
    force: ForceOpt = False,
    verbose: VerboseOpt = True,
    threads: ThreadsOpt = None,
    render_backend: RenderBackendOpt = None,
) -> None:
    """Export the avatar: viewer files (canonical, a timestep, or a sequence), GaussianAvatars folder, web player, meshes, and an animatable bundle (default: --ply --bundle)."""
    with cli_errors():
        from sage_core.errors import ConfigError
        from sage_core.stages import EXPORT_FORMATS

        known = set(EXPORT_FORMATS)
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
        flags = {"stage": stage, "mc_resolution": mc_resolution, "color_camera": color_camera, "render_backend": render_backend,
                 "orientation": orientation, "sh_degree": sh_degree, **parse_sets(set_)}  # fmt: skip
        viewer = [f for f, on in (("ply", ply), ("splat", splat), ("compressed-ply", compressed_ply)) if on]
        if not (viewer or mesh or bundle or gaussian_avatars or web):
            viewer, bundle = ["ply"], True
        from sage_core.stages.export import check_export_options, workspace_preset

        check_export_options(viewer=viewer, mesh=mesh, bundle=bundle, gaussian_avatars=gaussian_avatars, web=web, frame=frame,
                             flame_seq=flame_seq, max_frames=max_frames)  # fmt: skip
        require_workspace(ws)
        if preset is None:
            preset = workspace_preset(ws) or "default"
        cfg = resolve_stage_config("export", preset, config, flags)
        if cfg.mc_resolution < 8:
            raise ConfigError(f"--mc-resolution must be >= 8, got {cfg.mc_resolution}")
        from sage_core.stages import StageSettings, export_stage

        with StageDisplay(verbose, preset) as display:
            r = export_stage(ws, cfg, viewer=viewer, mesh=mesh, bundle=bundle, gaussian_avatars=gaussian_avatars, web=web, frame=frame,
                             flame_seq=flame_seq, max_frames=max_frames, include_flame_model=include_flame_model,
                             settings=StageSettings(seed, device, force, threads),
                             on_event=display)  # fmt: skip
        show(r)


def show(r: ExportResult) -> None:
    """The closing panel of an export result: each item's numbers and files (``sage export``, ``sage run``)."""
    from sage_core.stages import viewer_format
    from sage_core.workspace import Workspace

    out_dir = Workspace(r.workspace).stage_dir("export")
    rows: list[tuple[str, Any]] = [("avatar", r.avatar_stage)]
    paths: list[tuple[str, Path]] = []
    for name, e in r.items.items():
        if name == "gaussian-avatars":
            moved = e.get("rebound_from_mouth_interior")
            rows.append((name, f"{e.get('gaussians', '?')} Gaussians bound to GaussianAvatars' FLAME ({e.get('ga_vertices', '?')} vertices, "
                               f"{e.get('ga_faces', '?')} faces), {e.get('timesteps', '?')} FLAME frames"
                               + (f"; {moved} surfels of sage's mouth interior rebound" if moved else "")))
        elif name == "web":
            rows.append((name, f"{e.get('frames', '?')} frames, {e.get('surfels', '?')} surfels; open index.html in a browser"))
        elif viewer_format(name) is not None:
            orient = f", {e['orientation']} orientation" if e.get("orientation") else ""
            if "frames" in e:
                rows.append((name, f"{e['frames']} files{orient}, {e['rows_dropped']} rows dropped in all (non-finite or opacity < 1/255)"))
                folder = e.get("sequence_folder") or "ply"
                paths.append((name, out_dir / folder))
                continue
            rows.append((name, f"{e.get('rows', '?')} surfels written{orient}, {e.get('rows_dropped', '?')} rows dropped (non-finite or opacity < 1/255)"))
        elif name.startswith("mesh:"):
            rows.append((name, f"{e.get('vertices', '?')} vertices, {e.get('faces', '?')} faces" + (" (canonical space)" if name == "mesh:sdf" else "")))
        files = e["files"] if name not in ("bundle", "gaussian-avatars", "web") else [e["files"][0].split("/", 1)[0]] if e["files"] else []
        for rel in files:
            paths.append((name, out_dir / rel))
    if "bundle" in r.items:
        e = r.items["bundle"]
        need = "" if e.get("flame_model", "included") == "included" else f" --flame-model {e['flame_model'].split(': ', 1)[-1]}"
        what = f"FLAME model {e['flame_model']}; " if e.get("flame_model") else ""
        rows.append(("bundle", f"{what}drive it with `sage reenact --bundle {out_dir / 'bundle'}{need} --flame-seq SEQ --orbit`"))
    if not r.skipped:
        rows.append(("wall time", f"{r.wall_time_s:.1f} s"))
    summary_panel("sage export", rows, paths)
