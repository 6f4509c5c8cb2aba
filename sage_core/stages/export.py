"""The export stage: viewer files (3DGS PLY, .splat, compressed PLY), a GaussianAvatars folder, a
web player, meshes, and the animatable avatar bundle, accumulating in ``WS/export/``.

- ``ply/canonical.ply`` (canonical pose) or ``ply/frame_{T:05d}.ply`` (dataset timestep T):
  INRIA-layout PLY, SH degree 0 from the avatar's colours (``f_dc = (rgb − 0.5) / 0.28209479``;
  ``sh_degree 3`` zero-pads), thin third scale (docs/formats.md §7.1); ``splat`` / ``compressed-ply``
  write ``.splat`` and ``.compressed.ply`` beside them. With ``orientation viewer`` (the default)
  the world is turned by 180° about x into the y-down convention of splat viewers; ``flame`` keeps
  sage's y-up world and adds ``-flame`` to the file name (``canonical-flame.splat``), since a
  ``.splat`` cannot say which world it is in;
- ``ply/seq_<motion>[-flame]/{i:05d}.*``: one viewer file per frame of a driving motion, one motion
  per folder (a later export of another motion, motion length or avatar into the same folder
  replaces every format of the earlier one there);
- ``gaussian_avatars/``: ``point_cloud.ply`` + ``flame_param.npz`` (+ ``sage_export.json``) for
  GaussianAvatars' tools (:mod:`sage_core.export.gaussian_avatars`);
- ``web/``: ``index.html``, ``player.js``, ``avatar.js``: a page playing the avatar in a browser
  (:mod:`sage_core.export.web`);
- ``mesh/sdf_mesh.{ply,obj}``: zero level set of the canonical SDF (canonical space);
  ``mesh/flame_canonical.{ply,obj}`` or ``mesh/flame_frame_{T:05d}.{ply,obj}``: the posed FLAME mesh;
- ``bundle/``: ``avatar.safetensors`` + ``flame_param.npz`` + ``bundle.json`` (docs/formats.md §7.2).

``WS/export/results.json`` indexes every item with the key of its inputs and EVERY file it wrote
(relative to ``WS/export/``); a new export keeps the earlier items whose avatar is unchanged (their
files are carried over whole), and an item whose key is unchanged and whose files are all there is
not redone. The manifest lists every file, so a file deleted later makes the stage incomplete.
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
WEB_FILES = ("web/index.html", "web/player.js", "web/avatar.js")
"""Every file of the web player (an earlier version listed only ``index.html`` in its record)."""


@dataclass
class ExportResult(StageResult):
    """:class:`StageResult` of export: ``avatar_stage`` exported and ``items`` (results-index
    entries of the requested items: ``files`` relative to ``WS/export/`` and per-item numbers)."""

    avatar_stage: str = ""
    items: dict[str, Any] = field(default_factory=dict)


def viewer_format(name: str) -> str | None:
    """"ply" / "splat" / "compressed-ply" for a viewer item name (``ply:canonical``), else None."""
    return name.split(":", 1)[0] if name.startswith(_VIEWER_ITEMS) else None


def orientation_tag(orientation: str) -> str:
    """The file-name tag of a viewer orientation: "" for viewer (the default), "-flame" otherwise."""
    return "" if orientation == "viewer" else f"-{orientation}"


def sequence_folder(label: str, orientation: str) -> str:
    """``ply/seq_<label>[-flame]``: the folder of one motion's per-frame viewer files."""
    return f"ply/seq_{label}{orientation_tag(orientation)}"


def pose_stem(frame: int | None) -> str:
    """``canonical`` or ``frame_{T:05d}``: the file stem of a pose."""
    return "canonical" if frame is None else f"frame_{frame:05d}"


def entry_files(name: str, entry: dict[str, Any]) -> list[str]:
    """The files of a results entry (an entry of an earlier version that listed only part of its
    files gets the rest: the web player's ``player.js`` and ``avatar.js``)."""
    files = list(entry.get("files") or [])
    if name == "web" and files == ["web/index.html"]:
        files = list(WEB_FILES)
    return files


def _folder_files(root: Path, rel: str) -> list[str]:
    """Every file under ``root/rel``, as paths relative to ``root`` (sorted)."""
    return sorted(p.relative_to(root).as_posix() for p in (root / rel).rglob("*") if p.is_file())


def workspace_preset(ws: str | Path | Workspace) -> str | None:
    """The preset the workspace's avatar was trained with, or None when nothing tells.

    A manifest records the resolved config, not the preset's name, so this is the preset whose
    phase 1 and init-mesh settings agree with the recorded ones (``WS/phase1/config.json``,
    ``WS/init/config.json``) on the most of the fields the presets set: a run with a few flags on
    top of ``--preset tiny`` is still a tiny workspace. Ties go to the larger preset.
    """
    from ..config import PRESET_OVERRIDES, PRESETS, resolve_config, to_dict
    from ..workspace import read_json

    w = as_workspace(ws)
    recorded: dict[str, dict[str, Any]] = {}
    for stage in ("phase1", "init-mesh"):
        path = w.stage_dir(stage) / "config.json"
        try:
            doc = read_json(path) if path.is_file() else None
        except (OSError, ValueError):
            doc = None
        if isinstance(doc, dict):
            recorded[stage] = doc
    if not recorded:
        return None

    def flat(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
        out: dict[str, Any] = {}
        for k, v in d.items():
            out.update(flat(v, f"{prefix}{k}.") if isinstance(v, dict) else {f"{prefix}{k}": v})
        return out

    scores: dict[str, int] = {}
    for preset in PRESETS:
        score = 0
        for stage, doc in recorded.items():
            keys = {k for p in PRESETS for k in PRESET_OVERRIDES[p].get(stage, {})}
            mine, theirs = flat(to_dict(resolve_config(stage, preset))), flat(doc)
            score += sum(1 for k in keys if k in theirs and theirs[k] == mine.get(k))
        scores[preset] = score
    best = max(scores.values())
    return [p for p in PRESETS if scores[p] == best][-1]


def workspace_flame_source(ws: Workspace, data: Any, avatar: Any) -> Any:
    """The :class:`~sage_core.export.bundle.FlameSource` of a workspace's avatar: the user's model
    file named by ingest (its full SHA-256 when the file is still there with the content ingest
    hashed, else the hash prefix ingest recorded), the ingested model, and the lip vertex ids the
    mouth interior was placed from (when init-mesh appended one)."""
    from ..export.bundle import FlameSource
    from ..flame.regions import Regions
    from ..workspace import file_sha256

    prefix = str(((ws.manifest("ingest") or {}).get("inputs") or {}).get("files", {}).get("flame_model", ""))
    src = Path(str(data.summary.get("model_source") or "flame_model"))
    full = None
    if src.is_file():
        digest = file_sha256(src)
        full = digest if digest.startswith(prefix) else None
    base = data.load_model()
    lips = None
    if int(avatar.model_data.v_template.shape[0]) > base.n_vertices:
        masks = data.load_masks_json()
        if masks:
            regions = Regions(masks, base.faces, base.n_vertices, base.vertex_groups)
            if regions.has("lips"):
                ids = regions.vertex_ids("lips")
                lips = sorted({int(i) for i in ids if 0 <= int(i) < base.n_base_vertices})
    cavity = "mouth_upper" in avatar.model_data.vertex_groups
    return FlameSource(src.name, full, prefix, base, lips, cavity)


def check_export_options(*, viewer: list[str], mesh: bool, bundle: bool, gaussian_avatars: bool, web: bool,
                         frame: int | None, flame_seq: Any, max_frames: int | None) -> None:  # fmt: skip
    """ConfigError for options that would be ignored or contradict each other (before anything is
    read): ``--frame`` with ``--flame-seq``, ``--max-frames`` without a sequence to cut (a
    ``--flame-seq``, or the avatar's own sequence played by ``--web`` / ``--gaussian-avatars``) or
    with ``--frame``, ``--flame-seq`` without an item that plays it, and ``--frame`` with only the
    bundle (which holds every timestep)."""
    from ..errors import ConfigError

    for f in viewer:
        if f not in VIEWER_FORMATS:
            raise ConfigError(f"viewer format {f!r}: use one of {', '.join(VIEWER_FORMATS)}")
    if frame is not None and flame_seq is not None:
        raise ConfigError("give --frame or --flame-seq, not both")
    if max_frames is not None:
        if max_frames < 1:
            raise ConfigError(f"--max-frames must be >= 1, got {max_frames}")
        if frame is not None:
            raise ConfigError("--max-frames cuts a sequence; --frame poses a single timestep: give one of them")
        if flame_seq is None and not (web or gaussian_avatars):
            raise ConfigError("--max-frames cuts a sequence: add --flame-seq, or --web / --gaussian-avatars "
                              "(which play the avatar's own sequence)")  # fmt: skip
    if flame_seq is not None and not (viewer or gaussian_avatars or web):
        raise ConfigError("--flame-seq drives per-frame viewer files, --gaussian-avatars or --web: add one of them")
    if frame is not None and not (viewer or mesh or gaussian_avatars or web):
        raise ConfigError("--frame poses viewer files, meshes, --gaussian-avatars or --web; the bundle holds every timestep")


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
    include_flame_model: bool = False,
    settings: StageSettings = StageSettings(),
    on_event: EventFn | None = None,
) -> ExportResult:
    """Export the avatar (``cfg.stage``: auto, phase1, phase2) into ``WS/export/``.

    viewer: viewer files to write (:data:`VIEWER_FORMATS`) at the canonical pose, dataset timestep
    ``frame``, or one per frame of the motion ``flame_seq`` (its first ``max_frames``). mesh, bundle,
    gaussian_avatars, web: the other outputs. gaussian_avatars and web play a sequence: ``flame_seq``,
    else the single timestep ``frame``, else the avatar's own tracked sequence (its first
    ``max_frames``). Items already exported from the same avatar with the same settings are not
    redone (all of them: a ``skipped`` event); ``settings.force`` redoes them. The bundle references
    the user's FLAME model (its file name and SHA-256) instead of carrying it, unless
    ``include_flame_model``. ConfigError for
    options that would be ignored (:func:`check_export_options`), InputError for a missing
    timestep, camera or motion.
    """
    from ..data.dataset import IngestedData
    from ..errors import InputError
    from .avatars import resolve_avatar_stage
    from .reenact import seq_label
    from .results import fresh_results, result_key
    from ..workspace import file_fingerprint

    t0 = time.time()
    emitter = Emitter("export", on_event)
    emitter.emit("started")
    viewer = list(viewer)
    check_export_options(viewer=viewer, mesh=mesh, bundle=bundle, gaussian_avatars=gaussian_avatars, web=web, frame=frame,
                         flame_seq=flame_seq, max_frames=max_frames)  # fmt: skip
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
    tag = orientation_tag(cfg.orientation)
    wanted: dict[str, str] = {}
    seq_key = {"seq": None if flame_seq is None else str(Path(flame_seq).resolve()), "seq_fp": seq_fp, "max_frames": max_frames}
    played = {**seq_key, "frame": frame}  # the sequence that --web and --gaussian-avatars play
    seq_dir = None if flame_seq is None else sequence_folder(seq_label(Path(flame_seq)), cfg.orientation)
    # one motion per sequence folder: what identifies the sequence whose frames it holds
    seq_id = result_key(**base, **seq_key, orientation=cfg.orientation, color_camera=cfg.color_camera)
    for fmt in viewer:
        name = f"{fmt}:{seq_dir.split('/', 1)[1]}" if seq_dir is not None else f"{fmt}:{pose}{tag}"
        wanted[name] = result_key(item=name, **base, color_camera=cfg.color_camera, up_axis=cfg.up_axis,
                                  orientation=cfg.orientation, sh_degree=cfg.sh_degree if fmt != "splat" else 0,
                                  **seq_key)  # fmt: skip
    if gaussian_avatars:
        wanted["gaussian-avatars"] = result_key(item="gaussian-avatars", **base, **played, layout=2)
    if web:
        wanted["web"] = result_key(item="web", **base, **played, color_camera=cfg.color_camera, player=2)
    if mesh:
        wanted["mesh:sdf"] = result_key(item="mesh:sdf", **base, mc_resolution=cfg.mc_resolution)
        wanted[f"mesh:flame-{pose}"] = result_key(item=f"mesh:flame-{pose}", **base)
    if bundle:
        wanted["bundle"] = result_key(item="bundle", **base, up_axis=cfg.up_axis, flame_model=include_flame_model, layout=3)
    existing = fresh_results(ws, "export")
    for name, entry in list(existing.items()):
        files = entry_files(name, entry)
        if not all((ws.stage_dir("export") / rel).is_file() or (ws.stage_dir("export") / rel).is_dir() for rel in files):
            del existing[name]  # an entry with a file gone is redone (or dropped) rather than carried half
        else:
            existing[name] = {**entry, "files": files}
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

    keep = {k: v for k, v in existing.items() if k not in todo}
    if seq_dir is not None:  # another sequence in the same folder is replaced, every format of it
        keep = {k: v for k, v in keep.items()
                if not (v.get("sequence_folder") == seq_dir and v.get("sequence_id") != seq_id)}  # fmt: skip
    requires = ["ingest", *sorted({v["avatar_stage"] for v in keep.values()} | {av_stage})]
    holder: dict[str, Any] = {}

    def body(run, progress) -> None:
        import torch

        from ..geometry.rigid import world_to_canonical
        from ..export.avatar_ply import VIEWER_SUFFIX, write_posed_ply
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
        colours = "colours: SH degree 0 baked " + ("along each surfel normal" if cfg.color_camera is None else f"for camera {cfg.color_camera}")
        comments = [f"sage avatar {av_stage}", f"pose {'canonical' if frame is None else f'timestep {frame}'}", colours,
                    f"orientation {cfg.orientation}"]  # fmt: skip
        results = dict(keep)
        steps = len(todo)
        motion_cache: dict[str, Any] = {}

        def get_motion() -> Any:
            if "m" not in motion_cache:
                from .motion import load_driving_motion

                assert flame_seq is not None
                motion_cache["m"] = load_driving_motion(av, flame_seq, max_frames)
            return motion_cache["m"]

        def played_params() -> tuple[Any, float, str]:
            """The FLAME rows --web and --gaussian-avatars play, their frame rate and a label."""
            if flame_seq is not None:
                m = get_motion()
                return m.params, float(m.fps), f"motion {m.source} ({m.n_frames} frames)"
            p = av.params
            if frame is not None:
                return p.select([p.row_of(frame)]), 25.0, f"timestep {frame}"
            if max_frames is not None and max_frames < p.n_timesteps:
                p = p.select(list(range(max_frames)))
            return p, 25.0, f"the avatar's own sequence ({p.n_timesteps} frames)"

        view_opts = {"up_axis": cfg.up_axis, "orientation": cfg.orientation}
        for i, name in enumerate(todo):
            progress(i, steps, name)
            extra: dict[str, Any] = {}
            fmt = viewer_format(name)
            deg = cfg.sh_degree if fmt != "splat" else 0
            if fmt is not None and seq_dir is not None:
                from .motion import with_identity

                motion = get_motion()
                dropped = 0
                files = [f"{seq_dir}/{j:05d}{VIEWER_SUFFIX[fmt]}" for j in range(motion.n_frames)]
                for j in range(motion.n_frames):
                    posed = renderer.posed(with_identity(av, motion.frame_inputs(j, dev)), view_from)
                    r = write_posed_ply(run.work_dir / files[j], posed, sh_degree=deg, fmt=fmt, **view_opts,
                                        comments=[f"sage avatar {av_stage}", f"motion frame {j}", colours, f"orientation {cfg.orientation}"])  # fmt: skip
                    dropped += r.n_dropped
                    progress(i, steps, f"{name} {j + 1}/{motion.n_frames}")
                extra = {"frames": motion.n_frames, "rows_dropped": dropped, "source": str(motion.source),
                         "sequence_folder": seq_dir, "sequence_id": seq_id, "orientation": cfg.orientation}  # fmt: skip
            elif fmt is not None:
                files = [f"ply/{pose_stem(frame)}{tag}{VIEWER_SUFFIX[fmt]}"]
                r = write_posed_ply(run.work_dir / files[0], renderer.posed(inputs, view_from), comments=comments,
                                    sh_degree=deg, fmt=fmt, **view_opts)  # fmt: skip
                extra = {"rows": r.n_rows, "rows_dropped": r.n_dropped, "orientation": cfg.orientation,
                         "pose": "canonical" if frame is None else f"timestep {frame}"}  # fmt: skip
            elif name == "gaussian-avatars":
                params, _, label = played_params()
                ga = write_gaussian_avatars(av, run.work_dir / "gaussian_avatars", params)
                files = _folder_files(run.work_dir, "gaussian_avatars")
                extra = {"gaussians": ga.n_gaussians, "timesteps": ga.n_timesteps, "vertices": ga.n_vertices, "sequence": label,
                         **ga.record()}  # fmt: skip
            elif name == "web":
                from ..export.web import write_web_player

                params, fps, label = played_params()
                wp = write_web_player(av, renderer, params, run.work_dir / "web", reference_camera(data, cfg.color_camera),
                                      fps=fps, view_from=view_from, title=f"sage avatar ({av_stage})",
                                      progress=lambda d, t, m: progress(i, steps, f"web {m}"))  # fmt: skip
                files = list(WEB_FILES)
                extra = {"frames": wp.n_frames, "surfels": wp.n_surfels, "bytes": wp.n_bytes, "sequence": label}
            elif name == "mesh:sdf":
                files = ["mesh/sdf_mesh.ply", "mesh/sdf_mesh.obj"]
                v, f = sdf_mesh(av, cfg.mc_resolution)
                for rel in files:
                    write_mesh(run.work_dir / rel, v, f)
                extra = {"vertices": int(v.shape[0]), "faces": int(f.shape[0]), "space": "canonical",
                         "mc_resolution": cfg.mc_resolution}  # fmt: skip
            elif name.startswith("mesh:flame"):
                files = [f"mesh/flame_{pose_stem(frame)}.ply", f"mesh/flame_{pose_stem(frame)}.obj"]
                v, f = posed_mesh(av, inputs)
                for rel in files:
                    write_mesh(run.work_dir / rel, v, f)
                extra = {"vertices": int(v.shape[0]), "faces": int(f.shape[0])}
            else:
                flame_src = None if include_flame_model else workspace_flame_source(run.ws, data, av)
                try:
                    write_bundle(av, run.work_dir / "bundle", loaded.render, reference_camera=reference_camera(data),
                                 head_center=head_center(data), up_axis=cfg.up_axis, flame_source=flame_src,
                                 source={"workspace": "../..", "stage": av_stage, "fingerprint": loaded.fingerprint})  # fmt: skip
                except ValueError as e:
                    from ..errors import StageError

                    raise StageError(f"bundle: {e}") from None
                files = _folder_files(run.work_dir, "bundle")
                extra = {"flame_model": "included" if flame_src is None else f"referenced: {flame_src.file_name}",
                         "bytes": sum((run.work_dir / rel).stat().st_size for rel in files)}  # fmt: skip
            missing = [rel for rel in files if not (run.work_dir / rel).is_file()]
            assert not missing, f"{name}: {missing} not written"
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
    return finish_result(result, outcome, ws, emitter, t0)
