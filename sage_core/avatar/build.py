"""Building a new :class:`~sage_core.avatar.model.Avatar` from a workspace's init-mesh outputs.

:func:`build_avatar` reads ``WS/init/`` (``flame_model.npz``, ``sdf.pt``, ``regions.json``), spreads
the surfels over the canonical mesh (:func:`sage_core.avatar.init.init_surfels`, mouth interior
included) with the training cameras mapped into canonical space, and loads the pretrained SDF.

Camera mapping: a camera of the canonical timestep sees the head moved by that timestep's rigid head
map W_ct (4×4 world-from-canonical, :func:`sage_core.geometry.rigid.world_from_canonical_matrix`);
for a head-turn clip (regime ``sv-hr``) :func:`clip_cameras_at_canonical` moves the one camera of
every training timestep t into the canonical timestep's world, w2c' = w2c·W_t·W_ct⁻¹, so that it
sees the head as it did in its own frame.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from ..data.cameras import Camera
from ..errors import InputError
from ..flame.canonical import canonical_inputs
from ..flame.lbs import FlameModel
from ..flame.params import FlameParams
from ..geometry.rigid import rigid_from_flame, world_from_canonical_matrix
from .init import init_surfels
from .surfels import SurfelSet

if TYPE_CHECKING:
    from .model import Avatar


def rigid_world_from_canonical(params: FlameParams, row: int, root_joint: torch.Tensor) -> np.ndarray:
    """(4, 4) float64 x_world = R0·(x_c − J0) + J0 + t of FLAME row ``row`` (J0 = root_joint (3,))."""
    R0, t = rigid_from_flame(
        torch.as_tensor(params.rotation[row], dtype=torch.float64), torch.as_tensor(params.translation[row], dtype=torch.float64)
    )
    return world_from_canonical_matrix(R0, t, root_joint.detach().cpu().double()).numpy()


def clip_cameras_at_canonical(data: Any, params: FlameParams, ct: int, root_joint: torch.Tensor, world_from_mesh: np.ndarray,
                              limit: int = 16) -> list[Camera]:
    """A head-turn clip's camera, once per training timestep (at most ``limit``, evenly spaced), moved
    into the canonical timestep's world so that it sees the head as it did in its own frame:
    w2c' = w2c·W_t·W_ct⁻¹ with W the rigid world-from-canonical map of each timestep
    (``world_from_mesh`` = W_ct (4, 4))."""
    frames = sorted({f.timestep: f for f in data.train}.items())
    if len(frames) > limit:
        keep = np.unique(np.linspace(0, len(frames) - 1, limit).round().astype(int))
        frames = [frames[i] for i in keep]
    inv_ct = np.linalg.inv(world_from_mesh)
    out: list[Camera] = []
    for t, fr in frames:
        W = rigid_world_from_canonical(params, params.row_of(t), root_joint)
        cam = fr.camera
        out.append(Camera(cam.K.copy(), np.asarray(cam.w2c, np.float64) @ W @ inv_ct, cam.width, cam.height, cam.index, cam.name))
    return out


def build_avatar(
    cls: type[Avatar],
    ws_init_dir: str | Path,
    data: Any,
    n_surfels: int,
    attributes: str = "mlp",
    *,
    app_args: dict[str, Any] | None = None,
    shape_args: dict[str, Any] | None = None,
    sh_degree: int = 0,
    init_opacity: float = 0.5,
    init_args: dict[str, Any] | None = None,
    neus_variance: float = 0.3,
    shading: str = "none",
    device: str | torch.device = "cpu",
    generator: torch.Generator | None = None,
) -> Avatar:
    """A new ``cls`` (an :class:`Avatar` class) from init-mesh outputs; the arguments of
    :meth:`Avatar.build`."""
    from ..fields.sdf_file import read_sdf_file
    from ..flame import load_flame_model
    from ..flame.regions import Regions

    d = Path(ws_init_dir)
    model_path = d / "flame_model.npz"
    if not model_path.is_file():
        raise InputError(model_path, "missing (run `sage init-mesh` first)")
    model_data = load_flame_model(model_path)
    sdf_args, sdf_state = read_sdf_file(d / "sdf.pt")
    regions = None
    reg_path = d / "regions.json"
    if reg_path.is_file():
        try:
            regions = Regions.from_dict(json.loads(reg_path.read_text()))
        except (ValueError, KeyError, TypeError) as e:
            raise InputError(reg_path, f"malformed regions: {e}") from None
    params = data.params
    ct = data.canonical_timestep
    flame = FlameModel(model_data)
    with torch.no_grad():
        out_c = flame(**canonical_inputs(params, ct))
    verts_c = out_c.vertices[0]
    world_from_mesh = rigid_world_from_canonical(params, params.row_of(ct), out_c.joints[0, 0])
    cams: list[Camera] = []
    seen: set[int] = set()
    for fr in data.train:
        if fr.timestep == ct and fr.camera_index not in seen:
            seen.add(fr.camera_index)
            cams.append(fr.camera)
    if getattr(data, "regime", "") == "sv-hr":
        cams = clip_cameras_at_canonical(data, params, ct, out_c.joints[0, 0], world_from_mesh)
    init = init_surfels(
        verts_c, flame.faces, n_surfels, regions, cams, world_from_mesh=world_from_mesh,
        generator=generator, device=device, **(init_args or {}),
    )  # fmt: skip
    kw: dict[str, Any] = {"attributes": attributes}
    if attributes == "free":
        kw.update(sh_degree=sh_degree, opacity=init_opacity)
    surfels = SurfelSet.from_init(init, **kw).to(device)
    app = {"hidden": 32, "n_layers": 2, "sh_degree": 2, **(app_args or {})}
    shp = {"hidden": 32, "n_layers": 2, **(shape_args or {})}
    avatar = cls(model_data, params, ct, surfels, sdf_args, attributes, app, shp if attributes == "mlp" else None,
                 neus_variance=neus_variance, shading=shading)
    avatar.sdf.load_state_dict(sdf_state)
    avatar.flame_source = model_path.resolve()
    return avatar.to(device)
