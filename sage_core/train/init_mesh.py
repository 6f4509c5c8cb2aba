"""The init-mesh stage: canonical FLAME mesh, mouth interior, and the SDF pretrained on the mesh.

Outputs (into the stage's work folder):
    flame_model.npz      the FLAME model as later stages use it (with the mouth interior appended)
    regions.json         region vertex/face sets of that model (``Regions.to_dict``)
    canonical_mesh.ply   canonical mesh of the whole model (head, eyes, teeth, mouth interior)
    head_mesh.ply        the outer head surface the SDF is fitted to
    mouth_interior.ply   the mouth-interior parts alone (when added)
    sdf.pt               SDF network state dict and its constructor arguments (a safetensors file,
                         :func:`save_sdf`; kind ``sage-sdf``)
    sdf_mesh.ply         marching-cubes zero level set of the pretrained SDF
    metrics.json         fit quality (also in the manifest)
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from ..config import InitMeshConfig
from ..data.dataset import IngestedData
from ..errors import InputError
from ..fields.pretrain import PretrainConfig as _EnginePretrainConfig
from ..fields.pretrain import SDFPretrainer
from ..fields.sdf import SDFNetwork
from ..fields.sdf_file import save_sdf
from ..flame import FlameModel, FlameModelData, Regions, add_mouth_interior, has_mouth_interior, has_teeth, save_flame_npz
from ..flame.canonical import canonical_vertices
from ..geometry.marching import extract_mesh
from ..workspace import atomic_write_bytes, atomic_write_json
from .loop import run_steps

Progress = Callable[..., None]

def build_model(data: IngestedData, mouth_interior: bool, cavity: bool = True, tongue: bool = False) -> tuple[FlameModelData, Regions | None]:
    """The ingested FLAME model, with the mouth interior appended when asked and possible.

    cavity: with ``mouth_interior``, the cavity and (when the model has none) the teeth; False: only
    the teeth, when the model has none (FLAME with teeth, as GaussianAvatars rigs it); tongue: with
    the cavity, also the tongue (:func:`sage_core.flame.add_mouth_interior`). Returns the
    model and its regions (None when the capture came without region masks; then the mouth
    interior cannot be located and is not added).
    """
    model = data.load_model()
    masks = data.load_masks_json()
    if not masks:
        return model, None
    regions = Regions(masks, model.faces, model.n_vertices, model.vertex_groups)
    wanted = cavity and not has_mouth_interior(model) or not cavity and not has_teeth(model)
    if mouth_interior and wanted:
        try:
            model = add_mouth_interior(model, regions, cavity=cavity, tongue=tongue and cavity)
        except ValueError as e:
            raise InputError(data.masks_path or data.root, f"cannot place the mouth interior: {e}") from None
        regions = Regions(masks, model.faces, model.n_vertices, model.vertex_groups)
    return model, regions


def head_faces(model: FlameModelData) -> np.ndarray:
    """Faces of the outer head surface: every face whose vertices are all original FLAME vertices
    (teeth and mouth-interior parts, which lie inside the head, are left out)."""
    f = np.asarray(model.faces)
    keep = (f < model.n_base_vertices).all(axis=1)
    return f[keep]


def sdf_box(vertices: np.ndarray, padding: float) -> tuple[np.ndarray, np.ndarray]:
    """A cube around the mesh: centre of its bounding box, half size = largest half size × (1 + padding)."""
    lo, hi = vertices.min(0), vertices.max(0)
    c = 0.5 * (lo + hi)
    h = 0.5 * float((hi - lo).max()) * (1.0 + padding)
    return c - h, c + h


def sdf_constructor_args(cfg: InitMeshConfig, bbox_min: np.ndarray, bbox_max: np.ndarray) -> dict[str, Any]:
    """Keyword arguments of :class:`SDFNetwork` for this config and box (plain data)."""
    return {
        "bbox_min": [float(x) for x in bbox_min],
        "bbox_max": [float(x) for x in bbox_max],
        "n_levels": cfg.grid.n_levels,
        "n_features": cfg.grid.n_features,
        "log2_table": cfg.grid.log2_table,
        "base_res": cfg.grid.base_res,
        "max_res": cfg.grid.max_res,
        "hidden": cfg.sdf.hidden,
        "n_hidden_layers": cfg.sdf.n_hidden_layers,
        "feature_dim": cfg.sdf.feature_dim,
        "sphere_radius": cfg.sphere_radius,
    }


def _mesh_bytes(vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray | None = None) -> bytes:
    import trimesh

    mesh = trimesh.Trimesh(vertices=np.asarray(vertices, np.float64), faces=np.asarray(faces, np.int64), process=False)
    if colors is not None:
        mesh.visual.vertex_colors = colors
    return mesh.export(file_type="ply")


def _region_colours(regions: Regions | None, n_vertices: int) -> np.ndarray | None:
    if regions is None:
        return None
    palette = {
        "skin": (220, 180, 160), "hair": (90, 60, 40), "lips": (200, 90, 100), "eyeballs": (240, 240, 250),
        "neck": (190, 160, 140), "ears": (210, 150, 140), "teeth": (250, 250, 230), "mouth_interior": (150, 40, 60),
    }
    col = np.full((n_vertices, 4), 255, np.uint8)
    col[:, :3] = (170, 170, 170)
    for name, rgb in palette.items():
        if regions.has(name):
            col[regions.vertex_mask(name), :3] = rgb
    return col


def run_init_mesh(
    data: IngestedData,
    out_dir: Path,
    cfg: InitMeshConfig,
    *,
    device: str = "cpu",
    seed: int = 0,
    checkpoint_dir: Path | None = None,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """Run the stage; returns its metrics. Resumes from the newest checkpoint in ``checkpoint_dir``."""
    out_dir = Path(out_dir)
    model_data, regions = build_model(data, cfg.mouth_interior, cfg.mouth_cavity, cfg.mouth_tongue)
    model = FlameModel(model_data).to(device)
    verts = canonical_vertices(model, data.params, data.canonical_timestep).detach().cpu().numpy().astype(np.float64)
    faces_all = np.asarray(model_data.faces, np.int64)
    faces_head = head_faces(model_data)

    save_flame_npz(model_data, out_dir / "flame_model.npz")
    if regions is not None:
        atomic_write_json(out_dir / "regions.json", regions.to_dict())
    atomic_write_bytes(out_dir / "canonical_mesh.ply", _mesh_bytes(verts, faces_all, _region_colours(regions, len(verts))))
    atomic_write_bytes(out_dir / "head_mesh.ply", _mesh_bytes(verts, faces_head))
    n_mouth_faces = 0
    if has_mouth_interior(model_data) or has_teeth(model_data):
        groups = [g for g in model_data.vertex_groups if g.startswith("mouth_") or g.startswith("teeth_")]
        ids = np.unique(np.concatenate([np.asarray(model_data.vertex_groups[g]) for g in groups])) if groups else np.zeros(0, np.int64)
        inside = np.isin(faces_all, ids).all(axis=1)
        n_mouth_faces = int(inside.sum())
        if n_mouth_faces:
            atomic_write_bytes(out_dir / "mouth_interior.ply", _mesh_bytes(verts, faces_all[inside]))

    # --- SDF pretraining ---------------------------------------------------------------
    bmin, bmax = sdf_box(verts[np.unique(faces_head)], cfg.bbox_padding)
    args = sdf_constructor_args(cfg, bmin, bmax)
    torch.manual_seed(seed)
    net = SDFNetwork(**args).to(device)
    pcfg = _EnginePretrainConfig(
        steps=cfg.pretrain.steps,
        batch_size=cfg.pretrain.batch_size,
        bank_size=cfg.pretrain.bank_size,
        lr_grid=cfg.pretrain.lr_grid,
        lr_mlp=cfg.pretrain.lr_mlp,
        near_sigmas=(float(cfg.pretrain.near_sigmas[0]), float(cfg.pretrain.near_sigmas[1])),
        truncation=cfg.pretrain.truncation,
        w_value=cfg.pretrain.w_value,
        w_normal=cfg.pretrain.w_normal,
        w_eikonal=cfg.pretrain.w_eikonal,
        confidence_band=cfg.pretrain.confidence_band,
        eval_resolution=cfg.mc_resolution,
        eval_samples=cfg.pretrain.eval_samples,
    )
    gen = torch.Generator().manual_seed(seed)
    trainer = SDFPretrainer(net, verts, faces_head, pcfg, generator=gen)
    total = pcfg.steps
    loop = run_steps(trainer, total, label="init-mesh", progress=progress, checkpoint_dir=checkpoint_dir,
                     checkpoint_every=cfg.checkpoint_every, state_key="pretrainer", map_location=device,
                     stats=lambda out: {k: float(v) for k, v in out.items() if k in ("loss", "value", "normal", "eikonal")},
                     stats_label="pretrain SDF")  # fmt: skip
    losses = dict(loop.last)

    # --- evaluation and outputs --------------------------------------------------------
    if progress is not None:
        progress(total, total, "marching cubes")
    ev = trainer.evaluate(cfg.mc_resolution)
    mv, mf = extract_mesh(net.sdf, net.bbox_min, net.bbox_max, cfg.mc_resolution, device=device)
    atomic_write_bytes(out_dir / "sdf_mesh.ply", _mesh_bytes(mv, mf))
    save_sdf(out_dir / "sdf.pt", args, net)

    diag = float(np.linalg.norm(verts[np.unique(faces_head)].max(0) - verts[np.unique(faces_head)].min(0)))
    metrics = {
        "n_vertices": int(len(verts)),
        "n_faces": int(len(faces_all)),
        "n_head_faces": int(len(faces_head)),
        "n_mouth_faces": n_mouth_faces,
        "head_diagonal_m": diag,
        "mean_abs_sdf_vertices_m": float(ev["mean_abs_sdf_vertices"]),
        "mean_abs_sdf_rel": float(ev["mean_abs_sdf_rel"]),
        "normal_cos": float(ev["normal_cos"]),
        "chamfer_m": float(ev["chamfer"]),
        "chamfer_rel": float(ev["chamfer"]) / diag if diag > 0 else float("nan"),
        "sdf_mesh_faces": int(len(mf)),
        "final_loss": float(losses.get("loss", float("nan"))) if losses else float("nan"),
        "pretrain_steps": total,
    }
    atomic_write_json(out_dir / "metrics.json", metrics)
    return metrics
