"""Person segmentation with MediaPipe's selfie segmentation model (``selfie_segmentation.tflite``).

The model sees the whole image stretched to 256×256 (RGB in [0, 1]) and returns the probability
that each pixel shows a person (head, hair, neck, shoulders); it is resized back to the image.
"""

from __future__ import annotations

import numpy as np

from .litert import TFLiteModel

INPUT_SIZE = 256


class Segmenter:
    """model_path: verified ``selfie_segmentation.tflite``; threads: interpreter threads."""

    def __init__(self, model_path: str, threads: int = 1) -> None:
        self.model = TFLiteModel(model_path, threads)

    def __call__(self, image: np.ndarray) -> np.ndarray:
        """image: (H, W, 3) float RGB in [0, 1] -> (H, W) float32 person probability in [0, 1]."""
        import cv2

        H, W = image.shape[:2]
        interp = cv2.INTER_AREA if max(H, W) > INPUT_SIZE else cv2.INTER_LINEAR
        x = cv2.resize(np.ascontiguousarray(image[..., :3], dtype=np.float32), (INPUT_SIZE, INPUT_SIZE), interpolation=interp)
        out = self.model(x)
        prob = self.model.output_by_size(out, INPUT_SIZE * INPUT_SIZE).reshape(INPUT_SIZE, INPUT_SIZE)
        prob = cv2.resize(prob.astype(np.float32), (W, H), interpolation=cv2.INTER_LINEAR)
        return np.clip(prob, 0.0, 1.0)
