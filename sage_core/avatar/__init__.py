"""Surfels bound to FLAME triangles: binding maths, initialization, rebinding, surfel correction, shading.

The :class:`Avatar` (``model``) holds the data; its jobs live in ``build`` (from init-mesh outputs),
``storage`` (the avatar file), ``posing`` (canonical state, FLAME posing, the rigid head map, the
correction hook) and ``rendering`` (rasterizing, shading, exposure gains); see ``model``'s docstring
for the public surface with tensor shapes.
"""

from .binding import local_to_world, nearest_triangles, point_triangle_distance, world_to_local
from .correction import CorrectionResult, SurfelCorrection
from .init import (
    REGION_EYES,
    REGION_FACE,
    REGION_HAIR,
    REGION_MOUTH,
    REGION_NAMES,
    REGION_NECK,
    REGION_OTHER,
    SurfelInit,
    face_region_labels,
    init_surfels,
)
from .model import Avatar, CanonicalSurfels, PosedSurfels
from .neighbours import surfel_neighbours, triangle_neighbours
from .shading import SHADING_MODES, SHIrradiance, orient_outward
from .surfels import SurfelSet, replace_optimizer_param

__all__ = [
    "Avatar",
    "CanonicalSurfels",
    "PosedSurfels",
    "CorrectionResult",
    "REGION_EYES",
    "REGION_FACE",
    "REGION_HAIR",
    "REGION_MOUTH",
    "REGION_NAMES",
    "REGION_NECK",
    "REGION_OTHER",
    "SHADING_MODES",
    "SHIrradiance",
    "SurfelCorrection",
    "SurfelInit",
    "SurfelSet",
    "face_region_labels",
    "init_surfels",
    "local_to_world",
    "nearest_triangles",
    "orient_outward",
    "point_triangle_distance",
    "replace_optimizer_param",
    "surfel_neighbours",
    "triangle_neighbours",
    "world_to_local",
]
