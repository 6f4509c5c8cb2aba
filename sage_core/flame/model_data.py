"""The FLAME model as plain numpy arrays (:class:`FlameModelData`): what the model file readers
produce and the rig, the teeth and the mouth interior extend."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np


@dataclass
class FlameModelData:
    """A FLAME-style linear blend skinning model as plain numpy arrays.

    Attributes:
        v_template: (V, 3) float64 mean head (metres).
        faces: (F, 3) int64 triangles.
        shapedirs: (V, 3, S) float64 identity blendshapes.
        exprdirs: (V, 3, E) float64 expression blendshapes (E may be 0).
        posedirs: (V, 3, P) float64 pose correctives, P = 9·(J−1).
        j_regressor: (J, V) float64 dense joint regressor.
        lbs_weights: (V, J) float64 skinning weights.
        parents: (J,) int64 kinematic tree, -1 for the root; parents[j] < j.
        n_base_vertices: vertex count of the model before any extension (teeth, mouth interior).
        face_table: id of the face table, e.g. "flame" or "flame+sage-teeth-v1".
        version: free label, e.g. "flame2023".
        vertex_groups: name -> int64 vertex ids of appended parts (e.g. "teeth_upper").
    """

    v_template: np.ndarray
    faces: np.ndarray
    shapedirs: np.ndarray
    exprdirs: np.ndarray
    posedirs: np.ndarray
    j_regressor: np.ndarray
    lbs_weights: np.ndarray
    parents: np.ndarray
    n_base_vertices: int
    face_table: str = "flame"
    version: str = "flame"
    vertex_groups: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def n_vertices(self) -> int:
        return int(self.v_template.shape[0])

    @property
    def n_faces(self) -> int:
        return int(self.faces.shape[0])

    @property
    def n_joints(self) -> int:
        return int(self.parents.shape[0])

    @property
    def n_shape(self) -> int:
        return int(self.shapedirs.shape[2])

    @property
    def n_expr(self) -> int:
        return int(self.exprdirs.shape[2])

    def copy(self) -> FlameModelData:
        """A deep copy (arrays copied)."""
        return replace(
            self,
            v_template=self.v_template.copy(),
            faces=self.faces.copy(),
            shapedirs=self.shapedirs.copy(),
            exprdirs=self.exprdirs.copy(),
            posedirs=self.posedirs.copy(),
            j_regressor=self.j_regressor.copy(),
            lbs_weights=self.lbs_weights.copy(),
            parents=self.parents.copy(),
            vertex_groups={k: v.copy() for k, v in self.vertex_groups.items()},
        )
