"""FLAME posed at a subset of its vertices: the landmark fit poses only the few hundred vertices the
landmarks lie on, for hundreds of frames at once.

The joints depend on every vertex (``J = J_regressor · v_shaped``), but linearly, so their template
part and their shape and expression blendshapes are regressed once here; posing then touches only
the chosen rows. The result equals :class:`sage_core.flame.FlameModel` at those rows (tested).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from ..flame import FlameModel
from ..geometry.rotations import axis_angle_to_matrix


class JointBasis:
    """The joints' template and blendshapes of a model, regressed once (shared by many subsets).

    model: the full model; n_shape, n_expr: the leading blendshape columns kept (None: all).
    """

    def __init__(self, model: FlameModel, n_shape: int | None = None, n_expr: int | None = None) -> None:
        V = model.n_vertices
        self.n_shape = model.n_shape if n_shape is None else min(int(n_shape), model.n_shape)
        self.n_expr = model.n_expr if n_expr is None else min(int(n_expr), model.n_expr)
        jr = model.j_regressor
        self.template = jr @ model.v_template  # (J, 3)
        self.shapedirs = torch.einsum("jv,vck->jck", jr, model.shapedirs.view(V, 3, -1)[..., : self.n_shape])
        self.exprdirs = torch.einsum("jv,vck->jck", jr, model.exprdirs.view(V, 3, -1)[..., : self.n_expr])


class FlameSubset(torch.nn.Module):
    """The rows ``vertex_ids`` of a FLAME model.

    model: the full model (its buffers are sliced, not copied as parameters). vertex_ids: (n,) long.
    joints: the model's :class:`JointBasis` (regressed here when None); its column counts decide how
    many shape and expression coefficients count (later ones are ignored, as if zero).
    """

    def __init__(self, model: FlameModel, vertex_ids: torch.Tensor, joints: JointBasis | None = None) -> None:
        super().__init__()
        joints = JointBasis(model) if joints is None else joints
        ids = torch.as_tensor(vertex_ids, dtype=torch.long, device=model.v_template.device)
        V = model.n_vertices
        self.register_buffer("ids", ids)
        self.register_buffer("v_template", model.v_template[ids])
        self.register_buffer("shapedirs", model.shapedirs.view(V, 3, -1)[ids, :, : joints.n_shape])  # (n, 3, S)
        self.register_buffer("exprdirs", model.exprdirs.view(V, 3, -1)[ids, :, : joints.n_expr])  # (n, 3, E)
        P = model.posedirs.shape[0]
        self.register_buffer("posedirs", model.posedirs.view(P, V, 3)[:, ids].reshape(P, -1))  # (P, n·3)
        self.register_buffer("lbs_weights", model.lbs_weights[ids])
        self.register_buffer("j_regressor", model.j_regressor)
        self.register_buffer("j_template", joints.template)
        self.register_buffer("j_shapedirs", joints.shapedirs)
        self.register_buffer("j_exprdirs", joints.exprdirs)
        self.parents = list(model.parents)
        self.n_shape = joints.n_shape
        self.n_expr = joints.n_expr

    def forward(self, shape: torch.Tensor, expr: torch.Tensor, rotation: torch.Tensor, neck_pose: torch.Tensor,
                jaw_pose: torch.Tensor, eyes_pose: torch.Tensor, translation: torch.Tensor,
                static_offset: torch.Tensor | None = None) -> torch.Tensor:
        """Posed vertices (B, n, 3).

        shape: (S',) shared; expr: (B, E'); rotation, neck_pose, jaw_pose, translation: (B, 3);
        eyes_pose: (B, 6); static_offset: (V, 3) over all model vertices, or None. Coefficients are
        zero-padded or cut to the subset's counts (FlameModel pads or cuts to the model's).
        """
        B = expr.shape[0]
        n = self.ids.shape[0]
        J = self.j_template.shape[0]

        def fit(x: torch.Tensor, k: int) -> torch.Tensor:
            return x[..., :k] if x.shape[-1] >= k else F.pad(x, (0, k - x.shape[-1]))

        beta = fit(shape.reshape(-1), self.n_shape)
        psi = fit(expr, self.n_expr)
        v = self.v_template + torch.einsum("nck,k->nc", self.shapedirs, beta)  # (n, 3)
        v = v[None] + torch.einsum("nck,bk->bnc", self.exprdirs, psi)  # (B, n, 3)
        j = self.j_template + torch.einsum("jck,k->jc", self.j_shapedirs, beta)
        j = j[None] + torch.einsum("jck,bk->bjc", self.j_exprdirs, psi)  # (B, J, 3)
        if static_offset is not None:
            v = v + static_offset[self.ids][None]
            j = j + (self.j_regressor @ static_offset)[None]
        pose = torch.cat([rotation, neck_pose, jaw_pose, eyes_pose], 1).reshape(B, 5, 3)
        pose = pose[:, :J] if J <= 5 else F.pad(pose, (0, 0, 0, J - 5))
        rot = axis_angle_to_matrix(pose)  # (B, J, 3, 3)
        if J > 1:
            eye = torch.eye(3, dtype=v.dtype, device=v.device)
            v = v + ((rot[:, 1:] - eye).reshape(B, 9 * (J - 1)) @ self.posedirs).view(B, n, 3)
        rel = j.clone()
        if J > 1:
            rel[:, 1:] = j[:, 1:] - j[:, self.parents[1:]]
        local = torch.cat([rot, rel[..., None]], -1)
        bottom = v.new_tensor([0.0, 0.0, 0.0, 1.0]).expand(B, J, 1, 4)
        local = torch.cat([local, bottom], -2)
        chain = [local[:, 0]]
        for k in range(1, J):
            chain.append(chain[self.parents[k]] @ local[:, k])
        G = torch.stack(chain, 1)
        corr = G[:, :, :3, 3] - (G[:, :, :3, :3] @ j[..., None])[..., 0]
        A = torch.cat([G[:, :, :3, :3], corr[..., None]], -1)  # (B, J, 3, 4)
        T = torch.einsum("nj,bjrc->bnrc", self.lbs_weights, A)
        out = (T[..., :3] * v[:, :, None, :]).sum(-1) + T[..., 3]
        return out + translation[:, None]
