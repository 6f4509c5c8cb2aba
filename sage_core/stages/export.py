"""The export stage: viewer files (3DGS PLY, .splat, compressed PLY), a GaussianAvatars folder, a
web player, meshes, and the animatable avatar bundle, accumulating in ``WS/export/``.

- ``ply/canonical.ply`` (canonical pose), ``ply/frame_{T:05d}.ply`` (dataset timestep T) or
  ``ply/{i:05d}.ply`` (frame i of a motion): INRIA-layout PLY, SH degree 0 from the avatar's colours
  (``f_dc = (rgb − 0.5) / 0.28209479``; ``sh_degree 3`` zero-pads), thin third scale (docs/formats.md
  §7.1); ``splat`` / ``compressed-ply`` write ``.splat`` and ``.compressed.ply`` beside them. With
  ``orientation viewer`` the world is turned by 180° about x into the y-down convention of splat
  viewers; ``flame`` keeps sage's y-up world;
- ``gaussian_avatars/``: ``point_cloud.ply`` + ``flame_param.npz`` for GaussianAvatars' tools
  (:mod:`sage_core.export.gaussian_avatars`);
- ``web/``: ``index.html`` playing the avatar in a browser (:mod:`sage_core.export.web`);
- ``mesh/sdf_mesh.{ply,obj}``: zero level set of the canonical SDF (canonical space);
  ``mesh/flame_canonical.{ply,obj}`` or ``mesh/flame_frame_{T:05d}.{ply,obj}``: the posed FLAME mesh;
- ``bundle/``: ``avatar.safetensors`` + ``flame_param.npz`` + ``bundle.json`` (docs/formats.md §7.2).

``WS/export/results.json`` indexes every item with the key of its inputs; a new export keeps the
earlier items whose avatar is unchanged, and an item whose key is unchanged is not redone.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..config import ExportConfig
from ..workspace import Workspace
from ._runner import StageResult, StageSettings, as_workspace, execute_stage, finish_result
from .events import Emitter, EventFn

VIEWER_FORMATS: tuple[str, ...] = ("ply", "splat", "compressed-ply")
EXPORT_FORMATS: tuple[str, ...] = (*VIEWER_FORMATS, "gaussian-avatars", "web", "mesh", "bundle")
_VIEWER_ITEMS = tuple(f"{f}:" for f in VIEWER_FORMATS)


@dataclass
class ExportResult(StageResult):
    """:class:`StageResult` of export: ``avatar_stage`` exported and ``items`` (results-index
    entries of the requested items: ``files`` relative to ``WS/export/`` and per-item numbers)."""

    avatar_stage: str = ""
    items: dict[str, Any] = field(default_factory=dict)


def viewer_format(name: str) -> str | None:
    """"ply" / "splat" / "compressed-ply" for a viewer item name (``ply:canonical``), else None."""
    return name.split(":", 1)[0] if name.startswith(_VIEWER_ITEMS) else None


def _item_files(name: str, frame: int | None, n_seq: int = 0) -> list[str]:
    from ..export.avatar_ply import VIEWER_SUFFIX

    pose = "canonical" if frame is None else f"frame_{frame:05d}"
    fmt = viewer_format(name)
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


def export_stage(
    ws: str | Path | Workspace,
    cfg: ExportConfig,
    *,
    viewer: list[str] | tuple[str, ...] = ("ply",),
    mesh: bool = False,
    bundle: bool = True,
    gaussian_avatars: bool = False,
    web: bool = False,
    frame: int | None = None,
    flame_seq: str | Path | None = None,
    max_frames: int | None = None,
    settings: StageSettings = StageSettings(),
    on_event: EventFn | None = None,
) -> ExportResult:
    """Export the avatar (``cfg.stage``: auto, phase1, phase2) into ``WS/export/``.

    viewer: viewer files to write (:data:`VIEWER_FORMATS`) at the canonical pose, dataset timestep
    ``frame``, or one per frame of the motion ``flame_seq`` (its first ``max_frames``). mesh, bundle,
    gaussian_avatars, web: the other outputs (the last two follow ``flame_seq`` too). Items already
    exported from the same avatar with the same settings are not redone (all of them: a ``skipped``
    event); ``settings.force`` redoes them. InputError for a missing timestep, camera or motion.
    """
    from ..data.dataset import IngestedData
    from ..errors import ConfigError, InputError
    from .avatars import resolve_avatar_stage
    from .results import fresh_results, result_key
    from ..workspace import file_fingerprint

    t0 = time.time()
    emitter = Emitter("export", on_event)
    emitter.emit("started")
    viewer = list(viewer)
    for f in viewer:
        if f not in VIEWER_FORMATS:
            raise ConfigError(f"viewer format {f!r}: use one of {', '.join(VIEWER_FORMATS)}")
    if frame is not None and flame_seq is not None:
        raise ConfigError("give --frame or --flame-seq, not both")
    ws = as_workspace(ws)
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
    todo = [k for k in wanted if settings.force or existing.get(k, {}).get("key") != wanted[k]]
    result = ExportResult("export", ws.root, avatar_stage=av_stage)
    if not todo:
        emitter.emit("skipped", message="every requested item is already exported from the same avatar with the same settings; "
                                        "skipping. Use --force to redo it.")  # fmt: skip
        result.items = {k: existing[k] for k in wanted}
        result.skipped = True
        result.fill(ws.manifest("export"), t0)
        emitter.emit("finished", result=result)
        return result

    # a new sequence replaces the files of an earlier one
    keep = {k: v for k, v in existing.items() if k not in todo}
    requires = ["ingest", *sorted({v["avatar_stage"] for v in keep.values()} | {av_stage})]
    holder: dict[str, Any] = {}

    def body(run, progress) -> None:
        import torch

        from ..geometry.rigid import world_to_canonical
        from ..export.avatar_ply import write_posed_ply
        from ..export.gaussian_avatars import write_gaussian_avatars
        from ..export.bundle import write_bundle
        from ..export.meshes import posed_mesh, sdf_mesh, write_mesh
        from ..flame.canonical import canonical_inputs
        from .avatars import AvatarRenderer, head_center, load_stage_avatar, reference_camera
        from .results import carry_results
        from ..workspace import atomic_write_json, now_iso

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
                    centre = world_to_canonical(centre, R0, t, av.root_joint)
            view_from = centre
        comments = [f"sage avatar {av_stage}", f"pose {'canonical' if frame is None else f'timestep {frame}'}",
                    "colours: SH degree 0 baked " + ("along each surfel normal" if cfg.color_camera is None else f"for camera {cfg.color_camera}")]  # fmt: skip
        results = dict(keep)
        steps = len(todo)
        motion_cache: dict[str, Any] = {}

        def get_motion() -> Any:
            if "m" not in motion_cache:
                from .motion import load_driving_motion

                assert flame_seq is not None
                motion_cache["m"] = load_driving_motion(av, flame_seq, max_frames)
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
            fmt = viewer_format(name)
            deg = cfg.sh_degree if fmt != "splat" else 0
            if fmt is not None and name.endswith(":seq"):
                from .motion import with_identity

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
                from ..export.web import write_web_player

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
        progress(steps, steps, "done")
        atomic_write_json(run.work_dir / "results.json", results)
        for name, entry in results.items():
            if "rows_dropped" in entry:
                run.metrics[f"{name} rows_dropped"] = entry["rows_dropped"]
            run.outputs[name] = str(run.ws.stage_dir("export") / entry["files"][0]) if entry["files"] else ""
        holder["results"] = results

    emitter.title = f"export {av_stage}"
    external = {"flame_seq": seq_fp} if seq_fp is not None else None
    outcome = execute_stage("export", ws, cfg, body, dataclasses.replace(settings, force=True), emitter, requires=tuple(requires),
                            external_inputs=external, discard_work_on_failure=True)  # fmt: skip
    assert outcome.manifest is not None
    result.items = {k: holder["results"][k] for k in wanted}
    return finish_result(result, outcome, ws, emitter, t0)  # type: ignore[return-value]
