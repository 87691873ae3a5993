"""Which training photos pay for the density of each occupancy cell, and the free space too few of them pay for.

A capture shot all around a subject leaves space that one or two photos alone look through: the cone
right in front of each camera, and the space near the camera ring that the cameras across the room
frame only behind the subject. A NeRF can explain those photos with density hanging there (they pay
for it, no other photo does: view-dependent colour hides it from the rest), and a view between the
training cameras then looks through it: grey floaters in front of the subject. Counting the cameras
whose frustum holds a cell (Nerfbusters' visibility) misses them, since the cameras across the room
frame that space too, behind the subject. What counts is which photos see *through* a cell: a cell is
seen through by a photo when it lies in the photo's frustum no deeper than the photo's depth there
(what the NeRF shows that photo, at low resolution; a cell's width of margin keeps the surface's own
cells). A cell seen through by at least one photo but fewer than `min_views` is ruled out. A cell no
photo sees through (an object's inside, space behind everything) is left as it is: ruling it out would
hollow solid objects and give extraction a double surface.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np
import torch

from .camera import Camera
from .occupancy import OccupancyGrid
from .renderer import render_image

DEPTH_DOWNSCALE = 4  # the photos' depth is rendered at this fraction of their size


def small_camera(camera: Camera, downscale: int) -> Camera:
    """The pinhole of `camera` at 1/downscale of its size (the lens's distortion is within a pixel's margin there)."""
    return dataclasses.replace(
        camera,
        fx=camera.fx / downscale,
        fy=camera.fy / downscale,
        cx=camera.cx / downscale,
        cy=camera.cy / downscale,
        width=max(1, camera.width // downscale),
        height=max(1, camera.height // downscale),
        distortion=None,
    )


def model_depth(model, camera: Camera) -> torch.Tensor:
    """(H, W) distance along each pixel's ray to what `model` shows `camera` (inf where the ray escapes)."""
    was = model.training
    model.eval()
    try:
        out = render_image(model, camera)
    finally:
        model.train(was)
    depth = torch.from_numpy(out["depth"]).to(model.device)
    return torch.where(
        torch.from_numpy(out["rgba"][..., 3]).to(model.device) > 0.5, depth, torch.full_like(depth, float("inf"))
    )


@torch.no_grad()
def photos_seeing_through(
    grid: OccupancyGrid,
    cameras: list,
    depth_of: Callable[[Camera], torch.Tensor],
    downscale: int = DEPTH_DOWNSCALE,
    chunk: int = 1 << 20,
) -> torch.Tensor:
    """(cells,) int32: for each cell of `grid`, how many of `cameras` see through it (module docstring), given
    `depth_of(camera)`, the (H, W) depth a camera sees (`model_depth` of the NeRF being trained)."""
    dev = grid.mask.device
    n = grid.resolution**3
    margin = float(grid.cell_size.norm())
    counts = torch.zeros(n, dtype=torch.int32, device=dev)
    for cam in cameras:
        small = small_camera(cam, downscale)
        depth = depth_of(small).reshape(-1)
        rot = torch.tensor(np.asarray(small.c2w)[:3, :3], dtype=torch.float32, device=dev)
        origin = torch.tensor(np.asarray(small.c2w)[:3, 3], dtype=torch.float32, device=dev)
        for s in range(0, n, chunk):
            centres = grid.cell_centers(torch.arange(s, min(n, s + chunk), device=dev), jitter=False)
            q = (centres - origin) @ rot  # camera space: looking down -Z, +Y up
            z = -q[:, 2]
            zs = z.clamp_min(1e-9)
            i = torch.floor(small.fx * q[:, 0] / zs + small.cx)
            j = torch.floor(-small.fy * q[:, 1] / zs + small.cy)
            framed = (z > 0) & (i >= 0) & (i < small.width) & (j >= 0) & (j < small.height)
            pixel = (j.clamp(0, small.height - 1) * small.width + i.clamp(0, small.width - 1)).long()
            distance = (centres - origin).norm(dim=-1)
            counts[s : s + chunk] += (framed & (distance <= depth[pixel] + margin)).int()
    return counts


def paid_for(counts: torch.Tensor, min_views: int) -> torch.Tensor:
    """Flat bool: the cells that may stay occupied: seen through by no photo, or by at least `min_views`."""
    return (counts == 0) | (counts >= min_views)
