"""Training stages: init-mesh (SDF pretraining), expression sampling; phases 1 and 2 build on these."""

from .expressions import ExpressionSampler, component_ranges_from_dirs
from .phase1 import Phase1Trainer, build_avatar, run_phase1

__all__ = ["ExpressionSampler", "Phase1Trainer", "build_avatar", "component_ranges_from_dirs", "run_phase1"]
