"""Random FLAME expressions and poses for the self-supervised phase (SAGE phase 2).

Each sample is either *synthetic* (a few expression components drawn from per-component normal
distributions, a uniform jaw opening and gaze) or, with probability ``observed_weight``, one of the
capture's own tracked expressions perturbed by a small noise. Neck, global rotation and translation
get a small jitter in both cases. All randomness comes from one CPU ``torch.Generator``, so a seed
gives the same samples on every device.
"""

from __future__ import annotations

import numpy as np
import torch


def component_ranges_from_dirs(
    exprdirs: torch.Tensor | np.ndarray,
    target: float = 0.01,
    vertex_mask: torch.Tensor | np.ndarray | None = None,
    eps: float = 1e-12,
) -> torch.Tensor:
    """Per-component standard deviations that give every component the same visible effect.

    exprdirs: (V, 3, E) expression blendshapes (FLAME ``shapedirs[..., 300:]``, metres per unit
    coefficient). For component e, m_e = max_v ‖exprdirs[v, :, e]‖ is the largest vertex
    displacement per unit coefficient; the returned std_e = target / m_e makes a 1σ coefficient move
    the most-affected vertex by ``target`` (default 1 cm). vertex_mask: (V,) bool restricting the
    maximum to some vertices (e.g. the face). Components that move no vertex (m_e ≤ eps) get 0.
    Returns (E,) float32 on CPU.
    """
    d = torch.as_tensor(np.asarray(exprdirs) if not isinstance(exprdirs, torch.Tensor) else exprdirs).detach()
    d = d.to(device="cpu", dtype=torch.float64)
    if d.dim() != 3 or d.shape[1] != 3:
        raise ValueError(f"exprdirs must be (V, 3, E), got {tuple(d.shape)}")
    if vertex_mask is not None:
        m = torch.as_tensor(np.asarray(vertex_mask) if not isinstance(vertex_mask, torch.Tensor) else vertex_mask)
        d = d[m.to(device="cpu", dtype=torch.bool)]
    peak = d.norm(dim=1).amax(dim=0) if d.shape[0] > 0 else torch.zeros(d.shape[2], dtype=torch.float64)
    std = torch.where(peak > eps, target / peak.clamp_min(eps), torch.zeros_like(peak))
    return std.to(torch.float32)


def _fit_columns(x: torch.Tensor, n: int) -> torch.Tensor:
    """Zero-pad or truncate the last dimension to n."""
    if x.shape[-1] >= n:
        return x[..., :n]
    return torch.nn.functional.pad(x, (0, n - x.shape[-1]))


class ExpressionSampler:
    """Sampler of FLAME expression and pose parameters.

    Args:
        n_expr: E, the number of expression coefficients produced.
        expr_std: (E,) per-component standard deviation or a scalar (e.g. from
            :func:`component_ranges_from_dirs`).
        clip_sigma: synthetic coefficients and jitters are clamped to ±clip_sigma·std.
        n_active: a synthetic sample activates between 1 and n_active components chosen uniformly
            (None: all components).
        jaw_range: (min, max) jaw opening in radians, a rotation about x (positive opens the mouth).
        eye_range: maximum gaze angle (rad); both eyes share one pitch (x) and yaw (y), uniform in
            ±eye_range.
        neck_std, rotation_std: jitter std (rad) of each axis-angle component of the neck pose and
            the global rotation.
        translation_std: jitter std (m) of each translation component.
        observed_expr: (T, E') the capture's tracked expressions (padded or truncated to E), or None.
        observed_jaw: (T, 3) tracked jaw poses matching ``observed_expr``, or None (then observed
            samples draw the jaw like synthetic ones).
        observed_weight: probability of starting from an observed expression (0 without any).
        observed_noise: observed samples add N(0, (observed_noise·expr_std)²) to each coefficient
            and N(0, (observed_noise·jaw span)²) to the jaw angle (clamped to ``jaw_range``).
        seed: seed of the sampler's own generator (used when ``sample`` gets none).
        device, dtype: of the returned tensors.
    """

    def __init__(
        self,
        n_expr: int,
        expr_std: float | torch.Tensor | np.ndarray = 1.0,
        *,
        clip_sigma: float = 2.5,
        n_active: int | None = 8,
        jaw_range: tuple[float, float] = (0.0, 0.4),
        eye_range: float = 0.2,
        neck_std: float = 0.05,
        rotation_std: float = 0.05,
        translation_std: float = 0.005,
        observed_expr: torch.Tensor | np.ndarray | None = None,
        observed_jaw: torch.Tensor | np.ndarray | None = None,
        observed_weight: float = 0.3,
        observed_noise: float = 0.2,
        seed: int = 0,
        device: torch.device | str = "cpu",
        dtype: torch.dtype = torch.float32,
    ) -> None:
        if n_expr < 0:
            raise ValueError("n_expr must be non-negative")
        std = torch.as_tensor(np.asarray(expr_std, dtype=np.float64) if not isinstance(expr_std, torch.Tensor) else expr_std)
        std = std.detach().to(device="cpu", dtype=torch.float64)
        if std.dim() == 0:
            std = std.expand(n_expr).clone()
        if std.shape != (n_expr,):
            raise ValueError(f"expr_std must be a scalar or ({n_expr},), got {tuple(std.shape)}")
        if torch.any(std < 0):
            raise ValueError("expr_std must be non-negative")
        if jaw_range[0] > jaw_range[1]:
            raise ValueError(f"jaw_range must be (min, max), got {jaw_range}")
        if not 0.0 <= observed_weight <= 1.0:
            raise ValueError("observed_weight must be in [0, 1]")
        if n_active is not None and n_active < 1:
            raise ValueError("n_active must be at least 1 (or None)")
        self.n_expr = int(n_expr)
        self.expr_std = std
        self.clip_sigma = float(clip_sigma)
        self.n_active = None if n_active is None else min(int(n_active), max(self.n_expr, 1))
        self.jaw_range = (float(jaw_range[0]), float(jaw_range[1]))
        self.eye_range = float(eye_range)
        self.neck_std = float(neck_std)
        self.rotation_std = float(rotation_std)
        self.translation_std = float(translation_std)
        self.observed_expr: torch.Tensor | None = None
        self.observed_jaw: torch.Tensor | None = None
        if observed_expr is not None:
            obs = torch.as_tensor(np.asarray(observed_expr) if not isinstance(observed_expr, torch.Tensor) else observed_expr)
            obs = obs.detach().to(device="cpu", dtype=torch.float64)
            if obs.dim() != 2 or obs.shape[0] == 0:
                raise ValueError(f"observed_expr must be (T, E) with T ≥ 1, got {tuple(obs.shape)}")
            self.observed_expr = _fit_columns(obs, self.n_expr)
            if observed_jaw is not None:
                jaw = torch.as_tensor(np.asarray(observed_jaw) if not isinstance(observed_jaw, torch.Tensor) else observed_jaw)
                jaw = jaw.detach().to(device="cpu", dtype=torch.float64).reshape(-1, 3)
                if jaw.shape[0] != obs.shape[0]:
                    raise ValueError(f"observed_jaw has {jaw.shape[0]} rows, observed_expr {obs.shape[0]}")
                self.observed_jaw = jaw
        self.observed_weight = float(observed_weight) if self.observed_expr is not None else 0.0
        self.observed_noise = float(observed_noise)
        self.generator = torch.Generator().manual_seed(int(seed))
        self.device = torch.device(device)
        self.dtype = dtype

    def _jitter(self, n: int, width: int, std: float, g: torch.Generator) -> torch.Tensor:
        x = torch.randn(n, width, generator=g, dtype=torch.float64) * std
        lim = self.clip_sigma * std
        return x.clamp(-lim, lim)

    def sample(self, n: int, generator: torch.Generator | None = None) -> dict[str, torch.Tensor]:
        """n samples as keyword arguments of ``FlameModel.forward``.

        Returns expr (n, E), jaw_pose (n, 3), eyes_pose (n, 6), neck_pose (n, 3), rotation (n, 3),
        translation (n, 3) on the sampler's device and dtype. ``generator`` (a CPU generator)
        overrides the sampler's own; the draws depend only on it and n.
        """
        g = generator if generator is not None else self.generator
        E = self.n_expr
        f64 = torch.float64
        lo, hi = self.jaw_range

        # synthetic expressions: a random subset of components, clipped normal coefficients
        coeff = torch.randn(n, E, generator=g, dtype=f64)
        lim = self.clip_sigma
        expr = coeff.clamp(-lim, lim) * self.expr_std
        if self.n_active is not None and E > 0:
            keys = torch.rand(n, E, generator=g, dtype=f64)
            rank = keys.argsort(dim=1).argsort(dim=1)
            k = torch.randint(1, self.n_active + 1, (n, 1), generator=g)
            expr = expr * (rank < k)
        jaw = lo + (hi - lo) * torch.rand(n, generator=g, dtype=f64)

        # observed expressions, perturbed
        use_obs = torch.rand(n, generator=g, dtype=f64) < self.observed_weight
        if self.observed_expr is not None:
            pick = torch.randint(0, self.observed_expr.shape[0], (n,), generator=g)
            noise = torch.randn(n, E, generator=g, dtype=f64) * (self.observed_noise * self.expr_std)
            obs = self.observed_expr[pick] + noise
            expr = torch.where(use_obs[:, None], obs, expr)
            if self.observed_jaw is not None:
                jaw_noise = torch.randn(n, generator=g, dtype=f64) * (self.observed_noise * (hi - lo))
                obs_jaw = (self.observed_jaw[pick, 0] + jaw_noise).clamp(lo, hi)
                jaw = torch.where(use_obs, obs_jaw, jaw)

        jaw_pose = torch.zeros(n, 3, dtype=f64)
        jaw_pose[:, 0] = jaw
        gaze = (2 * torch.rand(n, 2, generator=g, dtype=f64) - 1) * self.eye_range
        eyes_pose = torch.zeros(n, 6, dtype=f64)
        eyes_pose[:, 0:2] = gaze
        eyes_pose[:, 3:5] = gaze
        out = {
            "expr": expr,
            "jaw_pose": jaw_pose,
            "eyes_pose": eyes_pose,
            "neck_pose": self._jitter(n, 3, self.neck_std, g),
            "rotation": self._jitter(n, 3, self.rotation_std, g),
            "translation": self._jitter(n, 3, self.translation_std, g),
        }
        return {key: v.to(device=self.device, dtype=self.dtype) for key, v in out.items()}
