"""``sage export WS``: viewer files (3DGS PLY, .splat, compressed PLY), a GaussianAvatars folder, a
web player, meshes, and the animatable avatar bundle.

Outputs accumulate in ``WS/export/`` (a workspace stage with a manifest):

- ``ply/canonical.ply`` (canonical pose), ``ply/frame_{T:05d}.ply`` (dataset timestep T) or
  ``ply/{i:05d}.ply`` (frame i of ``--flame-seq``): INRIA-layout PLY, SH degree 0 from the
  avatar's colours (``f_dc = (rgb − 0.5) / 0.28209479``; ``--sh-degree 3`` zero-pads), thin third
  scale (docs/formats.md §7.1); ``--splat`` / ``--compressed-ply`` write ``.splat`` and
  ``.compressed.ply`` beside them. By default (``--orientation viewer``) the world is turned by
  180° about x into the y-down convention of splat viewers; ``--orientation flame`` keeps sage's
  y-up world;
- ``gaussian_avatars/``: ``point_cloud.ply`` + ``flame_param.npz`` for GaussianAvatars' tools
  (:mod:`sage_core.export.gaussian_avatars`);
- ``web/``: ``index.html`` playing the avatar in a browser (:mod:`sage_core.export.web`);
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
    PresetOpt,
    SeedOpt,
    SetOpt,
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
        flags = {"stage": stage, "mc_resolution": mc_resolution, "color_camera": color_camera,
                 "orientation": orientation, "sh_degree": sh_degree, **parse_sets(set_)}  # fmt: skip
        cfg = resolve_stage_config("export", preset, config, flags)
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
        from sage_core.stages import StageSettings, export_stage

        with StageDisplay(verbose, preset) as display:
            r = export_stage(ws, cfg, viewer=viewer, mesh=mesh, bundle=bundle, gaussian_avatars=gaussian_avatars, web=web, frame=frame,
                             flame_seq=flame_seq, max_frames=max_frames, settings=StageSettings(seed, device, force), on_event=display)  # fmt: skip
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
            rows.append((name, f"{e.get('gaussians', '?')} Gaussians bound to FLAME faces, {e.get('timesteps', '?')} FLAME frames"))
        elif name == "web":
            rows.append((name, f"{e.get('frames', '?')} frames, {e.get('surfels', '?')} surfels; open index.html in a browser"))
        elif viewer_format(name) is not None:
            if "frames" in e:
                rows.append((name, f"{e['frames']} files, {e['rows_dropped']} rows dropped in all (non-finite or opacity < 1/255)"))
                paths.append((name, out_dir / "ply"))
                continue
            rows.append((name, f"{e.get('rows', '?')} surfels written, {e.get('rows_dropped', '?')} rows dropped (non-finite or opacity < 1/255)"))
        elif name.startswith("mesh:"):
            rows.append((name, f"{e.get('vertices', '?')} vertices, {e.get('faces', '?')} faces" + (" (canonical space)" if name == "mesh:sdf" else "")))
        for rel in e["files"]:
            paths.append((name, out_dir / rel))
    if "bundle" in r.items:
        rows.append(("bundle", "drive it with `sage reenact --bundle " + str(out_dir / "bundle") + " --flame-seq SEQ --orbit`"))
    if not r.skipped:
        rows.append(("wall time", f"{r.wall_time_s:.1f} s"))
    summary_panel("sage export", rows, paths)
