"""Cameras (pure numpy, no torch: the add-on may import this module).

`Camera`: camera-to-world 4x4 in the Blender/OpenGL convention (the camera looks
down its local -Z, +Y up; for Blender cameras it is `matrix_world`), focal
lengths and principal point in pixels, image size, and optionally its lens
`Distortion` (the models and the rays through distorted pixels: lens.py). A
pinhole's pixel (i, j) (column i, row j from the top) looks along
((i + 0.5 - cx)/fx, -(j + 0.5 - cy)/fy, -1) in camera space: rays through pixel
centres, as Blender renders them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

LENS_MODELS = ("opencv", "fisheye")


@dataclass(frozen=True)
class Distortion:
    """OpenCV's lens models: "opencv" (radial-tangential k1 k2 k3, p1 p2) or "fisheye" (k1-k4)."""

    model: str = "opencv"
    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    k4: float = 0.0  # fisheye only
    p1: float = 0.0  # radial-tangential only
    p2: float = 0.0

    def __post_init__(self):
        if self.model not in LENS_MODELS:
            raise ValueError(f"unknown lens model {self.model!r}: one of {', '.join(LENS_MODELS)}")

    @property
    def is_identity(self) -> bool:
        return not any((self.k1, self.k2, self.k3, self.k4, self.p1, self.p2))

    def as_dict(self) -> dict:
        return {
            "model": self.model,
            "k1": self.k1,
            "k2": self.k2,
            "k3": self.k3,
            "k4": self.k4,
            "p1": self.p1,
            "p2": self.p2,
        }


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
    distortion: Distortion | None = None  # None: a pinhole (Blender's cameras, NeRF-synthetic data)

    @classmethod
    def from_fov(cls, c2w, width: int, height: int, camera_angle_x: float, name: str = "") -> Camera:
        """NeRF-synthetic camera: square pixels, focal from the horizontal field of view, centred."""
        f = 0.5 * width / math.tan(0.5 * camera_angle_x)
        return cls(np.asarray(c2w, dtype=np.float64), f, f, width / 2.0, height / 2.0, int(width), int(height), name)

    @classmethod
    def looking_at_box(
        cls, aabb, width: int, height: int, direction=(0.65, -0.61, 0.44), fov_deg: float = 40.0, name: str = "box view"
    ) -> Camera:
        """A camera looking at the centre of a box ((2,3): low, high corners) from `direction` (by default
        where Blender's default camera stands: front right, above), Z up, just far enough that the
        box's bounding sphere fills the shorter image side of a `fov_deg` view."""
        lo, hi = np.asarray(aabb, dtype=np.float64).reshape(2, 3)
        centre, radius = (lo + hi) / 2, max(float(np.linalg.norm(hi - lo)) / 2, 1e-6)
        half = math.radians(fov_deg) / 2
        back = np.asarray(direction, dtype=np.float64)
        back = back / np.linalg.norm(back)
        right = np.cross((0.0, 0.0, 1.0), back)
        right = right / np.linalg.norm(right)
        c2w = np.eye(4)
        c2w[:3, 0], c2w[:3, 1], c2w[:3, 2] = right, np.cross(back, right), back
        c2w[:3, 3] = centre + back * radius / math.sin(half)
        f = 0.5 * min(width, height) / math.tan(half)
        return cls(c2w, f, f, width / 2.0, height / 2.0, int(width), int(height), name)
