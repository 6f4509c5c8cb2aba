"""The procedural head as FLAME model files: the official pickle layout, the project's npz and
``FLAME_masks.pkl``."""

from __future__ import annotations

import pickle
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ._chumpy_pickle import Ch, csc_matrix, dumps_flame_pickle
from ._files import normalize_zip, write_bytes
from .head import PARENTS, HeadModel

if TYPE_CHECKING:
    from ...flame import FlameModel

PICKLE_NAME = "synth_flame.pkl"
NPZ_NAME = "synth_flame.npz"
MASKS_NAME = "FLAME_masks.pkl"
_KINTREE_ROOT = 4294967295


def flame_pickle_dict(head: HeadModel) -> dict:
    """The dict FLAME's pickle holds, with chumpy-style and old-sparse stand-ins.

    ``shapedirs`` and ``posedirs`` are stored as float32 to keep the file small (the official file
    uses float64; readers convert either way).
    """
    parents = PARENTS.copy()
    kintree = np.stack([np.where(parents < 0, _KINTREE_ROOT, parents), np.arange(len(parents))]).astype(np.int64)
    return {
        "f": head.faces.astype(np.uint32),
        "J_regressor": csc_matrix(head.j_regressor),
        "kintree_table": kintree,
        "J": head.joints.astype(np.float64),
        "weights": head.weights.astype(np.float64),
        "posedirs": Ch(head.posedirs.astype(np.float32)),
        "v_template": Ch(head.v_template.astype(np.float64)),
        "shapedirs": Ch(head.shapedirs.astype(np.float32)),
        "bs_style": "lbs",
        "bs_type": "lrotmin",
    }


def flame_model_data(head: HeadModel):
    """The head as ``sage_core.flame.FlameModelData`` (identity 300 + expression 100 columns)."""
    from ...flame import FlameModelData

    return FlameModelData(
        v_template=head.v_template.astype(np.float64),
        faces=head.faces.astype(np.int64),
        shapedirs=np.ascontiguousarray(head.shapedirs[:, :, :300]),
        exprdirs=np.ascontiguousarray(head.shapedirs[:, :, 300:]),
        posedirs=head.posedirs.astype(np.float64),
        j_regressor=head.j_regressor.astype(np.float64),
        lbs_weights=head.weights.astype(np.float64),
        parents=PARENTS.copy(),
        n_base_vertices=head.n_vertices,
        face_table="sage-synthetic-v1",
        version="sage-synthetic-v1",
    )


def flame_model(head: HeadModel) -> FlameModel:
    """The head as a float64 :class:`sage_core.flame.FlameModel` (what posing the synthetic truth uses)."""
    from ...flame import FlameModel

    return FlameModel(flame_model_data(head)).double()


def write_model_files(head: HeadModel, folder: str | Path) -> dict[str, Path]:
    """Write ``synth_flame.pkl``, ``synth_flame.npz`` and ``FLAME_masks.pkl`` into ``folder``.

    Returns name -> path ("pickle", "npz", "masks").
    """
    from ...flame import save_flame_npz

    folder = Path(folder)
    pkl = write_bytes(folder / PICKLE_NAME, dumps_flame_pickle(flame_pickle_dict(head)))
    npz = save_flame_npz(flame_model_data(head), folder / NPZ_NAME)
    normalize_zip(npz)
    masks = {k: np.asarray(v, dtype=np.int64) for k, v in head.masks.items()}
    msk = write_bytes(folder / MASKS_NAME, pickle.dumps(masks, protocol=2))
    return {"pickle": pkl, "npz": npz, "masks": msk}
