"""Capture data: cameras, image IO, the VHAP capture reader, the ingest engine and its output reader.

Importing this package is light (numpy only): OpenImageIO, cv2 and torch are imported inside the
functions that need them.
"""

from __future__ import annotations

from .cameras import Camera, camera_from_nerf_frame, camera_to_nerf_frame
from .capture import Capture, CaptureFrame, read_capture, validate_against_model
from .dataset import IngestedData, IngestedFrame
from .imageio import read_image, write_image
from .ingest import IngestSummary, ingest, select_frames

__all__ = [
    "Camera",
    "Capture",
    "CaptureFrame",
    "IngestSummary",
    "IngestedData",
    "IngestedFrame",
    "camera_from_nerf_frame",
    "camera_to_nerf_frame",
    "ingest",
    "read_capture",
    "read_image",
    "select_frames",
    "validate_against_model",
    "write_image",
]
