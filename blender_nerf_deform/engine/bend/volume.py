"""The NeRF as posed, sampled on a voxel grid: what `bake-volume` and the worker's `bake_volume` op run.

The lattice and the .npz file are baked_volume.py's (pure numpy). The add-on
writes the result as OpenVDB with the module Blender ships (the engine has no
OpenVDB), so Cycles and EEVEE render the edited NeRF as a native
emission-absorption volume. One grid per frame:

- The lattice: cubic voxels over an oriented box (the NeRF's box, the posed
  cage's box, or an edit region; the grid's axes follow the box),
  `resolution` voxels along its longest side. `index_to_nerf` maps a voxel's
  index (i, j, k) to its centre in the NeRF's frame (OpenVDB's convention:
  voxel centres at integer index coordinates).
- Density: per unit length of the NeRF's frame, as the renderer integrates it.
  A voxel holds the mean over `supersample`^3 points spread over it (a box
  filter): a thin shell keeps its optical depth on a coarse grid, where a point
  at the centre would miss it or count it whole. Posed: the rest density at each
  point's rest position times the tet's |det A|^(1/3) (`CageBend.map_points`).
- Colour: a volume emits alike in every direction, a NeRF's colour depends on
  the view. Each point's colour is the NeRF's as seen head-on from outside:
  looking against the density's gradient (central differences on the baked
  density), turned into rest space with the tet; where the density is flat
  (inside a solid) the mean over the 12 directions of an icosahedron (a
  spherical 5-design). Compared with a camera's own view direction (Cycles
  against the NeRF Deform engine), head-on is as close as the cosine-weighted
  mean over the outward hemisphere and closer than the mean over all
  directions (directions never photographed, from inside the object, pull it
  off); it is also one colour evaluation per point instead of twelve. sRGB, as the NeRF learnt it; the
  density-weighted mean over the voxel's points. Voxels next to dense ones get
  their neighbours' colour, so that a renderer's trilinear lookup at a surface
  does not blend in black.
- Empty: where the NeRF's occupancy grid is (the renderer skips the same
  space), space a pose vacates, and an unbounded NeRF's background outside its
  inner box (not baked).

The result is sparse: the indices and values of the voxels that hold anything.
"""

from __future__ import annotations

import math
import time

import numpy as np
import torch

from ..errors import EngineError
from ..geometry.region import EditRegion, check_region_in_box
from ..nerf.renderer import blocked_color, blocked_density  # the renderer's own field evaluation, block by block
from .baked_volume import BakedVolume, VolumeGrid, box_of_bounds, check_volume_memory

POINTS_PER_BATCH = 1 << 18  # sample points evaluated at once (bounded memory whatever the grid)

_PHI = (1.0 + math.sqrt(5.0)) / 2.0
VIEW_DIRECTIONS = np.array(
    [[0, s1, s2 * _PHI] for s1 in (-1, 1) for s2 in (-1, 1)]
    + [[s1, s2 * _PHI, 0] for s1 in (-1, 1) for s2 in (-1, 1)]
    + [[s2 * _PHI, 0, s1] for s1 in (-1, 1) for s2 in (-1, 1)],
    dtype=np.float64,
)
VIEW_DIRECTIONS /= np.linalg.norm(VIEW_DIRECTIONS, axis=1, keepdims=True)


def _sub_offsets(supersample: int) -> np.ndarray:
    """(s^3, 3) offsets of a voxel's sample points from its centre, in voxels: a regular s x s x s lattice."""
    a = (np.arange(supersample) + 0.5) / supersample - 0.5
    return np.stack(np.meshgrid(a, a, a, indexing="ij"), -1).reshape(-1, 3)


@torch.no_grad()
def bake_volume(model, grid: VolumeGrid, bend=None, supersample: int = 1, progress=None) -> BakedVolume:
    """The NeRF (ray-bent by `bend`, a posed `CageBend`, when given) sampled on `grid`.

    Two passes: the density of every voxel, then the colour of the voxels that hold any, seen
    from outside (the density's gradient says where outside is). `progress(done, total)` is called
    between batches (it may raise to cancel: nothing is kept)."""
    if isinstance(supersample, bool) or not isinstance(supersample, (int, np.integer)) or not 1 <= supersample <= 8:
        raise EngineError(
            f"supersample must be a whole number from 1 to 8 (points per voxel along each axis), got {supersample!r}"
        )
    check_volume_memory(grid)
    start = time.perf_counter()
    sampler = _VoxelSampler(model, grid, bend, supersample)
    nx, ny, nz = grid.shape
    density = np.zeros(grid.shape, dtype=np.float32)
    # Slabs of whole k-layers, about POINTS_PER_BATCH points each; what the renderer skips is skipped.
    layers = max(1, POINTS_PER_BATCH // max(1, nx * ny * sampler.n_sub))
    work = nz + max(1, nz // 2)  # the colour pass, counted as half the density pass
    for k0 in range(0, nz, layers):
        k1 = min(nz, k0 + layers)
        ii, jj, kk = np.meshgrid(np.arange(nx), np.arange(ny), np.arange(k0, k1), indexing="ij")
        voxels = np.stack([ii, jj, kk], -1).reshape(-1, 3)
        sigma, _geo, _rot, owner = sampler.sample(voxels, skip_empty=True)
        slab = torch.zeros(len(voxels), dtype=torch.float32).index_add_(0, owner, sigma.cpu()) / sampler.n_sub
        density[:, :, k0:k1] = slab.reshape(nx, ny, k1 - k0).numpy()
        if progress is not None:
            progress(k1, work)

    filled = density > 0
    index = np.argwhere(filled)
    normals = _outward_normals(density, index, grid)
    color = np.zeros((len(index), 3), dtype=np.float32)
    per_batch = max(1, POINTS_PER_BATCH // (sampler.n_sub * len(VIEW_DIRECTIONS)) * 4)
    for s in range(0, len(index), per_batch):
        voxels = index[s : s + per_batch]
        sigma, geo, rotation, owner = sampler.sample(voxels, skip_empty=False)
        rgb = _seen_color(model, geo, rotation, torch.as_tensor(normals[s : s + per_batch])[owner])
        summed = torch.zeros(len(voxels), 3).index_add_(0, owner, (rgb * sigma[:, None]).cpu())
        weight = torch.zeros(len(voxels)).index_add_(0, owner, sigma.cpu())
        color[s : s + per_batch] = (summed / weight.clamp_min(1e-30)[:, None]).clamp(0, 1).numpy()
        if progress is not None:
            progress(nz + (s + len(voxels)) * max(1, nz // 2) // max(1, len(index)), work)

    dense_color = np.zeros(grid.shape + (3,), dtype=np.float32)
    dense_color[tuple(index.T)] = color
    shell = _shell_colors(dense_color, filled)
    del dense_color
    shell_index = np.argwhere(shell.any(axis=-1))
    all_index = np.concatenate([index, shell_index]).astype(np.int32)
    all_density = np.concatenate([density[tuple(index.T)], np.zeros(len(shell_index), np.float32)])
    all_color = np.concatenate([color, shell[tuple(shell_index.T)]]).astype(np.float32)
    stats = {
        "seconds": time.perf_counter() - start,
        "points": sampler.n_points,
        "colored_points": sampler.n_colored,
        "voxels": grid.n_voxels,
        "dense_voxels": len(index),
        "active_voxels": len(all_index),
    }
    return BakedVolume(grid, all_index, all_density, all_color, stats)


class _VoxelSampler:
    """The field at a voxel's points: density (scaled by the pose), geometry features, rotation."""

    def __init__(self, model, grid: VolumeGrid, bend, supersample: int):
        self.model, self.bend = model, bend
        self.device = model.device
        self.occupancy = bend.occupancy if bend is not None else model.occupancy
        self.offsets = torch.as_tensor(_sub_offsets(supersample), dtype=torch.float32, device=self.device)
        self.n_sub = len(self.offsets)
        self.matrix = torch.as_tensor(grid.index_to_nerf, dtype=torch.float32, device=self.device)
        self.n_points = self.n_colored = 0

    def sample(self, voxels: np.ndarray, skip_empty: bool):
        """(sigma (P,), geo (P, F), rotation (P, 3, 3), owner (P,): each point's row in `voxels`) of the
        points of `voxels` (V, 3) that hold density; with `skip_empty` those the occupancy grid marks
        empty are not evaluated (and have no geo)."""
        dev = self.device
        idx = (torch.as_tensor(voxels, dtype=torch.float32, device=dev)[:, None, :] + self.offsets[None]).reshape(-1, 3)
        pts = idx @ self.matrix[:3, :3].T + self.matrix[:3, 3]
        owner = torch.arange(len(voxels), device=dev).repeat_interleave(self.n_sub)
        self.n_points += len(pts)
        if skip_empty:
            live = torch.nonzero(self.occupancy.occupied(pts)).squeeze(1)
            pts, owner = pts[live], owner[live]
        if self.bend is not None:
            pts, keep, scale, rotation = self.bend.map_points(pts)
        else:
            keep = self.model.occupancy.occupied(pts)
            scale = torch.ones(len(pts), device=dev)
            rotation = torch.eye(3, device=dev).expand(len(pts), 3, 3)
        pts, scale, rotation, owner = pts[keep], scale[keep], rotation[keep], owner[keep]
        sigma, geo = blocked_density(self.model, pts) if len(pts) else (pts.new_zeros(0), None)
        sigma = sigma * scale
        dense = sigma > 0
        if not skip_empty:
            self.n_colored += int(dense.sum())
        return sigma[dense], (geo[dense] if geo is not None else None), rotation[dense], owner[dense].cpu()


def _outward_normals(density: np.ndarray, index: np.ndarray, grid: VolumeGrid) -> np.ndarray:
    """(N, 3) unit vectors, NeRF frame: where density falls at each voxel of `index` (central
    differences; zero where it is flat, inside a solid)."""
    n = len(index)
    grad = np.zeros((n, 3), dtype=np.float64)
    for axis in range(3):
        up, down = index.copy(), index.copy()
        up[:, axis] = np.minimum(up[:, axis] + 1, grid.shape[axis] - 1)
        down[:, axis] = np.maximum(down[:, axis] - 1, 0)
        grad[:, axis] = density[tuple(up.T)].astype(np.float64) - density[tuple(down.T)]
    # Index space to the NeRF frame (cubic voxels: the grid's rotation), pointing away from the density.
    rotation = grid.index_to_nerf[:3, :3] / grid.voxel_size
    outward = -grad @ rotation.T
    length = np.linalg.norm(outward, axis=1, keepdims=True)
    return np.where(length > 1e-12, outward / np.maximum(length, 1e-30), 0.0).astype(np.float32)


def _seen_color(model, geo: torch.Tensor, rotation: torch.Tensor, outward: torch.Tensor) -> torch.Tensor:
    """(N, 3): each point's colour as seen head-on from outside: looking along -`outward`; where
    `outward` is zero (inside a solid, no gradient) the mean over VIEW_DIRECTIONS. Directions turn
    into rest space by `rotation`."""
    head_on = outward.abs().sum(1) > 0
    out = geo.new_zeros(len(geo), 3)
    if head_on.any():
        d = torch.einsum("bij,bj->bi", rotation[head_on], -outward[head_on])
        out[head_on] = blocked_color(model, geo[head_on], d)
    if (~head_on).any():
        g, r = geo[~head_on], rotation[~head_on]
        dirs = torch.as_tensor(VIEW_DIRECTIONS, dtype=torch.float32, device=geo.device)
        k = len(dirs)
        rest_dirs = torch.einsum("bij,kj->bki", r, dirs).reshape(-1, 3)
        out[~head_on] = blocked_color(model, g.repeat_interleave(k, dim=0), rest_dirs).reshape(len(g), k, 3).mean(1)
    return out


def _shell_colors(color: np.ndarray, filled: np.ndarray) -> np.ndarray:
    """Colour for the empty voxels next to filled ones (26-neighbours): their filled neighbours' mean;
    zero elsewhere."""
    from scipy.ndimage import uniform_filter

    weight = uniform_filter(filled.astype(np.float32), size=3, mode="constant")
    shell = np.zeros_like(color)
    near = (weight > 0.01) & ~filled  # the filter leaves rounding residue; a true neighbour weighs >= 1/27
    if not near.any():
        return shell
    for c in range(3):
        summed = uniform_filter(color[..., c] * filled, size=3, mode="constant")
        shell[..., c] = np.where(near, summed / np.maximum(weight, 1e-12), 0.0)
    return shell


def bake_box(extent, model, cage_vertices=None) -> EditRegion:
    """The box a bake covers: "nerf" (the NeRF's box; an unbounded NeRF's inner box), "cage" (the box
    of `cage_vertices`, the cage as posed), or an EditRegion (an edit region, or any oriented box),
    checked to meet the NeRF's box."""
    bounds = model.aabb.detach().cpu().double().reshape(2, 3).numpy()
    if isinstance(extent, EditRegion):
        check_region_in_box(extent, bounds)
        return extent
    if extent == "nerf":
        return box_of_bounds(bounds)
    if extent == "cage":
        if cage_vertices is None:
            raise EngineError("the cage's box needs a cage: build one, or bake the NeRF's box or an edit region")
        v = np.asarray(cage_vertices, dtype=np.float64)
        return box_of_bounds(np.stack([v.min(0), v.max(0)]))
    raise EngineError(f"unknown extent {extent!r}: nerf, cage, or an edit region")
