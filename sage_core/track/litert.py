"""A TensorFlow Lite model run by the LiteRT interpreter (PyPI ``ai-edge-litert``), imported lazily."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import ConfigError

INSTALL_HINT = "pip install 'ai-edge-litert>=2.3' (the LiteRT interpreter; from a checkout: pip install -e '.[track]')"


def litert_available() -> str | None:
    """None when ``ai_edge_litert`` imports, else why not (one sentence naming what to install)."""
    try:
        import ai_edge_litert.interpreter  # noqa: F401
    except ImportError as exc:
        return f"the LiteRT interpreter is not installed ({exc}); {INSTALL_HINT}"
    return None


class TFLiteModel:
    """One ``.tflite`` model with a single float32 input.

    path: the model file (already verified). threads: interpreter threads.
    ``input_shape``: (1, H, W, C). :meth:`__call__` takes (H, W, C) float32 and returns the outputs as a
    dict name -> array, in the model's output order.
    """

    def __init__(self, path: str | Path, threads: int = 1) -> None:
        reason = litert_available()
        if reason is not None:
            raise ConfigError(reason)
        from ai_edge_litert.interpreter import Interpreter

        self.path = Path(path)
        self._it = Interpreter(model_path=str(self.path), num_threads=max(1, int(threads)))
        self._it.allocate_tensors()
        inp = self._it.get_input_details()
        if len(inp) != 1:
            raise ValueError(f"{self.path.name}: expected one input, found {len(inp)}")
        self._in = inp[0]["index"]
        self.input_shape = tuple(int(s) for s in inp[0]["shape"])
        self._outs = [(d["name"], d["index"], tuple(int(s) for s in d["shape"])) for d in self._it.get_output_details()]

    @property
    def output_shapes(self) -> dict[str, tuple[int, ...]]:
        """Output name -> shape."""
        return {name: shape for name, _, shape in self._outs}

    def __call__(self, x: np.ndarray) -> dict[str, np.ndarray]:
        """x: (H, W, C) float32 matching ``input_shape[1:]`` -> output name -> array (copies)."""
        x = np.ascontiguousarray(x, dtype=np.float32)
        if x.shape != self.input_shape[1:]:
            raise ValueError(f"{self.path.name}: input shape {x.shape}, expected {self.input_shape[1:]}")
        self._it.set_tensor(self._in, x[None])
        self._it.invoke()
        return {name: np.array(self._it.get_tensor(idx)) for name, idx, _ in self._outs}

    def output_by_size(self, outputs: dict[str, np.ndarray], size: int) -> np.ndarray:
        """The output with ``size`` elements (the models' output names differ between exports)."""
        hits = [a for a in outputs.values() if a.size == size]
        if len(hits) != 1:
            raise ValueError(f"{self.path.name}: expected one output of {size} values, found {len(hits)}")
        return hits[0]
