"""Smooth scalar helpers shared by the procedural head and its appearance (numpy, vectorised)."""

from __future__ import annotations

import numpy as np


def smoothstep(x: np.ndarray, e0: float, e1: float) -> np.ndarray:
    """Hermite step: 0 for x <= e0, 1 for x >= e1 (e0 > e1 flips the direction). x: any shape."""
    t = np.clip((np.asarray(x, dtype=np.float64) - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def gauss(d: np.ndarray, sigma: float) -> np.ndarray:
    """exp(-(d/sigma)^2). d: any shape."""
    return np.exp(-np.square(np.asarray(d, dtype=np.float64) / sigma))


def _hash01(ix: np.ndarray, iy: np.ndarray, iz: np.ndarray, seed: int) -> np.ndarray:
    """Deterministic pseudo-random values in [0, 1) for integer lattice points (same shapes)."""
    with np.errstate(over="ignore"):
        h = (
            ix.astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15)
            ^ iy.astype(np.uint64) * np.uint64(0xC2B2AE3D27D4EB4F)
            ^ iz.astype(np.uint64) * np.uint64(0x165667B19E3779F9)
            ^ np.uint64((seed * 0x27D4EB2F165667C5) & 0xFFFFFFFFFFFFFFFF)
        )
        h ^= h >> np.uint64(29)
        h *= np.uint64(0xBF58476D1CE4E5B9)
        h ^= h >> np.uint64(32)
        h *= np.uint64(0x94D049BB133111EB)
        h ^= h >> np.uint64(31)
    return (h >> np.uint64(11)).astype(np.float64) / float(1 << 53)


def value_noise(p: np.ndarray, frequency: float, seed: int) -> np.ndarray:
    """Smooth 3D value noise in [0, 1].

    p: (N, 3) positions (metres); frequency: lattice cells per metre -> (N,).
    """
    q = np.asarray(p, dtype=np.float64) * frequency
    i0 = np.floor(q)
    f = q - i0
    f = f * f * (3.0 - 2.0 * f)
    i0 = i0.astype(np.int64)
    out = np.zeros(q.shape[0])
    for dx in (0, 1):
        wx = f[:, 0] if dx else 1.0 - f[:, 0]
        for dy in (0, 1):
            wy = f[:, 1] if dy else 1.0 - f[:, 1]
            for dz in (0, 1):
                wz = f[:, 2] if dz else 1.0 - f[:, 2]
                out += wx * wy * wz * _hash01(i0[:, 0] + dx, i0[:, 1] + dy, i0[:, 2] + dz, seed)
    return out


def fbm(p: np.ndarray, frequency: float, seed: int, octaves: int = 3) -> np.ndarray:
    """Fractal sum of value noise, roughly in [0, 1]. p: (N, 3) -> (N,)."""
    total = np.zeros(p.shape[0])
    amp, norm = 1.0, 0.0
    for o in range(octaves):
        total += amp * value_noise(p, frequency * (2.0**o), seed + 101 * o)
        norm += amp
        amp *= 0.5
    return total / norm
