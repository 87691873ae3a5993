"""Compile the geometry stage's CPU kernels ahead of time (`compile` command, Set Up Worker).

As nerf/warmup.py: a tiny cage (a 3x3x3 lattice of vertices, 48 tets) posed by the ARAP that the
product solves (surface_arap.SurfaceArap, what a handle pose runs, with its barrier active; its elements
energy runs every kernel of arap_kernels.py) and its points located, runs each kernel with the
argument types real cages pass. The reference deform.ArapDeformer shares those kernels and argument
types; it serves the tests and benchmarks and is not run here.
"""

from __future__ import annotations

import numpy as np

from .embedding import embed_points
from .locate import TetLocator
from .surface_arap import SurfaceArap

# The six tets of a unit cube sharing its diagonal 0-7 (corner k at bits x=1, y=2, z=4): a conforming
# split when every cube of a lattice uses it.
_CUBE_TETS = np.array([[0, 1, 3, 7], [0, 3, 2, 7], [0, 2, 6, 7], [0, 6, 4, 7], [0, 4, 5, 7], [0, 5, 1, 7]])


def lattice_cage(lo, hi, n: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (n^3, 3), tets (6 (n-1)^3, 4), positively oriented) filling the box lo..hi."""
    axes = [np.linspace(a, b, n) for a, b in zip(lo, hi)]
    gx, gy, gz = np.meshgrid(*axes, indexing="ij")
    vertices = np.stack([gx, gy, gz], axis=-1).reshape(-1, 3)
    idx = np.arange(n**3).reshape(n, n, n)
    tets = []
    for i in range(n - 1):
        for j in range(n - 1):
            for k in range(n - 1):
                corner = [idx[i + (c & 1), j + (c >> 1 & 1), k + (c >> 2 & 1)] for c in range(8)]
                tets.extend([[corner[c] for c in t] for t in _CUBE_TETS])
    tets = np.array(tets, dtype=np.int64)
    e = vertices[tets[:, 1:]] - vertices[tets[:, :1]]
    flip = np.linalg.det(e) < 0
    tets[flip] = tets[flip][:, [0, 2, 1, 3]]
    return vertices, tets


def bent_pose(vertices: np.ndarray, angle: float = 0.3) -> np.ndarray:
    """The lattice twisted about z, more towards its top: a pose every tet of which moves."""
    z = (vertices[:, 2] - vertices[:, 2].min()) / max(np.ptp(vertices[:, 2]), 1e-9)
    a = angle * z
    c, s = np.cos(a), np.sin(a)
    out = vertices.copy()
    out[:, 0], out[:, 1] = c * vertices[:, 0] - s * vertices[:, 1], s * vertices[:, 0] + c * vertices[:, 1]
    return out


def compile_kernels() -> None:
    vertices, tets = lattice_cage((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
    # A strong twist of the top layer, so the surface ARAP's barrier acts too.
    twist = np.eye(4)
    twist[:2, :2] = [[np.cos(2.5), -np.sin(2.5)], [np.sin(2.5), np.cos(2.5)]]
    surface = 0.9 * vertices[np.abs(vertices).max(axis=1) > 0.9]  # points on a box inside the cage
    SurfaceArap(
        vertices,
        tets,
        embed_points(surface, vertices, tets),
        [np.flatnonzero(surface[:, 2] > 0.5)],
        np.flatnonzero(surface[:, 2] < -0.5),
    ).solve([twist], max_iter=5)
    points = np.random.default_rng(0).uniform(-1.2, 1.2, (256, 3))
    TetLocator(bent_pose(vertices), tets).locate(points, return_barycentric=True)
