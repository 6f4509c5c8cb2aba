"""Training stages: init-mesh (SDF pretraining), expression sampling, phases 1 and 2, one-shot pseudo-views."""

from .expressions import ExpressionSampler, component_ranges_from_dirs
from .phase1 import Phase1Trainer, build_avatar, run_phase1
from .pseudo_views import MirrorViewProvider, PseudoView, PseudoViewProvider, TexturedRingProvider, build_pseudo_views
from .rest_teacher import RestTeacher

__all__ = [
    "ExpressionSampler",
    "MirrorViewProvider",
    "Phase1Trainer",
    "PseudoView",
    "PseudoViewProvider",
    "RestTeacher",
    "TexturedRingProvider",
    "build_avatar",
    "build_pseudo_views",
    "component_ranges_from_dirs",
    "run_phase1",
]
