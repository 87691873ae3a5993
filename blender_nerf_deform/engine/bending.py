"""Ray bending: render a NeRF through a deformed cage (DESIGN.md: "bend + render").

Every ray sample in deformed space is decided on its own (not per grid cell):

- inside a deformed tet: mapped to rest space by that tet's affine
  T_rest · T_deformed⁻¹ and the NeRF is queried there; its view direction is
  turned by the rotation of that affine (polar decomposition), so
  view-dependent colour follows the surface (switch: `rotate_directions`);
- outside the deformed cage but inside the rest cage: empty (density 0), so
  space an edit vacates shows the background, not a ghost of the original;
- outside both: unchanged (the rest of the scene stays where it was).

Degenerate deformed tets (zero volume, no inverse) map everything to their rest
centroid instead of producing inf/NaN; inverted tets keep their (orientation
reversing) affine. A point where inverted tets overlap is taken by the one the
locator finds first, deterministically. Both are counted in `inversion`.

Empty-space skipping after deformation: `occupancy` is a grid over the
deformed scene's bounds whose cells are marked by sending a few points per cell
through the same per-sample map into the NeRF's own occupancy grid, dilated by
one cell so thin occupied regions are not missed.
"""

from __future__ import annotations

import numpy as np
import torch

from .barycentric import deformed_to_rest_affines, inversion_report
from .occupancy import OccupancyGrid
from .point_location import TetLocator


def polar_rotations(linear: np.ndarray) -> np.ndarray:
    """(M,3,3) rotation part R of each A = R S (polar decomposition), det R = +1 even for inverted tets."""
    u, _s, vt = np.linalg.svd(linear)
    d = np.sign(np.linalg.det(u @ vt))
    u[:, :, 2] *= d[:, None]
    return u @ vt


class CageBend:
    """The deformed→rest map of one cage pose, as a `sample_transform` and an occupancy for the renderer."""

    def __init__(self, model, rest_vertices, tets, *, rotate_directions: bool = True, occupancy_resolution: int = 96):
        self.model = model
        self.device = model.device
        self.rest_vertices = np.asarray(rest_vertices, dtype=np.float64)
        self.tets = np.asarray(tets, dtype=np.int64)
        self.rest = TetLocator(self.rest_vertices, self.tets, device=self.device)
        self.rotate_directions = rotate_directions
        self.occupancy_resolution = occupancy_resolution
        self.deformed: TetLocator | None = None

    def set_deformed(self, deformed_vertices) -> "CageBend":
        """Prepare the map for one pose (same vertex order and tets as the rest cage)."""
        deformed = np.asarray(deformed_vertices, dtype=np.float64)
        self.inversion = inversion_report(self.rest_vertices, deformed, self.tets)
        affine = deformed_to_rest_affines(self.rest_vertices, deformed, self.tets)
        bad = np.unique(np.r_[self.inversion.degenerate, np.flatnonzero(~np.isfinite(affine).all(axis=(1, 2)))])
        if len(bad):
            affine[bad] = 0.0
            affine[bad, :3, 3] = self.rest_vertices[self.tets[bad]].mean(axis=1)
            affine[bad, 3, 3] = 1.0
        rotation = polar_rotations(affine[:, :3, :3])
        rotation[bad] = np.eye(3)
        f32 = dict(dtype=torch.float32, device=self.device)
        self.linear = torch.as_tensor(affine[:, :3, :3], **f32)
        self.offset = torch.as_tensor(affine[:, :3, 3], **f32)
        self.rotation = torch.as_tensor(rotation, **f32)
        # A flat tet holds no volume: locate among the others, and map their indices back.
        located = np.setdiff1d(np.arange(len(self.tets)), bad)
        self.deformed = TetLocator(deformed, self.tets[located], device=self.device)
        self.located_tets = torch.as_tensor(located, dtype=torch.int64, device=self.device)
        self.deformed_bounds = np.stack([deformed.min(0), deformed.max(0)])
        self.occupancy = self._deformed_occupancy()
        return self

    @torch.no_grad()
    def sample_transform(self, positions: torch.Tensor, dirs: torch.Tensor):
        """Renderer hook: (positions, dirs) in deformed space → (rest positions, rest dirs, keep)."""
        tet = self.deformed.locate(positions).to(positions.device)
        inside = tet >= 0
        p, d = positions.clone(), dirs.clone()
        t = self.located_tets[tet[inside]]
        p[inside] = torch.einsum("nij,nj->ni", self.linear[t], positions[inside]) + self.offset[t]
        if self.rotate_directions:
            d[inside] = torch.einsum("nij,nj->ni", self.rotation[t], dirs[inside])
        keep = inside.clone()
        outside = torch.nonzero(~inside).squeeze(1)
        if len(outside):
            keep[outside] = ~self.rest.contains(positions[outside]).to(positions.device)
        # As in an undeformed render, the NeRF is empty wherever its own occupancy grid says so.
        keep &= self.model.occupancy.occupied(p)
        return p, d, keep

    def _deformed_occupancy(self) -> OccupancyGrid:
        model_box = self.model.aabb.detach().cpu().numpy().reshape(2, 3)
        lo = np.minimum(model_box[0], self.deformed_bounds[0])
        hi = np.maximum(model_box[1], self.deformed_bounds[1])
        r = self.occupancy_resolution
        cell = (hi - lo) / r
        # Cells in OccupancyGrid's flat order (x fastest), probed at their 2x2x2 quarter points.
        z, y, x = np.meshgrid(np.arange(r), np.arange(r), np.arange(r), indexing="ij")
        idx = np.stack([x, y, z], -1).reshape(-1, 3)
        sub = np.array([[a, b, c] for c in (0.25, 0.75) for b in (0.25, 0.75) for a in (0.25, 0.75)])
        occupied = np.zeros(r**3, dtype=bool)
        dirs = torch.zeros(1, 3, device=self.device).expand(len(idx), 3)
        for s in sub:
            pts = torch.as_tensor(lo + (idx + s) * cell, dtype=torch.float32, device=self.device)
            _p, _d, keep = self.sample_transform(pts, dirs)  # keep: mapped into an occupied rest cell
            occupied |= keep.cpu().numpy()
        grid = occupied.reshape(r, r, r)  # [z, y, x]
        dilated = grid.copy()
        for axis in range(3):
            for shift in (-1, 1):
                dilated |= np.roll(grid, shift, axis=axis) & _valid_roll(r, axis, shift)
        box = torch.as_tensor(np.stack([lo, hi]), dtype=torch.float32, device=self.device)
        return OccupancyGrid.from_mask(box, torch.as_tensor(dilated, device=self.device))


def _valid_roll(r: int, axis: int, shift: int) -> np.ndarray:
    """Mask that drops the wrapped-around slice of np.roll."""
    valid = np.ones((r, r, r), dtype=bool)
    index = [slice(None)] * 3
    index[axis] = 0 if shift > 0 else r - 1
    valid[tuple(index)] = False
    return valid
