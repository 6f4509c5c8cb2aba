"""Fit an SDF network to a (possibly open) triangle mesh before image-based training.

Samples come from a bank drawn once from the static mesh: a third on the surface (with face normals), a
third near it (surface + N(0, sigma^2), half with sigma = near_sigmas[0] * head size and half with
near_sigmas[1] * head size) and a third uniform in the SDF box. Targets are libigl fast-winding-number
signed distances (negative inside); near and uniform samples are weighted by the sign confidence of their
winding number so that points next to the mesh's holes (FLAME neck, eye sockets) barely count.

Loss per step: ``w_value * L1(clamp(f, -tau, tau), clamp(d, -tau, tau))`` (confidence-weighted)
``+ w_normal * mean(1 - cos(grad f, n))`` on surface samples ``+ w_eikonal * mean((|grad f| - 1)^2)``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import torch

from ..geometry.marching import extract_mesh
from ..geometry.mesh_metrics import mesh_chamfer
from ..geometry.mesh_sdf import sample_surface, sign_confidence, signed_distance, vertex_normals, winding_number
from .sdf import SDFNetwork


@dataclass
class PretrainConfig:
    """Settings of SDF pretraining on a mesh.

    steps: optimisation steps (tiny preset ~300-1000, default ~3000).
    batch_size: samples per step, split evenly over surface / near / uniform.
    bank_size: samples precomputed per kind (surface, near, uniform).
    lr_grid: Adam learning rate of the hash table.
    lr_mlp: Adam learning rate of the MLP.
    near_sigmas: near-surface noise std as fractions of the head size (largest mesh bbox side).
    truncation: |d| truncation as a fraction of the head size (None: no truncation).
    w_value: weight of the L1 distance term.
    w_normal: weight of the 1 - cos normal term on surface samples.
    w_eikonal: weight of the eikonal term.
    confidence_band: winding-number band around 0.5 over which the sign weight rises from 0 to 1.
    eval_resolution: marching-cubes resolution used by ``evaluate``.
    eval_samples: surface samples per mesh for the Chamfer distance in ``evaluate``.
    """

    steps: int = 3000
    batch_size: int = 8192
    bank_size: int = 200000
    lr_grid: float = 1e-2
    lr_mlp: float = 1e-3
    near_sigmas: tuple[float, float] = (0.005, 0.02)
    truncation: float | None = 0.1
    w_value: float = 1.0
    w_normal: float = 1.0
    w_eikonal: float = 0.1
    confidence_band: float = 0.25
    eval_resolution: int = 128
    eval_samples: int = 20000


class SDFPretrainer:
    """Stateful pretraining loop: ``step()`` repeatedly, checkpoint with ``state_dict()``.

    Args:
        sdf_net: the network to fit (modified in place).
        vertices: (V, 3) mesh vertices in the SDF's world space; faces: (F, 3).
        config: PretrainConfig.
        generator: torch CPU generator; it seeds the sample bank and the batch draws, so two pretrainers
            built with equally seeded generators run identically, and ``load_state_dict`` resumes exactly.
    """

    def __init__(
        self,
        sdf_net: SDFNetwork,
        vertices: np.ndarray | torch.Tensor,
        faces: np.ndarray | torch.Tensor,
        config: PretrainConfig | None = None,
        generator: torch.Generator | None = None,
    ) -> None:
        self.net = sdf_net
        self.config = config or PretrainConfig()
        self.generator = generator if generator is not None else torch.Generator().manual_seed(0)
        v = vertices.detach().cpu().numpy() if isinstance(vertices, torch.Tensor) else np.asarray(vertices)
        f = faces.detach().cpu().numpy() if isinstance(faces, torch.Tensor) else np.asarray(faces)
        self.vertices = np.asarray(v, dtype=np.float64)
        self.faces = np.asarray(f, dtype=np.int64)
        self.head_size = float((self.vertices.max(0) - self.vertices.min(0)).max())
        self.step_count = 0
        param = next(sdf_net.parameters())
        self.device, self.dtype = param.device, param.dtype
        self._build_bank()
        self.optimizer = torch.optim.Adam(
            [
                {"params": sdf_net.grid_parameters(), "lr": self.config.lr_grid},
                {"params": sdf_net.mlp_parameters(), "lr": self.config.lr_mlp},
            ],
            betas=(0.9, 0.99),
            eps=1e-15,
        )

    def _build_bank(self) -> None:
        cfg = self.config
        seed = int(torch.randint(0, 2**31 - 1, (1,), generator=self.generator).item())
        rng = np.random.default_rng(seed)
        n = int(cfg.bank_size)
        surf, normals = sample_surface(self.vertices, self.faces, n, rng)
        base, _ = sample_surface(self.vertices, self.faces, n, rng)
        sigma = np.where(np.arange(n) % 2 == 0, cfg.near_sigmas[0], cfg.near_sigmas[1]) * self.head_size
        near = base + rng.normal(size=(n, 3)) * sigma[:, None]
        lo = self.net.bbox_min.detach().cpu().numpy().astype(np.float64)
        hi = self.net.bbox_max.detach().cpu().numpy().astype(np.float64)
        near = np.clip(near, lo, hi)
        uniform = lo + rng.random((n, 3)) * (hi - lo)
        off = np.concatenate([near, uniform], 0)
        d, _, _ = signed_distance(off, self.vertices, self.faces)
        conf = sign_confidence(winding_number(off, self.vertices, self.faces), cfg.confidence_band)

        def t(a: np.ndarray) -> torch.Tensor:
            return torch.as_tensor(a, dtype=self.dtype, device=self.device)

        self.bank_surface = t(surf)
        self.bank_normals = t(normals)
        self.bank_off = t(off)
        self.bank_off_sdf = t(d)
        self.bank_off_conf = t(conf)

    def _draw(self, high: int, count: int) -> torch.Tensor:
        return torch.randint(0, high, (count,), generator=self.generator).to(self.device)

    def step(self) -> dict[str, float]:
        """One Adam step on a fresh batch; returns the loss terms as floats."""
        cfg = self.config
        n_each = max(1, cfg.batch_size // 3)
        n_bank = self.bank_surface.shape[0]
        i_s = self._draw(n_bank, n_each)
        i_o = self._draw(2 * n_bank, 2 * n_each)
        xs = self.bank_surface[i_s]
        ns = self.bank_normals[i_s]
        xo = self.bank_off[i_o]
        do = self.bank_off_sdf[i_o]
        co = self.bank_off_conf[i_o]
        x = torch.cat([xs, xo], 0)
        target = torch.cat([torch.zeros_like(xs[:, 0]), do], 0)
        conf = torch.cat([torch.ones_like(xs[:, 0]), co], 0)

        self.net.train()
        sdf, grad, _ = self.net.gradient(x, create_graph=True)
        if cfg.truncation is not None:
            tau = cfg.truncation * self.head_size
            pred, tgt = sdf.clamp(-tau, tau), target.clamp(-tau, tau)
        else:
            pred, tgt = sdf, target
        loss_value = (conf * (pred - tgt).abs()).sum() / conf.sum().clamp_min(1e-8)
        gs = grad[:n_each]
        cos = (gs * ns).sum(-1) / gs.norm(dim=-1).clamp_min(1e-12)
        loss_normal = (1.0 - cos).mean()
        loss_eik = ((grad.norm(dim=-1) - 1.0) ** 2).mean()
        loss = cfg.w_value * loss_value + cfg.w_normal * loss_normal + cfg.w_eikonal * loss_eik
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()
        self.step_count += 1
        return {
            "loss": float(loss.detach()),
            "value": float(loss_value.detach()),
            "normal": float(loss_normal.detach()),
            "eikonal": float(loss_eik.detach()),
        }

    def run(self, progress: Callable[[int, int, dict[str, float]], None] | None = None) -> dict[str, float]:
        """Step until ``config.steps``; ``progress(step, total, losses)`` after each step. Returns last losses."""
        losses: dict[str, float] = {}
        while self.step_count < self.config.steps:
            losses = self.step()
            if progress is not None:
                progress(self.step_count, self.config.steps, losses)
        return losses

    def state_dict(self) -> dict[str, Any]:
        """Network, optimizer, step and RNG state (plus the config as plain data)."""
        return {
            "version": 1,
            "network": self.net.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "step": self.step_count,
            "rng": self.generator.get_state(),
            "config": asdict(self.config),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a ``state_dict()``.

        The sample bank is not stored: it is rebuilt from the generator at construction, so resume with an
        equally seeded generator and the same mesh. Raises ValueError if the bank settings differ.
        """
        saved = state.get("config", {})
        for key in ("bank_size", "near_sigmas", "confidence_band"):
            if key in saved and tuple(np.atleast_1d(saved[key])) != tuple(np.atleast_1d(getattr(self.config, key))):
                raise ValueError(f"checkpoint was made with {key}={saved[key]!r}, not {getattr(self.config, key)!r}")
        self.net.load_state_dict(state["network"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.step_count = int(state["step"])
        self.generator.set_state(state["rng"])

    @torch.no_grad()
    def evaluate(self, resolution: int | None = None) -> dict[str, float]:
        """Fit quality against the mesh.

        Returns mean_abs_sdf_vertices (world units), mean_abs_sdf_rel (relative to the mesh bbox diagonal),
        normal_cos (mean cos between grad f and vertex normals), chamfer (world units, marching-cubes mesh vs
        input mesh; inf if no surface) and mc_faces.
        """
        self.net.eval()
        v = torch.as_tensor(self.vertices, dtype=self.dtype, device=self.device)
        sdf, grad, _ = self.net.gradient(v)
        vn = torch.as_tensor(vertex_normals(self.vertices, self.faces), dtype=self.dtype, device=self.device)
        cos = (grad * vn).sum(-1) / grad.norm(dim=-1).clamp_min(1e-12)
        diag = float(np.linalg.norm(self.vertices.max(0) - self.vertices.min(0)))
        mean_abs = float(sdf.abs().mean())
        res = int(resolution or self.config.eval_resolution)
        mv, mf = extract_mesh(self.net.sdf, self.net.bbox_min, self.net.bbox_max, res, device=self.device)
        chamfer = mesh_chamfer(mv, mf, self.vertices, self.faces, self.config.eval_samples)
        return {
            "mean_abs_sdf_vertices": mean_abs,
            "mean_abs_sdf_rel": mean_abs / diag,
            "normal_cos": float(cos.mean()),
            "chamfer": chamfer,
            "mc_faces": float(len(mf)),
        }
