"""Pinhole cameras (pure numpy, no torch: the add-on may import this module).

`Camera`: camera-to-world 4x4 in the Blender/OpenGL convention (the camera looks
down its local -Z, +Y up; for Blender cameras it is `matrix_world`), focal
lengths and principal point in pixels, image size. Pixel (i, j) (column i, row j
from the top) looks along ((i + 0.5 - cx)/fx, -(j + 0.5 - cy)/fy, -1) in camera
space: rays through pixel centres, as Blender renders them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass
class Camera:
    """A pinhole camera. c2w: camera-to-world 4x4 (Blender's matrix_world for Blender cameras)."""

    c2w: np.ndarray
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    name: str = ""

    @classmethod
    def from_fov(cls, c2w, width: int, height: int, camera_angle_x: float, name: str = "") -> "Camera":
        """NeRF-synthetic camera: square pixels, focal from the horizontal field of view, centred."""
        f = 0.5 * width / math.tan(0.5 * camera_angle_x)
        return cls(np.asarray(c2w, dtype=np.float64), f, f, width / 2.0, height / 2.0, int(width), int(height), name)
