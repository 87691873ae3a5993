"""Which training photos pay for the density of each occupancy cell, and the cells too few of them pay for.

A capture shot all around a subject leaves space that one photo alone looks through: the cone right in
front of each camera above all, hidden behind the subject from the far side. A NeRF can explain that
photo with density hanging there (that photo pays for it, no other does), and a view between the
training cameras then looks through it: grey floaters in front of the subject. Counting the cameras
whose frustum holds a cell (Nerfbusters' visibility) misses them, since the cameras across the room
frame that space too, behind the subject; what matters is which photos' rays reach a cell while they
still see through (transmittance above one half: what is there shows in the photo, so the photo pays).

`ViewCounts` keeps per cell the set of such photos (bit photo % 64 of an int64: photos beyond 64 share
bits, so a count errs low) and how many training samples looked through it. A cell that enough samples
have reached (`MIN_SAMPLES`, so that a cell many photos see is not judged on its first rays) from fewer
than `min_views` photos is never occupied again; a cell no sample reached is left as it is.
"""

from __future__ import annotations

import torch

from .occupancy import OccupancyGrid

MIN_SAMPLES = 32  # samples that reached a cell before its photos are counted
_BITS = 64
_POPCOUNT = torch.tensor([bin(b).count("1") for b in range(256)], dtype=torch.int16)


def exclusive_weight(w: torch.Tensor, ray_idx: torch.Tensor) -> torch.Tensor:
    """Per sample (sorted by ray then t), the weight of its ray's samples before it: 1 - its transmittance."""
    total = torch.cumsum(w, 0)
    before = total - w
    first = torch.ones_like(ray_idx, dtype=torch.bool)
    first[1:] = ray_idx[1:] != ray_idx[:-1]
    start = torch.cummax(torch.where(first, torch.arange(len(w), device=w.device), 0), 0).values
    return before - before[start]


class ViewCounts:
    """Per cell of `grid`: the training photos whose rays reached it seeing through, and how many samples did."""

    def __init__(self, grid: OccupancyGrid):
        self.grid = grid
        n = grid.resolution**3
        self.photos = torch.zeros(n, dtype=torch.int64, device=grid.mask.device)
        self.samples = torch.zeros(n, dtype=torch.int32, device=grid.mask.device)

    @torch.no_grad()
    def record(self, points: torch.Tensor, photo: torch.Tensor) -> None:
        """Samples at world `points` (S, 3) of rays from training photos `photo` (S,) that still saw through."""
        cells, inside = self.grid.cell_index(points)
        cells, photo = cells[inside], photo[inside]
        if not cells.numel():
            return
        self.samples.index_add_(0, cells, torch.ones_like(cells, dtype=torch.int32))
        pairs = torch.unique(cells * _BITS + photo % _BITS)
        cells, flag = pairs // _BITS, torch.bitwise_left_shift(torch.ones_like(pairs), pairs % _BITS)
        new = (self.photos[cells] & flag) == 0  # the pairs are unique: adding a new bit is OR-ing it in
        self.photos.index_add_(0, cells[new], flag[new])

    def views(self) -> torch.Tensor:
        """(cells,) int: how many photos (modulo the shared bits) reached each cell seeing through."""
        return _POPCOUNT.to(self.photos.device)[self.photos.view(torch.uint8).long()].reshape(-1, 8).sum(dim=1)

    def paid_for(self, min_views: int) -> torch.Tensor:
        """Flat bool: the cells that may stay occupied (not looked through by enough samples of too few photos)."""
        return (self.samples < MIN_SAMPLES) | (self.views() >= min_views)


def record_seen(counts: list, samples: tuple, origins: torch.Tensor, dirs: torch.Tensor, photo: torch.Tensor) -> None:
    """Fold a training step's composited samples (ray index, t, dt, weight; sorted by ray then t) into `counts`."""
    ray_idx, t, _, w = samples
    with torch.no_grad():
        front = exclusive_weight(w.detach(), ray_idx) < 0.5
        r, t = ray_idx[front], t[front].detach()
        points = origins[r] + dirs[r] * t[:, None]
        for c in counts:
            c.record(points, photo[r])
