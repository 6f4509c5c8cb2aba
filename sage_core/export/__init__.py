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
from .avatar_ply import encode_posed_ply, ply_render_inputs, rgb_to_sh_dc, sh_dc_to_rgb, write_posed_ply
from .bundle import Bundle, RenderSettings, is_bundle, load_bundle, read_bundle_metadata, write_bundle
from .meshes import mesh_bytes, posed_mesh, sdf_mesh, write_mesh
from .motion import Motion, load_motion, orbit_cameras
from .reenact import ReenactReport, reenact
from .video import VideoWriter

__all__ = [
    "Bundle",
    "RenderSettings",
    "encode_posed_ply",
    "is_bundle",
    "load_bundle",
    "mesh_bytes",
    "ply_render_inputs",
    "posed_mesh",
    "read_bundle_metadata",
    "rgb_to_sh_dc",
    "sdf_mesh",
    "sh_dc_to_rgb",
    "write_bundle",
    "write_mesh",
    "write_posed_ply",
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
