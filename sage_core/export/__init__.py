"""Export formats: world-space 3DGS PLY (and ``.splat``) for viewers, MP4 video."""

from .ply import (
    decode_ply,
    decode_ply_properties,
    encode_ply,
    encode_splat,
    property_names,
    read_ply,
    write_ply,
)
from .video import VideoWriter

__all__ = [
    "VideoWriter",
    "decode_ply",
    "decode_ply_properties",
    "encode_ply",
    "encode_splat",
    "property_names",
    "read_ply",
    "write_ply",
]
