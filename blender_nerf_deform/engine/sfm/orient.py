"""Put a reconstruction upright, centred and at a NeRF-friendly size, as instant-ngp's colmap2nerf does.

Structure from motion recovers cameras up to a similarity (any rotation, offset and
scale). For a dataset in Blender's frame (Z up) the cameras' mean up vector becomes +Z;
the origin goes to the point the optical axes pass closest to (what the capture looks
at; for a forward-facing capture, whose axes barely cross, the median of the sparse
points instead); and the scale puts the cameras 4 units from it on average, as the
NeRF-synthetic scenes are. Returns the 4x4 similarity applied, so that points (and the
sparse cloud) can follow.
"""

from __future__ import annotations

import numpy as np


def _rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The rotation taking unit vector a to unit vector b (Rodrigues)."""
    v, c = np.cross(a, b), float(np.dot(a, b))
    if np.linalg.norm(v) < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])  # opposite: half a turn about x
    k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + k + k @ k * (1.0 / (1.0 + c))


def axes_focus(origins: np.ndarray, directions: np.ndarray) -> np.ndarray | None:
    """The point nearest to all the lines (origin, direction), or None if they are nearly parallel."""
    d = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    P = np.eye(3)[None] - d[:, :, None] * d[:, None, :]  # projectors onto each line's normal plane
    A, b = P.sum(0), np.einsum("nij,nj->i", P, origins)
    if np.linalg.cond(A) > 1e4:
        return None
    return np.linalg.solve(A, b)


def orientation(c2ws: np.ndarray, points: np.ndarray | None = None, camera_distance: float = 4.0) -> np.ndarray:
    """The similarity (4x4: scale s, rotation R, translation t) to apply to world points."""
    up = c2ws[:, :3, 1].mean(0)
    R = _rotation_between(up / np.linalg.norm(up), np.array([0.0, 0.0, 1.0]))
    origins = c2ws[:, :3, 3] @ R.T
    forward = -c2ws[:, :3, 2] @ R.T
    focus = axes_focus(origins, forward)
    if focus is None:
        focus = np.median(points @ R.T, axis=0) if points is not None and len(points) else origins.mean(0)
    spread = float(np.linalg.norm(origins - focus, axis=1).mean())
    s = camera_distance / spread if spread > 0 else 1.0
    T = np.eye(4)
    T[:3, :3] = s * R
    T[:3, 3] = -s * focus
    return T


def apply_to_cameras(T: np.ndarray, c2ws: np.ndarray) -> np.ndarray:
    """Camera-to-world matrices moved by the similarity T, their rotations kept orthonormal."""
    s = float(np.cbrt(np.linalg.det(T[:3, :3])))
    out = c2ws.copy()
    out[:, :3, :3] = (T[:3, :3] / s) @ c2ws[:, :3, :3]
    out[:, :3, 3] = c2ws[:, :3, 3] @ T[:3, :3].T + T[:3, 3]
    return out
