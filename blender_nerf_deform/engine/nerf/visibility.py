"""What the training cameras see: how many of them frame each point, and the occupancy cells seen by enough.

A capture shot all around a subject leaves space that only one or two photos see: the cone right in
front of each camera above all. A NeRF can explain those photos with density hanging there (the
photo pays for it, no other does), and a view between the training cameras then looks through it:
grey floaters in front of the subject. Nerfbusters culls what no training view sees; cells framed by
fewer than `min_views` training cameras are never occupied here, so the field cannot put density where
too few photos would pay for it. A pinhole test per camera (the lens's distortion is within the margin
of whole cells), no occlusion: what a camera frames, not what it sees of it.
"""

from __future__ import annotations

import numpy as np
import torch

from .occupancy import OccupancyGrid


def views_framing(points: torch.Tensor, cameras: list, near: float = 0.0, chunk: int = 1 << 18) -> torch.Tensor:
    """(N,) int32: how many of `cameras` frame each world point (N, 3): in front of the camera beyond `near`
    and inside its image."""
    dev = points.device
    c2w = torch.tensor(np.stack([c.c2w[:3, :4] for c in cameras]), dtype=torch.float32, device=dev)
    rot_t = c2w[:, :3, :3].transpose(1, 2).contiguous()  # world -> camera
    origin = c2w[:, :3, 3]
    intr = torch.tensor([[c.fx, c.fy, c.cx, c.cy, c.width, c.height] for c in cameras], dtype=torch.float32, device=dev)
    counts = torch.zeros(points.shape[0], dtype=torch.int32, device=dev)
    for s in range(0, points.shape[0], chunk):
        p = points[s: s + chunk]
        for k in range(len(cameras)):
            q = (p - origin[k]) @ rot_t[k].T  # camera space: looking down -Z, +Y up
            z = -q[:, 2]
            fx, fy, cx, cy, w, h = intr[k].unbind()
            zs = z.clamp_min(1e-9)
            i = fx * q[:, 0] / zs + cx
            j = -fy * q[:, 1] / zs + cy
            counts[s: s + chunk] += ((z > near) & (i >= 0) & (i <= w) & (j >= 0) & (j <= h)).int()
    return counts


def framed_cells(grid: OccupancyGrid, cameras: list, min_views: int, near: float = 0.0) -> torch.Tensor:
    """Flat bool (resolution^3,): the grid's cells whose centre at least `min_views` of `cameras` frame."""
    idx = torch.arange(grid.resolution**3, device=grid.mask.device)
    centres = grid.cell_centers(idx, jitter=False)
    return views_framing(centres, cameras, near) >= min_views
