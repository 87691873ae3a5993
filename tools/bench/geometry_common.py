"""Shared pieces of the geometry benchmarks: an analytic test object, its extracted mesh and cage."""

from __future__ import annotations

import platform
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

BOUNDS = [[-1.5, -1.5, -1.5], [1.5, 1.5, 1.5]]


def _blob(p, c, r, peak=100.0, sharp=40.0):
    return peak / (1.0 + np.exp(-(r - np.linalg.norm(p - np.asarray(c), axis=1)) * sharp))


def analytic_density(p: np.ndarray) -> np.ndarray:
    """A lego-sized compound object (a body, a cab, four wheels, an arm) plus a few floaters."""
    d = np.zeros(len(p))
    # body: a rounded box
    q = np.abs(p - [0.0, 0.0, -0.2]) - [0.7, 0.45, 0.2]
    box = np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(1), 0) - 0.05
    d += 100.0 / (1 + np.exp(box * 40))
    d += _blob(p, (-0.2, 0, 0.25), 0.3)
    for x in (-0.5, 0.5):
        for y in (-0.5, 0.5):
            d += _blob(p, (x, y, -0.45), 0.2)
    for t in np.linspace(0, 1, 8):
        d += _blob(p, (0.4 + 0.5 * t, 0.0, 0.1 + 0.4 * t), 0.09)
    for c in ((1.2, 1.1, 1.0), (-1.0, 1.2, -1.1), (0.9, -1.2, 1.2)):
        d += _blob(p, c, 0.05)
    return d


def machine() -> str:
    import os

    cpu = platform.processor() or platform.machine()
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{cpu}, {os.cpu_count()} cores, no GPU"


def extracted_mesh(resolution: int = 128):
    from blender_nerf_deform.engine.geometry.extract import extract_mesh

    return extract_mesh(analytic_density, BOUNDS, resolution=resolution)


def timed(fn, repeat: int = 3):
    """(best seconds, result of the last call)."""
    best, out = float("inf"), None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out
