"""FLAME linear blend skinning in torch (docs/formats.md §3.2), batched and differentiable."""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from ..geometry.rotations import axis_angle_to_matrix
from .model_data import FlameModelData

# Joint order of the named FLAME pose parameters: rotation, neck, jaw, eye, eye.
_POSE_JOINTS = 5


@dataclass
class FlameOutput:
    """Result of one FLAME evaluation.

    Attributes:
        vertices: (B, V, 3) posed vertices, translation included.
        joints: (B, J, 3) posed joint positions, translation included; joints[:, 0] is the rest
            J0 + translation (the pivot of ``rotation`` does not move with it).
        v_shaped: (B, V, 3) template + shape + expression + offsets, before pose correctives and
            skinning (the canonical mesh when all poses are zero).
        A: (B, J, 4, 4) skinning transforms (rest pose removed, translation not included):
            vertices = (Σ_j w_j A_j)·[v_posed; 1] + translation.
    """

    vertices: torch.Tensor
    joints: torch.Tensor
    v_shaped: torch.Tensor
    A: torch.Tensor


def _batched(x: torch.Tensor | None, B: int, width: int, name: str, like: torch.Tensor) -> torch.Tensor:
    """(B, width) from (width,), (1, width) or (B, width); None -> zeros."""
    if x is None:
        return like.new_zeros(B, width)
    x = x.to(dtype=like.dtype, device=like.device)
    if x.ndim == 1:
        x = x[None]
    if x.ndim != 2 or x.shape[0] not in (1, B):
        raise ValueError(f"{name}: expected ({B}, {width}) or ({width},), got {tuple(x.shape)}")
    return x.expand(B, x.shape[1])


def _fit_coeffs(x: torch.Tensor, n: int) -> torch.Tensor:
    """Zero-pad or truncate the last dimension of (B, n') to n."""
    if x.shape[1] >= n:
        return x[:, :n]
    return F.pad(x, (0, n - x.shape[1]))


def _fit_offset(x: torch.Tensor | None, B: int, V: int, name: str, like: torch.Tensor) -> torch.Tensor | None:
    """(B, V, 3) from (V', 3) or (1|B, V', 3), zero-padding rows V'..V-1; None stays None."""
    if x is None:
        return None
    x = x.to(dtype=like.dtype, device=like.device)
    if x.ndim == 2:
        x = x[None]
    if x.ndim != 3 or x.shape[2] != 3 or x.shape[0] not in (1, B):
        raise ValueError(f"{name}: expected (V', 3) or ({B}, V', 3), got {tuple(x.shape)}")
    if x.shape[1] > V:
        raise ValueError(f"{name}: has {x.shape[1]} rows, the model has only {V} vertices")
    if x.shape[1] < V:
        x = F.pad(x, (0, 0, 0, V - x.shape[1]))
    return x.expand(B, V, 3)


def _left_mm(M: torch.Tensor, X: torch.Tensor) -> torch.Tensor:
    """M: (P, Q), X: (B, Q, C) -> (B, P, C) as one matrix product (faster than a batched one)."""
    B, Q, C = X.shape
    out = M @ X.permute(1, 0, 2).reshape(Q, B * C)
    return out.reshape(M.shape[0], B, C).permute(1, 0, 2)


class FlameModel(torch.nn.Module):
    """FLAME (or any FLAME-style) LBS model.

    Buffers (``dtype``, float32 by default; build with ``dtype=torch.float64`` for exact double
    precision, since ``.double()`` after construction keeps the float32 rounding): ``v_template (V,3)``,
    ``shapedirs (V·3,S)``, ``exprdirs (V·3,E)``, ``posedirs (P,V·3)``, ``j_regressor (J,V)``,
    ``lbs_weights (V,J)``, ``faces (F,3)`` long. ``parents`` is a python list.
    """

    def __init__(self, data: FlameModelData, dtype: torch.dtype = torch.float32) -> None:
        super().__init__()
        V, J = data.n_vertices, data.n_joints
        f32 = dtype
        self.register_buffer("v_template", torch.as_tensor(data.v_template, dtype=f32))
        self.register_buffer("shapedirs", torch.as_tensor(data.shapedirs, dtype=f32).reshape(V * 3, -1))
        self.register_buffer("exprdirs", torch.as_tensor(data.exprdirs, dtype=f32).reshape(V * 3, -1))
        self.register_buffer("posedirs", torch.as_tensor(data.posedirs, dtype=f32).reshape(V * 3, -1).T.contiguous())
        self.register_buffer("j_regressor", torch.as_tensor(data.j_regressor, dtype=f32))
        self.register_buffer("lbs_weights", torch.as_tensor(data.lbs_weights, dtype=f32))
        self.register_buffer("faces", torch.as_tensor(data.faces, dtype=torch.long))
        self.parents: list[int] = [int(p) for p in data.parents]
        self.n_base_vertices = int(data.n_base_vertices)
        self.face_table = data.face_table
        self.vertex_groups = {k: v.copy() for k, v in data.vertex_groups.items()}
        self.n_vertices = V
        self.n_joints = J
        self.n_shape = int(data.shapedirs.shape[2])
        self.n_expr = int(data.exprdirs.shape[2])

    def forward(
        self,
        shape: torch.Tensor | None = None,
        expr: torch.Tensor | None = None,
        rotation: torch.Tensor | None = None,
        neck_pose: torch.Tensor | None = None,
        jaw_pose: torch.Tensor | None = None,
        eyes_pose: torch.Tensor | None = None,
        translation: torch.Tensor | None = None,
        static_offset: torch.Tensor | None = None,
        dynamic_offset: torch.Tensor | None = None,
    ) -> FlameOutput:
        """Pose the model.

        shape: (B, S') or (S',); expr: (B, E'); rotation, neck_pose, jaw_pose, translation: (B, 3);
        eyes_pose: (B, 6); static_offset: (V', 3) or (B, V', 3); dynamic_offset: (B, V', 3).
        Any argument may be None (zeros) and any batched one may have batch size 1 (broadcast).
        Coefficients shorter than the model's blendshapes are zero-padded, longer ones truncated;
        offsets with V' < V rows are zero-padded. Pose joints: rotation -> 0, neck -> 1, jaw -> 2,
        eyes[:3] -> 3, eyes[3:] -> 4; joints beyond those get zero pose, missing ones are ignored.
        """
        like = self.v_template
        batch_sizes = [
            t.shape[0]
            for t in (expr, rotation, neck_pose, jaw_pose, eyes_pose, translation, dynamic_offset)
            if t is not None and t.ndim >= 2
        ]
        if shape is not None and shape.ndim == 2:
            batch_sizes.append(shape.shape[0])
        if static_offset is not None and static_offset.ndim == 3:
            batch_sizes.append(static_offset.shape[0])
        B = max(batch_sizes, default=1)
        V, J = self.n_vertices, self.n_joints

        shape_b = _batched(shape, B, self.n_shape, "shape", like) if shape is not None else like.new_zeros(B, 0)
        expr_b = _batched(expr, B, self.n_expr, "expr", like) if expr is not None else like.new_zeros(B, 0)
        poses = [
            _batched(rotation, B, 3, "rotation", like),
            _batched(neck_pose, B, 3, "neck_pose", like),
            _batched(jaw_pose, B, 3, "jaw_pose", like),
            _batched(eyes_pose, B, 6, "eyes_pose", like),
        ]
        for name, p, w in zip(("rotation", "neck_pose", "jaw_pose", "eyes_pose"), poses, (3, 3, 3, 6)):
            if p.shape[1] != w:
                raise ValueError(f"{name}: expected width {w}, got {p.shape[1]}")
        full_pose = torch.cat(poses, dim=1).reshape(B, _POSE_JOINTS, 3)
        if J <= _POSE_JOINTS:
            full_pose = full_pose[:, :J]
        else:
            full_pose = F.pad(full_pose, (0, 0, 0, J - _POSE_JOINTS))
        trans = _batched(translation, B, 3, "translation", like)
        if trans.shape[1] != 3:
            raise ValueError(f"translation: expected width 3, got {trans.shape[1]}")

        # 1-2. blendshapes and offsets (canonical space)
        v_shaped = like.expand(B, V, 3)
        if self.n_shape and shape_b.shape[1]:
            v_shaped = v_shaped + F.linear(_fit_coeffs(shape_b, self.n_shape), self.shapedirs).view(B, V, 3)
        if self.n_expr and expr_b.shape[1]:
            v_shaped = v_shaped + F.linear(_fit_coeffs(expr_b, self.n_expr), self.exprdirs).view(B, V, 3)
        for name, off in (("static_offset", static_offset), ("dynamic_offset", dynamic_offset)):
            o = _fit_offset(off, B, V, name, like)
            if o is not None:
                v_shaped = v_shaped + o

        # 3. joints from the offset mesh
        joints_rest = _left_mm(self.j_regressor, v_shaped)  # (B, J, 3)

        # 4-5. rotations and pose correctives
        rot = axis_angle_to_matrix(full_pose)  # (B, J, 3, 3)
        v_posed = v_shaped
        if J > 1:
            eye = torch.eye(3, dtype=like.dtype, device=like.device)
            pose_feature = (rot[:, 1:] - eye).reshape(B, 9 * (J - 1))
            v_posed = v_shaped + (pose_feature @ self.posedirs).view(B, V, 3)

        # 6. kinematic chain
        rel = joints_rest.clone()
        if J > 1:
            parents = torch.as_tensor(self.parents[1:], device=like.device)
            rel[:, 1:] = joints_rest[:, 1:] - joints_rest[:, parents]
        local = torch.cat([rot, rel[..., None]], dim=-1)  # (B, J, 3, 4)
        bottom = like.new_tensor([0.0, 0.0, 0.0, 1.0]).expand(B, J, 1, 4)
        local = torch.cat([local, bottom], dim=-2)  # (B, J, 4, 4)
        chain = [local[:, 0]]
        for j in range(1, J):
            chain.append(chain[self.parents[j]] @ local[:, j])
        G = torch.stack(chain, dim=1)  # (B, J, 4, 4)
        joints_posed = G[:, :, :3, 3]

        # 7. remove the rest pose: A_j = G_j · [[I, -J_j], [0, 1]]
        corr = G[:, :, :3, 3] - (G[:, :, :3, :3] @ joints_rest[..., None])[..., 0]
        A = torch.cat([G[:, :, :, :3], torch.cat([corr, G[:, :, 3:, 3]], dim=-1)[..., None]], dim=-1)

        # 8. skinning
        T = _left_mm(self.lbs_weights, A[:, :, :3, :].reshape(B, J, 12)).view(B, V, 3, 4)
        verts = (T[..., :3] * v_posed[:, :, None, :]).sum(-1) + T[..., 3]

        # 9. translation last
        verts = verts + trans[:, None]
        return FlameOutput(vertices=verts, joints=joints_posed + trans[:, None], v_shaped=v_shaped, A=A)
