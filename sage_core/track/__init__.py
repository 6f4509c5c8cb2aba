"""``sage track``: FLAME parameters, cameras and masks from your own photos, video or calibrated rig, on a CPU.

Face detection, 468 dense landmarks and person segmentation come from three MediaPipe models run by
the LiteRT interpreter (:mod:`.weights` finds and checks them; sage never downloads at run time). The
landmarks are tied to any FLAME-format mesh by a calibrated embedding (:mod:`.embedding`), FLAME and
the cameras are fitted to landmarks, silhouettes and colours through the project's mesh rasterizer
(:mod:`.fitting`), and the result is written as a VHAP-layout capture (:mod:`.pipeline`).
"""

from __future__ import annotations

from .config import REGIMES, TrackConfig, resolve_track_config
from .pipeline import TrackResult, track_capture

__all__ = ["REGIMES", "TrackConfig", "TrackResult", "resolve_track_config", "track_capture"]
