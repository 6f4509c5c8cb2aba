"""Initial surfels spread over the canonical FLAME triangles (SAGE: no densification).

Each triangle f gets a sampling weight

    w_f = area_f · region_weight(f) · (1 + camera_weight · view_f)

* ``area_f``: the canonical triangle's area, so that with all other factors equal the surfel
  density per unit area is uniform (the "by scale" distribution of the paper).
* ``region_weight``: ``face_weight`` on the face and the eyeballs, ``mouth_weight`` on the mouth
  interior and teeth, ``hair_weight`` on the hair, ``neck_weight`` on the neck, 1 elsewhere
  (ears, back of the head, boundary). Labels come from :func:`face_region_labels`.
* ``view_f`` ∈ [0, 1]: the triangle's best view over the training cameras,
  max_c cos⁺(n_f, o_c − T_f) / ‖o_c − T_f‖² for cameras whose image contains the centroid T_f
  (in front of the camera), divided by its maximum over all triangles. Triangles facing a nearby
  camera get up to (1 + camera_weight) times the density of unseen ones. Occlusion is ignored.

``min_per_face`` surfels go to every triangle of positive weight first; the remaining ones are
drawn by multinomial sampling over w_f (deterministic given the generator). A surfel sits at a
uniformly random point of its triangle (zero offset along the normal), lies flat on it
(q_loc = identity, or a random rotation about the normal), and has both in-plane scales
s = scale_factor·sqrt(area_f / (π·n_f)) with n_f the triangle's surfel count: n_f disks of radius s
have the triangle's area. Stored as s_loc = log(s/k_f), clamped to log(scale_range).

``layout="per_face"`` is GaussianAvatars' initialisation instead: one surfel at the centroid of
every triangle, flat on it, with s = k_f (s_loc = 0); the benchmark's GaussianAvatars rows then
grow and thin the set by adaptive density control (:mod:`sage_core.train.densify`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np
import torch

from ..data.cameras import Camera
from ..flame.frames import surfel_frames
from ..flame.regions import Regions

REGION_NAMES: tuple[str, ...] = ("other", "face", "eyes", "mouth", "hair", "neck")
"""Surfel region labels: index = ``region_id``. ``face`` is FLAME's face mask (lips, nose, eye
regions, forehead), ``eyes`` the eyeballs, ``mouth`` the mouth interior and teeth, ``hair`` the
derived hair region (scalp minus face and neck), ``neck`` the neck, ``other`` everything else."""

REGION_OTHER, REGION_FACE, REGION_EYES, REGION_MOUTH, REGION_HAIR, REGION_NECK = range(6)

INIT_LAYOUTS: tuple[str, ...] = ("sampled", "per_face")
"""Surfel layouts of :func:`init_surfels`: weighted sampling (SAGE) or one per triangle (GaussianAvatars)."""

# (label, region names whose union it covers), in priority order: a face matching several takes
# the first.
_LABEL_SOURCES: tuple[tuple[int, tuple[str, ...]], ...] = (
    (REGION_MOUTH, ("mouth_interior", "teeth")),
    (REGION_EYES, ("eyeballs",)),
    (REGION_FACE, ("face", "lips", "left_eye_region", "right_eye_region", "eye_region", "nose", "forehead")),
    (REGION_HAIR, ("hair",)),
    (REGION_NECK, ("neck",)),
)


def face_region_labels(regions: Regions | None, n_faces: int) -> np.ndarray:
    """(F,) int64 labels into :data:`REGION_NAMES` of every face (0 = other).

    Uses whichever of the source regions ``regions`` has; None gives all 0. Raises ValueError if
    ``regions`` describes a different number of faces.
    """
    labels = np.zeros(n_faces, dtype=np.int64)
    if regions is None:
        return labels
    if regions.n_faces != n_faces:
        raise ValueError(f"regions describe {regions.n_faces} faces, the mesh has {n_faces}")
    assigned = np.zeros(n_faces, dtype=bool)
    for label, names in _LABEL_SOURCES:
        mask = np.zeros(n_faces, dtype=bool)
        for name in names:
            if regions.has(name):
                mask |= regions.face_mask(name)
        mask &= ~assigned
        labels[mask] = label
        assigned |= mask
    return labels


@dataclass
class SurfelInit:
    """Initial per-surfel tensors (float tensors in the requested dtype, on the requested device).

    binding: (N,) int64 face ids, sorted; mu_loc: (N, 3); q_loc: (N, 4) wxyz unit; s_loc: (N, 2)
    log scales relative to k; region_id: (N,) int64 into :data:`REGION_NAMES`; face_region: (F,)
    int64 label of every face; face_weight: (F,) float64 sampling weight of every face (numpy);
    summary: counts and areas per region (plain data).
    """

    binding: torch.Tensor
    mu_loc: torch.Tensor
    q_loc: torch.Tensor
    s_loc: torch.Tensor
    region_id: torch.Tensor
    face_region: torch.Tensor
    face_weight: np.ndarray
    summary: dict[str, Any] = field(default_factory=dict)


def _camera_view_term(
    centroids: np.ndarray, normals: np.ndarray, cameras: Sequence[Camera], world_from_mesh: np.ndarray | None
) -> np.ndarray:
    """(F,) in [0, 1]: max over cameras of cos⁺·in-image / distance², normalised by its maximum."""
    if world_from_mesh is not None:
        M = np.asarray(world_from_mesh, dtype=np.float64)
        if M.shape != (4, 4):
            raise ValueError(f"world_from_mesh must be (4, 4), got {M.shape}")
        centroids = centroids @ M[:3, :3].T + M[:3, 3]
        normals = normals @ M[:3, :3].T
    best = np.zeros(centroids.shape[0])
    for cam in cameras:
        d = cam.center[None, :] - centroids
        dist2 = np.maximum((d * d).sum(-1), 1e-20)
        cos = (normals * d).sum(-1) / np.sqrt(dist2)
        uv, z = cam.project(centroids)
        inside = (z > 0) & np.isfinite(uv).all(-1)
        inside &= (uv[:, 0] >= 0) & (uv[:, 0] <= cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] <= cam.height)
        best = np.maximum(best, np.where(inside, np.clip(cos, 0.0, None) / dist2, 0.0))
    top = best.max() if best.size else 0.0
    return best / top if top > 0 else best


def init_surfels(
    vertices: torch.Tensor,
    faces: torch.Tensor,
    n_surfels: int,
    regions: Regions | None = None,
    cameras: Sequence[Camera] | None = None,
    *,
    face_weight: float = 3.0,
    mouth_weight: float = 2.0,
    hair_weight: float = 0.5,
    neck_weight: float = 0.5,
    camera_weight: float = 2.0,
    world_from_mesh: np.ndarray | None = None,
    min_per_face: int = 0,
    scale_factor: float = 1.0,
    scale_range: tuple[float, float] = (1e-3, 1.0),
    random_rotation: bool = False,
    layout: str = "sampled",
    generator: torch.Generator | None = None,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> SurfelInit:
    """Distribute ``n_surfels`` surfels over the triangles of a canonical mesh (see module doc).

    layout: "sampled" (the module doc) or "per_face": one surfel at the centroid of every triangle,
    flat on it with both local scales 1 (s = k_f), GaussianAvatars' initialisation; ``n_surfels``,
    the weights and ``scale_factor`` are then unused (the summary still reports the weights' regions).

    vertices: (V, 3) canonical mesh; faces: (F, 3); regions: labels for the region weights (None:
    every face weighs 1); cameras: training cameras for the view term (None or empty: no view
    term); world_from_mesh: (4, 4) rigid transform from the mesh's space to the cameras' world
    (None: the same space); scale_range: (lo, hi) clamp of s/k; generator: a CPU
    ``torch.Generator`` (sampling runs on the CPU in float64). Results go to ``device`` (default:
    the vertices' device) as ``dtype``. Raises ValueError on non-positive counts or weights, or
    when ``n_surfels < min_per_face ·`` (faces of positive weight).
    """
    if n_surfels <= 0:
        raise ValueError("n_surfels must be positive")
    for name, w in (("face_weight", face_weight), ("mouth_weight", mouth_weight), ("hair_weight", hair_weight),
                    ("neck_weight", neck_weight), ("camera_weight", camera_weight)):
        if not (w >= 0 and math.isfinite(w)):
            raise ValueError(f"{name} must be finite and non-negative, got {w}")
    if layout not in INIT_LAYOUTS:
        raise ValueError(f"layout must be one of {', '.join(INIT_LAYOUTS)}, got {layout!r}")
    lo, hi = scale_range
    if not (0 < lo <= hi):
        raise ValueError(f"scale_range must satisfy 0 < lo <= hi, got {scale_range}")
    device = torch.device(device) if device is not None else vertices.device
    v64 = vertices.detach().to("cpu", torch.float64)
    f64 = faces.detach().to("cpu", torch.long)
    F = f64.shape[0]
    R, T, k = surfel_frames(v64, f64)
    tri = v64[f64]  # (F, 3, 3)
    area = 0.5 * torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], dim=-1).norm(dim=-1)

    labels = face_region_labels(regions, F)
    region_w = np.ones(len(REGION_NAMES))
    region_w[[REGION_FACE, REGION_EYES]] = face_weight
    region_w[REGION_MOUTH] = mouth_weight
    region_w[REGION_HAIR] = hair_weight
    region_w[REGION_NECK] = neck_weight
    weight = area.numpy() * region_w[labels]
    if cameras:
        view = _camera_view_term(T.numpy(), R[:, :, 2].numpy(), cameras, world_from_mesh)
        weight = weight * (1.0 + camera_weight * view)
    if layout == "per_face":
        return _per_face(area, labels, weight, device, dtype)
    eligible = weight > 0
    if not eligible.any():
        raise ValueError("every triangle has zero sampling weight")
    n_fixed = int(min_per_face) * int(eligible.sum())
    if min_per_face < 0 or n_fixed > n_surfels:
        raise ValueError(f"min_per_face={min_per_face} needs {n_fixed} surfels, have {n_surfels}")

    fixed = np.repeat(np.nonzero(eligible)[0], int(min_per_face))
    n_draw = n_surfels - n_fixed
    if n_draw > 0:
        drawn = torch.multinomial(torch.as_tensor(weight), n_draw, replacement=True, generator=generator).numpy()
    else:
        drawn = np.zeros(0, dtype=np.int64)
    binding = torch.as_tensor(np.sort(np.concatenate([fixed, drawn]).astype(np.int64)))
    counts = torch.bincount(binding, minlength=F)

    uv = torch.rand((n_surfels, 2), generator=generator, dtype=torch.float64)
    flip = uv.sum(-1) > 1
    uv = torch.where(flip[:, None], 1.0 - uv, uv)
    t = tri[binding]
    pts = t[:, 0] + uv[:, :1] * (t[:, 1] - t[:, 0]) + uv[:, 1:] * (t[:, 2] - t[:, 0])
    kb = k[binding].clamp_min(1e-12)
    mu_loc = (R[binding].transpose(-1, -2) @ (pts - T[binding])[..., None]).squeeze(-1) / kb[:, None]
    mu_loc[:, 2] = 0.0

    if random_rotation:
        theta = 2 * math.pi * torch.rand(n_surfels, generator=generator, dtype=torch.float64)
        zero = torch.zeros_like(theta)
        q_loc = torch.stack([torch.cos(theta / 2), zero, zero, torch.sin(theta / 2)], -1)
    else:
        q_loc = torch.zeros((n_surfels, 4), dtype=torch.float64)
        q_loc[:, 0] = 1.0

    n_b = counts[binding].to(torch.float64)
    s = scale_factor * torch.sqrt(area[binding] / (math.pi * n_b))
    ratio = (s / kb).clamp(lo, hi)
    s_loc = torch.log(ratio)[:, None].expand(n_surfels, 2).clone()

    region_id = torch.as_tensor(labels)[binding]
    summary = _summary(labels, area.numpy(), counts.numpy(), n_surfels)

    def out(x: torch.Tensor) -> torch.Tensor:
        return x.to(device=device, dtype=dtype)

    return SurfelInit(
        binding=binding.to(device),
        mu_loc=out(mu_loc),
        q_loc=out(q_loc),
        s_loc=out(s_loc),
        region_id=region_id.to(device),
        face_region=torch.as_tensor(labels).to(device),
        face_weight=weight,
        summary=summary,
    )


def _per_face(area: torch.Tensor, labels: np.ndarray, weight: np.ndarray, device: torch.device, dtype: torch.dtype) -> SurfelInit:
    """One surfel per triangle at its frame origin (the centroid), q_loc = identity, s_loc = 0."""
    F = int(area.shape[0])
    q_loc = torch.zeros((F, 4), dtype=dtype)
    q_loc[:, 0] = 1.0
    return SurfelInit(
        binding=torch.arange(F, dtype=torch.long, device=device),
        mu_loc=torch.zeros((F, 3), dtype=dtype, device=device),
        q_loc=q_loc.to(device),
        s_loc=torch.zeros((F, 2), dtype=dtype, device=device),
        region_id=torch.as_tensor(labels).to(device),
        face_region=torch.as_tensor(labels).to(device),
        face_weight=weight,
        summary=_summary(labels, area.numpy(), np.ones(F, dtype=np.int64), F),
    )


def _summary(labels: np.ndarray, area: np.ndarray, counts: np.ndarray, n_surfels: int) -> dict[str, Any]:
    per_region: dict[str, dict[str, float | int]] = {}
    for i, name in enumerate(REGION_NAMES):
        m = labels == i
        if not m.any():
            continue
        a = float(area[m].sum())
        n = int(counts[m].sum())
        per_region[name] = {"surfels": n, "faces": int(m.sum()), "area": a, "density": n / a if a > 0 else 0.0}
    return {
        "n_surfels": int(n_surfels),
        "n_faces": int(labels.shape[0]),
        "faces_used": int((counts > 0).sum()),
        "max_per_face": int(counts.max()) if counts.size else 0,
        "regions": per_region,
    }
