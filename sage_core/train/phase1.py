"""Phase 1: joint optimisation of the triangle-bound surfels, the canonical SDF and the attribute
networks, supervised by the training images (SAGE §1–2).

Each step picks a random training frame (camera + timestep), poses the surfels with its FLAME
parameters, rasterizes them and combines:

* L_rgb = 0.8·L1 + 0.2·(1 − SSIM) of the surfel render;
* 2DGS normal consistency and depth distortion (from their start steps);
* L_pt and L_align at the canonical surfel centres (mouth-interior surfels excluded: the SDF models
  the outer head surface);
* on a random subset of foreground pixels, mapped to canonical rays (rigidly when the frame differs
  from canonical only by global rotation/translation, otherwise through the hit triangle of the
  posed mesh), NeuS volume rendering of the canonical SDF and appearance network: L1 against the
  image, L_D and L_N against the surfels' expected depth and rendered normal (the surfel side
  detached: the surfels supervise the SDF), eikonal on the NeuS samples and the surfel centres;
* MonoSDF normal smoothness at a subset of surfel centres.

Every random draw uses the trainer's own CPU generator, so a run resumed from ``state_dict`` repeats
the uninterrupted loss curve.
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from ..avatar.init import REGION_MOUTH
from ..avatar.model import Avatar, canonical_rays_rigid
from ..config import Phase1Config
from ..data.dataset import IngestedData, IngestedFrame
from ..evaluate.metrics import psnr, ssim
from ..flame.frames import surfel_frames
from ..render import RenderCamera
from ..render.mesh_raster import points_on_mesh, ray_directions, rasterize_mesh, warp_points_to_canonical, warp_directions_to_canonical
from ..render.volume import render_neus
from ..workspace import rng_state, set_rng_state
from . import losses as L
from ._groups import surfel_param_groups

Progress = Callable[..., None]
STATE_FORMAT = 1


def build_avatar(data: IngestedData, init_dir: str | Path, cfg: Phase1Config, device: str | torch.device, generator: torch.Generator) -> Avatar:
    """The phase-1 avatar from the init-mesh outputs and the config."""
    return Avatar.build(
        init_dir, data, cfg.n_surfels, cfg.attributes,
        app_args={"hidden": cfg.app_hidden, "n_layers": cfg.app_layers, "sh_degree": cfg.app_sh_degree},
        shape_args={"hidden": cfg.shape_hidden, "n_layers": cfg.shape_layers},
        sh_degree=cfg.sh_degree, init_opacity=cfg.init_opacity,
        init_args={"face_weight": cfg.face_weight, "mouth_weight": cfg.mouth_weight, "hair_weight": cfg.hair_weight,
                   "neck_weight": cfg.neck_weight, "camera_weight": cfg.camera_weight, "scale_factor": cfg.init_scale_factor},
        neus_variance=cfg.neus_variance, device=device, generator=generator,
    )  # fmt: skip


class CanonicalRays:
    """Maps a frame's pixels to canonical rays (rigid or through the posed mesh's hit triangles)."""

    def __init__(self, avatar: Avatar) -> None:
        self.avatar = avatar

    def map(
        self,
        flame_inputs: dict[str, torch.Tensor],
        camera: RenderCamera,
        pix: torch.Tensor,
        rigid: tuple[torch.Tensor, torch.Tensor] | None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """pix: (R,) flat pixel ids. Returns canonical origins (R, 3), unit directions (R, 3), the
        per-ray map of world distances to canonical distances (R,), world→canonical rotations
        (R, 3, 3) for normals, and a validity mask (R,) (False where a non-rigid ray misses the mesh)."""
        av = self.avatar
        o_w, d_w = ray_directions(camera.K, camera.w2c, camera.width, camera.height)
        o_w = o_w.reshape(-1, 3)[pix]
        d_w = d_w.reshape(-1, 3)[pix]
        R = pix.shape[0]
        if rigid is not None:
            R0, t = rigid
            o_c, d_c = canonical_rays_rigid(o_w, d_w, R0, t, av.root_joint)
            rot = R0.T.expand(R, 3, 3)
            return o_c, d_c, torch.ones(R, dtype=o_w.dtype, device=o_w.device), rot, torch.ones(R, dtype=torch.bool, device=o_w.device)
        with torch.no_grad():
            verts = av.pose_mesh(flame_inputs)
            ras = rasterize_mesh(verts, av.faces, camera.K, camera.w2c, camera.width, camera.height)
            fid = ras.face_id.reshape(-1)[pix]
            bary = ras.bary.reshape(-1, 3)[pix]
            ok = fid >= 0
            fid_s = torch.where(ok, fid, torch.zeros_like(fid))
            hit = points_on_mesh(verts, av.faces, fid_s, bary)
            fr_d = surfel_frames(verts, av.faces)
            fr_c = (av.R_c, av.T_c, av.k_c)
            hit_c = warp_points_to_canonical(hit, fid_s, fr_d, fr_c)
            d_c = warp_directions_to_canonical(d_w, fid_s, fr_d, fr_c)
            ratio = av.k_c[fid_s] / fr_d[2][fid_s]
            t_hit = ((hit - o_w) * d_w).sum(-1)
            o_c = hit_c - (t_hit * ratio)[:, None] * d_c
            rot = av.R_c[fid_s] @ fr_d[0][fid_s].transpose(-1, -2)
        return o_c, d_c, ratio, rot, ok


class Phase1Trainer:
    """Phase-1 optimisation (see the module doc).

    avatar: an :class:`Avatar` (mlp or free attributes); data: the ingested capture; cfg: the
    stage config; generator: CPU generator for every random draw (frames, rays, NeuS jitter).
    """

    def __init__(
        self,
        avatar: Avatar,
        data: IngestedData,
        cfg: Phase1Config,
        device: str | torch.device = "cpu",
        generator: torch.Generator | None = None,
    ) -> None:
        self.avatar = avatar
        self.data = data
        self.cfg = cfg
        self.device = torch.device(device)
        self.generator = generator if generator is not None else torch.Generator().manual_seed(0)
        self.step_count = 0
        self.frames: list[IngestedFrame] = list(data.train)
        if not self.frames:
            raise ValueError("no training frames")
        self._cache: dict[int, tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = {}
        self._inputs: dict[int, dict[str, torch.Tensor]] = {}
        self._rigid: dict[int, tuple[torch.Tensor, torch.Tensor] | None] = {}
        self.rays = CanonicalRays(avatar)
        self.length_unit = float(avatar.sdf.half_extent)
        self.optimizer = torch.optim.Adam(self._param_groups(), eps=1e-15)
        self._not_mouth = avatar.surfels.region_id != REGION_MOUTH

    # ------------------------------------------------------------------ setup
    def _param_groups(self) -> list[dict[str, Any]]:
        av, c = self.avatar, self.cfg
        return [
            {"name": "sdf_mlp", "params": av.sdf.mlp_parameters(), "lr": c.lr_sdf},
            {"name": "grid", "params": av.sdf.grid_parameters(), "lr": c.lr_grid},
            {"name": "variance", "params": list(av.variance.parameters()), "lr": c.lr_variance},
        ] + surfel_param_groups(
            av,
            lr_position=c.lr_position,
            lr_networks=c.lr_networks,
            lr_rotation=c.lr_rotation,
            lr_scale=c.lr_scale,
            lr_color=c.lr_color,
            lr_opacity=c.lr_opacity,
        )

    def _set_lrs(self) -> None:
        c = self.cfg
        t = min(1.0, self.step_count / max(1, c.iterations))
        lr = math.exp((1 - t) * math.log(c.lr_position) + t * math.log(c.lr_position_final))
        for g in self.optimizer.param_groups:
            if g["name"] == "mu_loc":
                g["lr"] = lr

    def _frame(self, i: int) -> tuple[torch.Tensor, torch.Tensor, RenderCamera]:
        if i not in self._cache:
            fr = self.frames[i]
            img = torch.as_tensor(self.data.load_image(fr), device=self.device)
            if fr.mask is not None:
                mask = torch.as_tensor(self.data.load_mask(fr), device=self.device)
            else:
                mask = torch.ones(img.shape[:2], device=self.device)
            cam = RenderCamera.from_camera(fr.camera, self.device)
            self._cache[i] = (img, mask, cam)  # type: ignore[assignment]
        img, mask, cam = self._cache[i]  # type: ignore[misc]
        return img, mask, cam  # type: ignore[return-value]

    def inputs(self, timestep: int) -> dict[str, torch.Tensor]:
        """Cached FLAME kwargs of a timestep."""
        if timestep not in self._inputs:
            self._inputs[timestep] = self.avatar.frame_inputs(timestep)
            self._rigid[timestep] = self.avatar.rigid_transform(self._inputs[timestep])
        return self._inputs[timestep]

    def rigid(self, timestep: int) -> tuple[torch.Tensor, torch.Tensor] | None:
        """(R0, t) of a rigidly moved timestep, else None (cached)."""
        self.inputs(timestep)
        return self._rigid[timestep]

    def _randint(self, n: int, size: int) -> torch.Tensor:
        return torch.randint(n, (size,), generator=self.generator)

    # ------------------------------------------------------------------ one step
    def step(self) -> dict[str, float]:
        """One optimisation step; returns the loss terms as floats."""
        c, av = self.cfg, self.avatar
        i = int(self._randint(len(self.frames), 1)[0])
        fr = self.frames[i]
        img, mask, cam = self._frame(i)
        inputs = self.inputs(fr.timestep)
        self._set_lrs()
        step = self.step_count
        use_sdf = step >= c.sdf_from

        canon = av.canonical_state(with_sdf=True, create_graph=use_sdf)
        render, _ = av.render(cam, inputs, c.background, canonical=canon, near=c.near, far=c.far, return_statistics=False)
        terms: dict[str, torch.Tensor] = {}
        terms["rgb"] = L.rgb_loss(render.color, img, c.ssim_weight)
        total = terms["rgb"]
        if c.w_normal_consistency > 0 and step >= c.normal_consistency_from:
            terms["normal_consistency"] = L.normal_consistency_loss(render.normal_world, render.surf_normal_world)
            total = total + c.w_normal_consistency * terms["normal_consistency"]
        if c.w_distortion > 0 and step >= c.distortion_from:
            terms["distortion"] = L.distortion_loss(render.distortion)
            total = total + c.w_distortion * terms["distortion"]

        if use_sdf:
            assert canon.sdf is not None and canon.sdf_grad is not None
            keep = self._not_mouth
            terms["pt"] = L.point_sdf_loss(canon.sdf[keep], self.length_unit)
            terms["align"] = L.align_loss(canon.normals[keep], canon.sdf_grad[keep])
            total = total + c.w_pt * terms["pt"] + c.w_align * terms["align"]
            total = total + self._sdf_terms(terms, canon, render, img, mask, cam, inputs, fr.timestep)

        self.optimizer.zero_grad(set_to_none=True)
        total.backward()
        self.optimizer.step()
        self.step_count += 1
        if c.rebind_every > 0 and self.step_count % c.rebind_every == 0 and self.step_count < c.iterations:
            n = av.surfels.rebind(av.canonical_vertices, av.faces, frames=(av.R_c, av.T_c, av.k_c), optimizer=self.optimizer)
            terms["rebound"] = torch.tensor(float(n))
            self._not_mouth = av.surfels.region_id != REGION_MOUTH
        out = {k: float(v.detach()) for k, v in terms.items()}
        out["loss"] = float(total.detach())
        with torch.no_grad():
            out["psnr"] = float(psnr(render.color.detach().permute(2, 0, 1), img.permute(2, 0, 1)))
        return out

    def _sdf_terms(self, terms, canon, render, img, mask, cam, inputs, timestep) -> torch.Tensor:
        c, av = self.cfg, self.avatar
        total = img.new_zeros(())
        fg = torch.nonzero(mask.reshape(-1) > 0.5, as_tuple=False).reshape(-1)
        if fg.numel() > 0 and c.rays_per_step > 0:
            pix = fg[self._randint(fg.numel(), c.rays_per_step).to(fg.device)]
            o_c, d_c, ratio, rot, ok = self.rays.map(inputs, cam, pix, self.rigid(timestep))
            out = render_neus(
                av.sdf, av.appearance, o_c, d_c, av.variance, c.neus_samples, c.neus_importance, c.neus_up_steps,
                1.0, c.background, length_unit=self.length_unit, perturb=True, generator=self.generator, return_samples=True,
            )  # fmt: skip
            gt = img.reshape(-1, 3)[pix]
            terms["neus_rgb"] = L.neus_rgb_loss(out.color[ok], gt[ok])
            total = total + c.w_neus_rgb * terms["neus_rgb"]
            # surfel depth (camera z) -> distance along the world ray -> canonical distance
            with torch.no_grad():
                Rw = cam.w2c[:3, :3]
                _, d_w = ray_directions(cam.K, cam.w2c, cam.width, cam.height)
                dz = (d_w.reshape(-1, 3)[pix] @ Rw.T)[:, 2]
                a = render.alpha.reshape(-1)[pix]
                t_s = render.depth.reshape(-1)[pix] / dz.clamp_min(1e-6) * ratio
                n_s = (rot @ render.normal_world.reshape(-1, 3)[pix][..., None]).squeeze(-1)
            wsum = out.weights_sum
            valid = ok & (a > 0.5) & (wsum.detach() > 0.5)
            t_sdf = out.depth / wsum.clamp_min(1e-6)
            terms["depth"] = L.depth_loss(t_sdf, t_s, valid, self.length_unit)
            terms["normal"] = L.normal_loss(out.normal, n_s, valid)
            total = total + c.w_depth * terms["depth"] + c.w_normal * terms["normal"]
            eik = L.eikonal_loss(out.gradients, out.sample_mask)
        else:
            eik = img.new_zeros(())
        eik = eik + L.eikonal_loss(canon.sdf_grad)
        terms["eikonal"] = eik
        total = total + c.w_eikonal * eik
        if c.w_smooth > 0:
            n = canon.means.shape[0]
            m = min(n, c.smooth_points)
            sub = self._randint(n, m).to(canon.means.device)
            delta = (torch.rand((m, 3), generator=self.generator, dtype=canon.means.dtype) * 2 - 1).to(canon.means.device)
            x2 = canon.means[sub].detach() + delta * c.smooth_delta * self.length_unit
            _, g2, _ = av.sdf.gradient(x2, create_graph=True)
            terms["smooth"] = L.normal_smoothness_loss(canon.sdf_grad[sub], g2)
            total = total + c.w_smooth * terms["smooth"]
        return total

    # ------------------------------------------------------------------ evaluation
    @torch.no_grad()
    def render_frame(self, fr: IngestedFrame) -> tuple[torch.Tensor, torch.Tensor]:
        """Render one ingested frame: (render (H, W, 3), ground truth (H, W, 3))."""
        cam = RenderCamera.from_camera(fr.camera, self.device)
        img, _ = self.avatar.render(cam, self.inputs(fr.timestep), self.cfg.background, near=self.cfg.near, far=self.cfg.far, return_statistics=False)
        gt = torch.as_tensor(self.data.load_image(fr), device=self.device)
        return img.color.clamp(0, 1), gt

    @torch.no_grad()
    def evaluate(self, split: str = "val", max_frames: int | None = None, return_images: bool = False) -> dict[str, Any]:
        """Mean PSNR / SSIM of the renders of one role ("train", "val", "test")."""
        frames = self.data.role(split)
        if max_frames is not None:
            frames = frames[:max_frames]
        ps, ss, images = [], [], []
        for fr in frames:
            pred, gt = self.render_frame(fr)
            a, b = pred.permute(2, 0, 1), gt.permute(2, 0, 1)
            ps.append(float(psnr(a, b)))
            ss.append(float(ssim(a, b)))
            if return_images:
                images.append((fr, pred.cpu().numpy(), gt.cpu().numpy()))
        out: dict[str, Any] = {
            "psnr": float(np.mean(ps)) if ps else float("nan"),
            "ssim": float(np.mean(ss)) if ss else float("nan"),
            "n": len(ps),
        }
        if return_images:
            out["images"] = images
        return out

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict[str, Any]:
        """Everything needed to resume exactly: avatar (incl. bindings), optimizer, RNGs, step."""
        return {
            "format": STATE_FORMAT,
            "step": self.step_count,
            "avatar": {k: v.detach().clone() for k, v in self.avatar.state_dict().items() if not k.startswith("flame.")},
            "optimizer": self.optimizer.state_dict(),
            "generator": self.generator.get_state(),
            "rng": rng_state(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict` (same surfel count)."""
        self.avatar.load_state_dict(state["avatar"], strict=False)
        self.optimizer.load_state_dict(state["optimizer"])
        self.generator.set_state(state["generator"])
        set_rng_state(state["rng"])
        self.step_count = int(state["step"])
        self._not_mouth = self.avatar.surfels.region_id != REGION_MOUTH


def _mesh_bytes(vertices: np.ndarray, faces: np.ndarray) -> bytes:
    import trimesh

    return trimesh.Trimesh(vertices=np.asarray(vertices, np.float64), faces=np.asarray(faces, np.int64), process=False).export(file_type="ply")


def run_phase1(
    data: IngestedData,
    init_dir: str | Path,
    out_dir: str | Path,
    cfg: Phase1Config,
    *,
    device: str = "cpu",
    seed: int = 0,
    checkpoint_dir: str | Path | None = None,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """Run phase 1 and write ``avatar.pt``, ``renders/``, ``sdf_mesh.ply`` and ``metrics.json`` into
    ``out_dir``; resumes from the newest checkpoint in ``checkpoint_dir``. Returns the metrics."""
    import trimesh

    from ..data.imageio import write_image
    from ..geometry.marching import extract_mesh
    from ..geometry.mesh_metrics import mesh_chamfer, normal_error
    from ..workspace import atomic_write_bytes, atomic_write_json, latest_checkpoint, load_checkpoint, save_checkpoint

    out_dir = Path(out_dir)
    init_dir = Path(init_dir)
    torch.manual_seed(seed)
    gen = torch.Generator().manual_seed(seed)
    avatar = build_avatar(data, init_dir, cfg, device, gen)
    trainer = Phase1Trainer(avatar, data, cfg, device, gen)
    if checkpoint_dir is not None:
        ck = latest_checkpoint(checkpoint_dir)
        if ck is not None:
            trainer.load_state_dict(load_checkpoint(ck, map_location=device)["state"]["trainer"])
    total = cfg.iterations
    start_step = trainer.step_count
    t0 = time.perf_counter()
    last: dict[str, float] = {}
    val_psnr = float("nan")
    while trainer.step_count < total:
        last = trainer.step()
        step = trainer.step_count
        if cfg.eval_every > 0 and step % cfg.eval_every == 0 and step < total:
            val_psnr = trainer.evaluate("val", max_frames=4)["psnr"]
        if progress is not None:
            stats = {k: v for k, v in last.items() if k in ("loss", "rgb", "pt", "depth", "normal", "neus_rgb", "psnr")}
            progress(step, total, "phase 1", val_psnr=val_psnr, **stats)
        if checkpoint_dir is not None and cfg.checkpoint_every > 0 and step % cfg.checkpoint_every == 0 and step < total:
            save_checkpoint(checkpoint_dir, step, {"trainer": trainer.state_dict()})
    train_time = time.perf_counter() - t0
    steps_run = trainer.step_count - start_step

    if progress is not None:
        progress(total, total, "evaluating")
    val = trainer.evaluate("val", return_images=True)
    train = trainer.evaluate("train", max_frames=16)
    renders = out_dir / "renders"
    renders.mkdir(parents=True, exist_ok=True)
    for fr, pred, gt in val.pop("images"):
        err = np.repeat(np.clip(np.abs(pred - gt).mean(-1, keepdims=True) * 4.0, 0, 1), 3, axis=-1)
        write_image(renders / f"val_t{fr.timestep:05d}_c{fr.camera_index:02d}.png", np.concatenate([gt, pred, err], 1))
    avatar.save(out_dir / "avatar.pt")

    if progress is not None:
        progress(total, total, "marching cubes")
    mv, mf = extract_mesh(avatar.sdf.sdf, avatar.sdf.bbox_min, avatar.sdf.bbox_max, cfg.mc_resolution, device=device)
    atomic_write_bytes(out_dir / "sdf_mesh.ply", _mesh_bytes(mv, mf))
    head = trimesh.load(init_dir / "head_mesh.ply", process=False)
    hv, hf = np.asarray(head.vertices), np.asarray(head.faces)
    diag = float(np.linalg.norm(hv[np.unique(hf)].max(0) - hv[np.unique(hf)].min(0)))
    chamfer = mesh_chamfer(mv, mf, hv, hf, n_samples=20000, seed=seed)
    nerr = normal_error(mv, mf, hv, hf, n_samples=10000, seed=seed)
    with torch.no_grad():
        canon = avatar.canonical_state(with_sdf=True)
        assert canon.sdf is not None
        keep = avatar.surfels.region_id != REGION_MOUTH
        mean_abs_sdf = float(canon.sdf[keep].abs().mean())
    metrics = {
        "attributes": cfg.attributes,
        "n_surfels": len(avatar.surfels),
        "iterations": total,
        "val_psnr": val["psnr"],
        "val_ssim": val["ssim"],
        "val_images": val["n"],
        "train_psnr": train["psnr"],
        "train_ssim": train["ssim"],
        "chamfer_m": chamfer,
        "chamfer_rel": chamfer / diag if diag > 0 else float("nan"),
        "normal_error_deg": nerr,
        "head_diagonal_m": diag,
        "surfel_mean_abs_sdf_m": mean_abs_sdf,
        "iterations_per_s": steps_run / train_time if train_time > 0 and steps_run > 0 else float("nan"),
        "train_time_s": train_time,
        "final_losses": last,
    }
    atomic_write_json(out_dir / "metrics.json", metrics)
    return metrics
