"""FLAME rig: model file IO (pickle without chumpy, npz), LBS, teeth and mouth interior, regions,
per-triangle frames, per-timestep parameter files."""

from .frames import surfel_frames, triangle_frames
from .lbs import FlameModel, FlameOutput
from .mirror import MirrorMap, mirror_correspondence, model_mirror
from .model_data import FlameModelData
from .model_io import load_flame_model, save_flame_npz, validate_model
from .mouth import add_mouth_interior, has_mouth_interior
from .params import FlameParams, load_param_npz, save_param_npz
from .regions import Regions, load_masks
from .teeth import add_teeth, has_teeth

__all__ = [
    "MirrorMap",
    "mirror_correspondence",
    "model_mirror",
    "FlameModel",
    "FlameModelData",
    "FlameOutput",
    "FlameParams",
    "Regions",
    "add_mouth_interior",
    "add_teeth",
    "has_mouth_interior",
    "has_teeth",
    "load_flame_model",
    "load_masks",
    "load_param_npz",
    "save_flame_npz",
    "save_param_npz",
    "surfel_frames",
    "triangle_frames",
    "validate_model",
]
