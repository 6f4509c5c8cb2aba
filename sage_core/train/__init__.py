"""Training stages: init-mesh (SDF pretraining), expression sampling; phases 1 and 2 build on these."""

from .expressions import ExpressionSampler, component_ranges_from_dirs

__all__ = ["ExpressionSampler", "component_ranges_from_dirs"]
