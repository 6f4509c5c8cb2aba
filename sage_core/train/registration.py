"""Registration of a single training timestep's tracked pose to the surface phase 1 reconstructed.

An avatar trained on one timestep learns its canonical content relative to that timestep's tracked
FLAME mesh. When the tracker placed that mesh a little off the head (a frame's rigid jitter: on the
benchmark's tracked captures up to 1.5 mm and 0.6°), the content keeps the offset in canonical
space, and every other frame, posed with its own (differently off) tracked parameters, carries it:
a perfect copy of the training timestep moved with the tracked mesh scored 23.49 dB on a subject
whose tracking alone allows 24.63 (docs/results.md). The multiview images fix where the head
really is, and phase 1's SDF has reconstructed that surface; so at the end of phase 1 the tracked
mesh is registered to it.

Estimate (:func:`estimate_translation`): the translation τ that moves the canonical mesh's vertices
of the skin regions a tracker fits (face, neck and ears by default; not the scalp, which the hair
covers) onto the SDF's zero level set, together with one uniform offset d along the normals that the
translation does not explain, by point-to-plane Gauss-Newton steps: each step linearises
f(x + τ) − d ≈ f(x) + ∇f·δτ − d − δd and solves the robust (Cauchy-weighted) normal equations. The
offset takes up a reconstruction that is uniformly fuller or slimmer than the mesh, which over
forward-facing points would otherwise read as a translation: on the benchmark's two tiny subjects
it took the training mesh's error from 1.77 to 1.02 mm and from 0.78 to 0.56 mm, where the
translation alone gave 0.98 and 0.84 mm (docs/results.md). Only a translation is estimated: a
rotation from the same points was not reliable (it reduced one subject's vertex error 1.77 → 0.59 mm
and raised the other's 0.78 → 1.43 mm).

Apply (:func:`register_training_pose`): the content is moved by −τ relative to the mesh
(:func:`sage_core.avatar.canonical_shift.shift_canonical`, exact) and the timestep's FLAME
translation by R0·τ, so the training views render exactly as before while the mesh now lies on the
reconstructed head; every other pose then moves content that sits where the truth's does relative
to the mesh. The registered translation is baked into the avatar's parameters (its renders of the
training timestep and ``sage eval``'s views of it use them).

A translation under half a pixel of the training views at the head (``registration.min_pixels``) is
not applied: the reconstruction does not place the surface that well, and on the benchmark subject
whose training mesh was 0.8 mm (0.35 px) off, applying the fitted 0.56 mm lowered held-out PSNR by
0.13 dB although it brought the training mesh closer to the truth (0.78 → 0.56 mm): with a few held-out
frames, part of that small offset had happened to cancel theirs.

Rounds (:class:`RegistrationRounds`, ``registration.rounds``): the fit can also run while the SDF
still trains, so that the rest of phase 1 works on the re-anchored mesh; the last round runs after
the final step, as a single fit does.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

if TYPE_CHECKING:
    from ..avatar.model import Avatar
    from ..config import RegistrationConfig
    from ..data.cameras import Camera
    from ..flame.regions import Regions

SdfWithGradient = Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]]
"""``x (N, 3) -> (f (N,), ∇f (N, 3))``: signed distances and their gradients."""


@dataclass(frozen=True)
class TranslationFit:
    """The result of :func:`estimate_translation`.

    translation: (3,) float64, the τ that moves the points onto the surface; offset: the uniform
    distance along the normals left between them (the reconstruction's inflation against the
    mesh, not a motion); residual_before, residual_after: mean |f| of the points before and mean
    |f − offset| after; iterations: Gauss-Newton steps taken.
    """

    translation: torch.Tensor
    offset: float
    residual_before: float
    residual_after: float
    iterations: int


def estimate_translation(sdf: SdfWithGradient, points: torch.Tensor, scale: float, iterations: int = 50, tol: float = 1e-9) -> TranslationFit:
    """Robust point-to-plane fit of one translation τ and one uniform normal offset d with
    f(points + τ) ≈ d.

    The offset takes up a surface that is uniformly larger or smaller than the mesh (a head a little
    fuller than its FLAME fit, a reconstruction biased outwards): over points whose normals face
    mostly one way, such as a face, it would otherwise be read as a translation towards them.
    sdf: the signed distance and its gradient; points: (N, 3); scale: the robust scale (Cauchy
    weights 1 / (1 + (r/scale)²) of each residual r: a point much further than ``scale`` from the
    surface hardly counts); iterations: at most this many Gauss-Newton steps, stopping when a step is
    shorter than ``tol``. Raises ValueError when there are fewer than 4 points or their normals and
    the offset leave the fit undetermined.
    """
    x0 = points.detach().to(torch.float64)
    if x0.ndim != 2 or x0.shape[1] != 3 or x0.shape[0] < 4:
        raise ValueError(f"need at least 4 points of shape (N, 3), got {tuple(x0.shape)}")
    tau = torch.zeros(3, dtype=torch.float64, device=x0.device)
    d = 0.0
    first = float("nan")
    steps = 0
    for steps in range(1, iterations + 1):
        f, g = sdf(x0 + tau)
        f, g = f.detach().to(torch.float64), g.detach().to(torch.float64)
        if steps == 1:
            first = float(f.abs().mean())
        r = f - d
        n = g / g.norm(dim=1, keepdim=True).clamp_min(1e-12)
        w = 1.0 / (1.0 + (r / scale) ** 2)
        jac = torch.cat([n, -torch.ones_like(r)[:, None]], 1)  # d r / d(τ, d)
        a = (jac * w[:, None]).T @ jac
        if float(torch.linalg.eigvalsh(a)[0]) <= 1e-6 * float(w.sum()):
            raise ValueError("the points' normals do not fix a translation apart from a uniform offset: the translation is undetermined")
        step = torch.linalg.solve(a, -(jac * w[:, None]).T @ r)
        tau = tau + step[:3]
        d += float(step[3])
        if float(step.norm()) < tol:
            break
    f, _ = sdf(x0 + tau)
    last = float((f.detach().to(torch.float64) - d).abs().mean())
    return TranslationFit(tau, d, first, last, steps)


def registration_applies(mode: str, regime: str, train_timesteps: int, sdf_trained: bool, pose_refine: bool) -> tuple[bool, str]:
    """Whether phase 1 registers the training timestep, and why (or why not).

    mode: ``RegistrationConfig.mode``; regime: the ingested regime; train_timesteps: distinct
    training timesteps; sdf_trained: the SDF terms ran (``schedule.sdf_from`` < iterations);
    pose_refine: phase 1 refines training poses itself. ``on`` with several training timesteps or
    with pose refinement is a ValueError (one canonical cannot be re-anchored to several frames).
    """
    if mode == "off":
        return False, "off"
    if mode == "on":
        if train_timesteps != 1:
            raise ValueError(f"registration.mode=on needs one training timestep, this capture trains on {train_timesteps}")
        if pose_refine:
            raise ValueError("registration.mode=on and pose_refine both move the training poses: choose one")
        if not sdf_trained:
            raise ValueError("registration.mode=on needs the SDF terms (schedule.sdf_from below the iterations)")
        return True, "on"
    if regime != "mv-sf":
        return False, f"auto: regime {regime} (registration runs for one multiview timestep, mv-sf)"
    if train_timesteps != 1 or pose_refine or not sdf_trained:
        why = "several training timesteps" if train_timesteps != 1 else ("pose refinement on" if pose_refine else "SDF terms off")
        return False, f"auto: {why}"
    return True, "auto"


def region_points(avatar: Avatar, regions: Regions | None, names: list[str]) -> tuple[torch.Tensor, list[str]]:
    """Canonical FLAME vertices (M, 3) of the named vertex regions that the model has, and those
    names; (0, 3) when it has none of them."""
    verts = avatar.canonical_vertices.detach()
    have = [n for n in names if regions is not None and regions.has(n)]
    if not have:
        return verts[:0], []
    assert regions is not None
    ids = np.unique(np.concatenate([regions.vertex_ids(n) for n in have])).astype(np.int64)
    return verts[torch.as_tensor(ids, device=verts.device)], have


def pixel_footprint(cameras: list[Camera], center: np.ndarray) -> float:
    """The median over ``cameras`` of the size of one pixel at ``center`` (3,): distance from the
    camera centre over its focal length (scene units per pixel)."""
    sizes = [float(np.linalg.norm(np.asarray(c.center) - center)) / float(0.5 * (c.K[0, 0] + c.K[1, 1])) for c in cameras]
    return float(np.median(sizes))


def register_training_pose(
    avatar: Avatar, regions: Regions | None, cfg: RegistrationConfig, pixel: float | None = None, refining: bool = False
) -> dict[str, Any]:
    """Estimate the canonical timestep's translation against the avatar's SDF and apply it (see the
    module doc). pixel: the training views' pixel size at the head (:func:`pixel_footprint`); with
    it, a translation under ``cfg.min_pixels`` of them is reported and not applied, unless
    ``refining`` (an earlier round of the same run was applied: this fit refines it). Returns
    metrics: ``registration`` ("applied" or why not), the translation in mm (canonical and world),
    the uniform normal offset, the mean |SDF| of the points before and after (mm), the regions used."""
    from ..avatar.canonical_shift import shift_canonical

    names = list(cfg.regions)
    pts, used = region_points(avatar, regions, names)
    out: dict[str, Any] = {"registration_regions": used}
    if len(pts) < 4:
        out["registration"] = f"skipped: the model has none of the regions {', '.join(names)}"
        return out
    half = float(avatar.sdf.half_extent)

    def sdf(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        with torch.enable_grad():
            xf = x.to(torch.float32).detach().requires_grad_(True)
            f = avatar.sdf.sdf(xf)
            (g,) = torch.autograd.grad(f.sum(), xf)
        return f.detach(), g.detach()

    try:
        fit = estimate_translation(sdf, pts, cfg.robust_scale * half, cfg.iterations)
    except ValueError as e:
        out["registration"] = f"skipped: {e}"
        return out
    tau = fit.translation
    out.update({
        "registration_translation_mm": [float(v) * 1000.0 for v in tau],
        "registration_translation_norm_mm": float(tau.norm()) * 1000.0,
        "registration_normal_offset_mm": fit.offset * 1000.0,
        "registration_residual_before_mm": fit.residual_before * 1000.0,
        "registration_residual_after_mm": fit.residual_after * 1000.0,
        "registration_points": len(pts),
    })  # fmt: skip
    if pixel is not None:
        out["registration_pixel_mm"] = pixel * 1000.0
        if not refining and float(tau.norm()) < cfg.min_pixels * pixel:
            out["registration"] = (f"skipped: the fit moved the mesh {float(tau.norm()) * 1000:.2f} mm, under registration.min_pixels "
                                   f"({cfg.min_pixels:g} px = {cfg.min_pixels * pixel * 1000:.2f} mm)")
            return out
    if float(tau.norm()) > cfg.max_translation * half:
        out["registration"] = f"skipped: the fit moved the mesh {float(tau.norm()) * 1000:.1f} mm, over registration.max_translation"
        return out
    t0 = avatar.canonical_timestep
    rig = avatar.rigid_transform(avatar.frame_inputs(t0))
    if rig is None:
        out["registration"] = f"skipped: timestep {t0} is not a rigid motion of canonical space"
        return out
    world = (rig[0].detach().to(torch.float64).cpu() @ tau.cpu()).numpy()
    shift_canonical(avatar, -tau)
    params = avatar.params
    moved = params.translation.copy()
    moved[params.row_of(t0)] += world.astype(moved.dtype)
    avatar.params = dataclasses.replace(params, translation=moved)
    out["registration"] = "applied"
    out["registration_world_translation_mm"] = [float(v) * 1000.0 for v in world]
    return out


def head_pixel(avatar: Avatar, cameras: list[Camera]) -> float | None:
    """The size of one pixel of ``cameras`` at the canonical timestep's posed head centre
    (:func:`pixel_footprint`), None without cameras."""
    from ..geometry.rigid import canonical_to_world

    if not cameras:
        return None
    center = avatar.canonical_vertices.detach().mean(0)
    rig = avatar.rigid_transform(avatar.frame_inputs(avatar.canonical_timestep))
    if rig is not None:
        center = canonical_to_world(center, rig[0], rig[1], avatar.root_joint)
    return pixel_footprint(cameras, center.detach().cpu().double().numpy())


def round_steps(rounds: int, sdf_from: int, sdf_until: int) -> list[int]:
    """The steps after which the first ``rounds`` − 1 fits run: evenly spaced over the SDF-trained
    span [``sdf_from``, ``sdf_until``) (the last round runs after the final step). Steps outside
    [1, ``sdf_until``) are dropped."""
    span = sdf_until - sdf_from
    steps = {sdf_from + round(span * i / rounds) for i in range(1, rounds)}
    return sorted(s for s in steps if 1 <= s < sdf_until)


class RegistrationRounds:
    """The registration of one phase-1 run: fits after the steps :func:`round_steps` gives, while
    the SDF still trains, and one after the last step (``cfg.rounds`` in all).

    Why rounds: a fit made while training goes on lets the rest of phase 1 work on the re-anchored
    mesh: the surfels are rebound and relocated against triangles that lie on the reconstructed
    head, and the priors that hold the content near the mesh no longer pull it towards the tracked
    pose; the next round fits what is left. A round applies when its own translation reaches
    ``cfg.min_pixels``; once one has, the later rounds refine it whatever their size.

    The applied translation (canonical and world) and each round's metrics are trainer state
    (:meth:`state_dict`): a run resumed after a round has the avatar's content from the checkpoint
    and its FLAME translation from here.
    avatar: the avatar about to be trained (its parameters give the timestep's tracked
    translation); regions: the model's vertex regions; cameras: the canonical timestep's training
    cameras; cfg: the section; steps: the in-training rounds' steps, ascending (:func:`round_steps`).
    """

    def __init__(self, avatar: Avatar, regions: Regions | None, cameras: list[Camera], cfg: RegistrationConfig, steps: list[int]) -> None:
        self.regions = regions
        self.cameras = cameras
        self.cfg = cfg
        self.steps = steps
        self.row = avatar.params.row_of(avatar.canonical_timestep)
        self.base = np.asarray(avatar.params.translation[self.row], np.float64).copy()
        self.applied = np.zeros(3)
        """Canonical translation applied so far (scene units)."""
        self.world = np.zeros(3)
        """World translation added to the timestep's FLAME translation so far."""
        self.rounds: list[dict[str, Any]] = []

    def due(self, step: int) -> bool:
        """Whether an in-training round runs after ``step``."""
        return step in self.steps

    @property
    def any_applied(self) -> bool:
        """Whether a round so far was applied."""
        return any(r["registration"] == "applied" for r in self.rounds)

    def fit(self, avatar: Avatar, step: int) -> dict[str, Any]:
        """One round: fit, apply when the rules allow (:func:`register_training_pose`), record it.
        The caller drops its cached poses afterwards."""
        out = register_training_pose(avatar, self.regions, self.cfg, head_pixel(avatar, self.cameras), refining=self.any_applied)
        out["registration_step"] = int(step)
        if out["registration"] == "applied":
            self.applied += np.asarray(out["registration_translation_mm"]) / 1000.0
            self.world += np.asarray(out["registration_world_translation_mm"]) / 1000.0
            self._set_translation(avatar)  # the same float rounding as a resumed run's
        self.rounds.append(out)
        return out

    def _set_translation(self, avatar: Avatar) -> None:
        params = avatar.params
        moved = params.translation.copy()
        moved[self.row] = (self.base + self.world).astype(moved.dtype)
        avatar.params = dataclasses.replace(params, translation=moved)

    def summary(self) -> dict[str, Any]:
        """Phase-1 metrics: the last round's (``registration*``), the applied total
        (``registration_applied_mm``, canonical norm) and, with several rounds, every round's
        metrics (``registration_rounds``). Needs at least one round."""
        out = dict(self.rounds[-1])
        out.pop("registration_step", None)
        if self.any_applied:
            out["registration"] = "applied"
        out["registration_applied_mm"] = float(np.linalg.norm(self.applied)) * 1000.0
        out["registration_applied_world_mm"] = [float(v) * 1000.0 for v in self.world]
        if len(self.rounds) > 1:
            out["registration_rounds"] = [dict(r) for r in self.rounds]
        return out

    def state_dict(self) -> dict[str, Any]:
        """The applied translations and the rounds so far (plain data)."""
        return {"applied": self.applied.tolist(), "world": self.world.tolist(), "rounds": [dict(r) for r in self.rounds]}

    def load_state_dict(self, state: dict[str, Any], avatar: Avatar) -> None:
        """Restore :meth:`state_dict` and give the avatar's parameters the registered translation
        (the avatar's content comes from the same checkpoint). The caller drops its cached poses."""
        self.applied = np.asarray(state["applied"], np.float64).reshape(3)
        self.world = np.asarray(state["world"], np.float64).reshape(3)
        self.rounds = [dict(r) for r in state["rounds"]]
        self._set_translation(avatar)
