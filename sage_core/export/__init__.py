"""Export: world-space 3DGS PLY (and ``.splat``) for viewers, MP4 video, driving motions and reenactment."""

from .ply import (
    decode_ply,
    decode_ply_properties,
    encode_ply,
    encode_splat,
    property_names,
    read_ply,
    write_ply,
)
from .motion import Motion, load_motion, orbit_cameras
from .reenact import ReenactReport, reenact
from .video import VideoWriter

__all__ = [
    "Motion",
    "ReenactReport",
    "VideoWriter",
    "load_motion",
    "orbit_cameras",
    "reenact",
    "decode_ply",
    "decode_ply_properties",
    "encode_ply",
    "encode_splat",
    "property_names",
    "read_ply",
    "write_ply",
]
