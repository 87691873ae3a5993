"""Ray bending: render a NeRF through a deformed cage (docs/ARCHITECTURE.md: "bend + render").

Every ray sample in deformed space is decided on its own (not per grid cell):

- inside a deformed tet: mapped to rest space by that tet's affine
  T_rest · T_deformed⁻¹ and the NeRF is queried there; its view direction is
  turned by the rotation of that affine (polar decomposition), so
  view-dependent colour follows the surface (switch: `rotate_directions`);
- stretch and compression along the ray: each sample's density is
  scaled by |A d| (A: its tet's deformed→rest linear part, d the unit ray), the
  rest-space length of a unit step, so the NeRF's opacity is integrated over
  the rest-space path (a shell squashed across the ray stays as opaque; one
  stretched across it does not thicken; switch: `density_correction`; 1 exactly
  for an identity pose); with `refine_step` (off by default, see __init__), where
  a pose compresses the content by more than STEP_REFINE_FROM, frames march with
  a finer step (`render_kwargs`), so a squashed shell is not stepped over. Strong smooth stretches need a cage fine
  enough to follow them: `geometry.cage_refine.refine_cage` (`cage --refine-edge`);
- outside the deformed cage but inside the rest cage: empty (density 0), so
  space an edit vacates shows the background, not a ghost of the original;
- outside both: unchanged (the rest of the scene stays where it was).

Inverted and degenerate tets (the policy; `inversion` counts both per pose,
the CLI prints the counts per frame, the worker's render op returns them and
the add-on reports them):

- inverted (det F < 0): kept, with their orientation-reversing affine. Where a
  fold makes deformed tets overlap, a sample takes the first tet the locator
  finds (deterministic for a cage and pose). A sample in any tet, inverted or
  not, gets that tet's finite map and its rest content, so a fold shows the
  folded content: never NaN, never a hole. View directions turn by the proper rotation
  (det +1) of the polar decomposition.
- degenerate (|det F| <= 1e-6, no inverse): left out of point location (they
  hold no volume, so no sample needs them); their affine is replaced by the
  constant map to their rest centroid so every table stays finite.

Empty-space skipping after deformation: `occupancy` sends each occupied cell
of the NeRF's own grid forward through the cage (the box of its corners
mapped by the tets that hold them) onto a grid aligned with the NeRF's, so
an identity pose skips exactly as an undeformed render does and deformed
frames march about as many samples. Posing costs no point location: the
cells' corners are located in the rest cage once, at construction.

On CPU (numba) the per-sample map and the occupancy marking run as fused
kernels; elsewhere (CUDA) the same computation runs in torch, on the device.
"""

from __future__ import annotations

import numpy as np
import torch

from .. import backend
from ..errors import EngineError
from ..geometry.barycentric import (
    deformed_to_rest_affines,
    inversion_from_det,
    inversion_report,
    tet_inverses,
    tet_matrices,
)
from ..geometry.locate import TetLocator
from ..geometry.poses import check_coordinates
from ..nerf.occupancy import OccupancyGrid
from . import bend_kernels


def polar_rotations(linear: np.ndarray) -> np.ndarray:
    """(M,3,3) rotation part R of each A = R S (polar decomposition), det R = +1 even for inverted tets."""
    u, _s, vt = np.linalg.svd(linear)
    d = np.sign(np.linalg.det(u @ vt))
    u[:, :, 2] *= d[:, None]
    return u @ vt


_CORNERS = np.array([[k & 1, (k >> 1) & 1, k >> 2] for k in range(8)])

# Where a pose compresses the NeRF's content (a deformed step covers more than one rest step), frames
# march with a finer step: render_step / (the compression that STEP_REFINE_SHARE of the content's rest
# volume reaches or exceeds), once that exceeds STEP_REFINE_FROM, at most MAX_STEP_REFINE times finer.
# The step is the whole frame's, so a share and not the maximum: a bend's crease squashes a few tets
# strongly (the fold-free ARAP holds some near flat, on a small share of the content), and refining
# the whole frame for them made a bent frame much slower; a squash of the whole part still refines.
STEP_REFINE_FROM = 1.5
MAX_STEP_REFINE = 4.0
STEP_REFINE_SHARE = 0.1


class CageBend:
    """The deformed→rest map of one cage pose, as a `sample_transform` and an occupancy for the renderer.

    Built once per rest cage (its locator, and the NeRF's occupied cells located
    in it); `set_deformed(V)` once per pose.
    """

    def __init__(
        self,
        model,
        rest_vertices,
        tets,
        *,
        rotate_directions: bool = True,
        density_correction: bool = True,
        refine_step: bool = False,
        max_occupancy_resolution: int = 256,
    ):
        self.model = model
        self.device = model.device
        self.rest_vertices = np.asarray(rest_vertices, dtype=np.float64)
        self.tets = np.asarray(tets, dtype=np.int64)
        self.rest = TetLocator(self.rest_vertices, self.tets, device=self.device)
        self.rotate_directions = rotate_directions
        self.density_correction = density_correction
        # Off by default: a finer step is applied to the whole frame, and it changes the undeformed
        # parts too (a different quadrature, visible at a few edge pixels), so an edit would change what
        # it did not touch. A per-cell step would not; the squash target is met without it.
        self.refine_step = refine_step
        self.max_occupancy_resolution = max_occupancy_resolution
        self.deformed: TetLocator | None = None
        self._rest_inverse = tet_inverses(self.rest_vertices, self.tets)
        # What every pose's affines start from (bend_kernels.pose_tets): the rest tets' edge matrices.
        corners = self.rest_vertices[self.tets]
        self._rest_first = np.ascontiguousarray(corners[:, 0])
        self._rest_edges = np.ascontiguousarray((corners[:, 1:] - corners[:, :1]).transpose(0, 2, 1))
        self._rest_edges_inv = np.ascontiguousarray(self._rest_inverse[:, 1:, :3])
        self._rest_det = np.linalg.det(self._rest_edges)
        self._locate_rest_cells()

    @property
    def use_kernels(self) -> bool:
        return backend.use_kernels(self.device)

    def _pose_tets(self, deformed: np.ndarray):
        """(deformed→rest affines (M,4,4), rotations (M,3,3) or None, rest→deformed affines (M,3,4),
        InversionReport) of one pose: the fused kernel on CPU, numpy elsewhere."""
        if self.use_kernels:
            m = len(self.tets)
            linear, offset, rotation = np.empty((m, 3, 3)), np.empty((m, 3)), np.empty((m, 3, 3))
            forward, det_f, needs_svd = np.empty((m, 3, 4)), np.empty(m), np.empty(m, dtype=np.bool_)
            bend_kernels.pose_tets(
                self._rest_edges,
                self._rest_edges_inv,
                self._rest_first,
                self._rest_det,
                np.ascontiguousarray(deformed),
                self.tets,
                linear,
                offset,
                rotation,
                forward,
                det_f,
                needs_svd,
            )
            affine = np.zeros((m, 4, 4))
            affine[:, :3, :3], affine[:, :3, 3], affine[:, 3, 3] = linear, offset, 1.0
            if needs_svd.any():  # inverted tets: the closest proper rotation, by SVD
                rotation[needs_svd] = polar_rotations(linear[needs_svd])
            inversion = inversion_from_det(det_f)
            return affine, rotation, forward, inversion
        inversion = inversion_report(self.rest_vertices, deformed, self.tets)
        affine = deformed_to_rest_affines(self.rest_vertices, deformed, self.tets)
        forward = (tet_matrices(deformed, self.tets) @ self._rest_inverse)[:, :3, :]
        return affine, None, forward, inversion

    def set_deformed(self, deformed_vertices) -> CageBend:
        """Prepare the map for one pose (same vertex order and tets as the rest cage)."""
        deformed = np.asarray(deformed_vertices, dtype=np.float64)
        if deformed.shape != self.rest_vertices.shape:
            raise EngineError(f"the posed cage has {deformed.shape} vertices, the rest cage {self.rest_vertices.shape}")
        check_coordinates(deformed, "the posed cage")  # what a solve or a file gave, before a kernel reads it
        affine, rotation, forward, self.inversion = self._pose_tets(deformed)
        bad = np.unique(np.r_[self.inversion.degenerate, np.flatnonzero(~np.isfinite(affine).all(axis=(1, 2)))])
        if len(bad):
            affine[bad] = 0.0
            affine[bad, :3, 3] = self.rest_vertices[self.tets[bad]].mean(axis=1)
            affine[bad, 3, 3] = 1.0
        if not self.rotate_directions:
            rotation = np.tile(np.eye(3), (len(affine), 1, 1))
        elif rotation is None:
            rotation = polar_rotations(affine[:, :3, :3])
        rotation[bad] = np.eye(3)
        f32 = dict(dtype=torch.float32, device=self.device)
        self.linear = torch.as_tensor(affine[:, :3, :3], **f32).contiguous()
        self.offset = torch.as_tensor(affine[:, :3, 3], **f32).contiguous()
        self.rotation = torch.as_tensor(rotation, **f32).contiguous()
        # A volume sampled on a grid has no ray direction: its density scale is the isotropic part of
        # the per-ray |A d|, |det A|^(1/3) (1 for a rigid motion and for the flat tets' constant map).
        volume_scale = np.cbrt(np.abs(np.linalg.det(affine[:, :3, :3])))
        volume_scale[bad] = 1.0
        self.volume_scale = torch.as_tensor(volume_scale, **f32)
        # A flat tet holds no volume: locate among the others, and map their indices back.
        located = np.setdiff1d(np.arange(len(self.tets)), bad)
        if len(located) == 0:
            raise EngineError(
                f"the pose collapsed the cage: all {len(self.tets)} tets are degenerate (flattened to "
                "zero volume), so no sample can be mapped through it; ease the pose"
            )
        self.deformed = TetLocator(deformed, self.tets[located], device=self.device)
        self.located_tets = torch.as_tensor(located, dtype=torch.int64, device=self.device)
        self.deformed_bounds = np.stack([deformed.min(0), deformed.max(0)])
        self.occupancy = self._deformed_occupancy(deformed, forward)
        # Measured only when it is used: it is an eigen-decomposition per content tet on every pose.
        self.step_refine = self._step_refine(affine[:, :3, :3], bad) if self.refine_step else 1.0
        self.render_step = self.model.config.render_step / self.step_refine
        return self

    def _step_refine(self, linear: np.ndarray, bad: np.ndarray) -> float:
        """How much finer than the NeRF's render step this pose's frames march: the largest singular
        value of the deformed→rest linear part (a squash to 0.5x makes each deformed step two rest
        steps, so a thin shell would be undersampled) that STEP_REFINE_SHARE of the rest volume of the
        tets holding the NeRF's occupied cells reaches; 1 below STEP_REFINE_FROM, at most MAX_STEP_REFINE."""
        content = self._content_tets
        if len(bad):
            content = np.setdiff1d(content, bad)
        if len(content) == 0:
            return 1.0
        a = linear[content]
        compression = np.sqrt(np.linalg.eigvalsh(np.einsum("nji,njk->nik", a, a))[:, -1])
        volume = np.abs(self._rest_det[content])
        order = np.argsort(-compression, kind="stable")  # most compressed first
        share = np.cumsum(volume[order]) / max(float(volume.sum()), 1e-300)
        level = float(compression[order][min(int(np.searchsorted(share, STEP_REFINE_SHARE)), len(order) - 1)])
        if not np.isfinite(level) or level <= STEP_REFINE_FROM:
            return 1.0
        return min(level, MAX_STEP_REFINE)

    def render_kwargs(self) -> dict:
        """What `render_image` / `render_rays` take to render the current pose."""
        kw = {"sample_transform": self.sample_transform, "occupancy": self.occupancy}
        if self.refine_step and self.step_refine != 1.0:
            kw["step"] = self.render_step
        return kw

    @torch.no_grad()
    def sample_transform(self, positions: torch.Tensor, dirs: torch.Tensor):
        """Renderer hook: (positions, dirs) in deformed space → (rest positions, rest dirs, keep) and,
        with `density_correction`, the density scale |A d| / |d| (A: the tet's deformed→rest linear
        part): the rest-space length of a unit step along the ray. Volume rendering integrates the
        rest density over the rest-space path, so a shell squashed across the ray keeps its opacity
        instead of thinning (and one stretched across it does not thicken)."""
        tet = self.deformed.locate(positions).to(positions.device)
        occ = self.model.occupancy
        scale = None
        if self.use_kernels and positions.device.type == "cpu":
            p, d = torch.empty_like(positions), torch.empty_like(dirs)
            keep = torch.empty(len(positions), dtype=torch.bool)
            scale = torch.empty(len(positions) if self.density_correction else 0, dtype=positions.dtype)
            box = occ.aabb.reshape(2, 3)
            bend_kernels.map_samples(
                positions.contiguous().numpy(),
                dirs.contiguous().numpy(),
                tet.numpy(),
                self.located_tets.numpy(),
                self.linear.numpy(),
                self.offset.numpy(),
                self.rotation.numpy(),
                self.rotate_directions,
                occ.mask.numpy(),
                box[0].numpy(),
                (box[1] - box[0]).numpy(),
                np.float32(occ.resolution),
                p.numpy(),
                d.numpy(),
                keep.numpy(),
                self.density_correction,
                scale.numpy(),
            )
            inside = tet >= 0
        else:
            inside = tet >= 0
            p, d = positions.clone(), dirs.clone()
            t = self.located_tets[tet[inside]]
            p[inside] = torch.einsum("nij,nj->ni", self.linear[t], positions[inside]) + self.offset[t]
            if self.rotate_directions:
                d[inside] = torch.einsum("nij,nj->ni", self.rotation[t], dirs[inside])
            if self.density_correction:
                di = dirs[inside]
                s = torch.einsum("nij,nj->ni", self.linear[t], di).norm(dim=-1) / di.norm(dim=-1).clamp_min(1e-30)
                s = torch.where((s - 1.0).abs() <= bend_kernels.DENSITY_SCALE_SNAP, torch.ones_like(s), s)
                scale = torch.ones(len(positions), dtype=positions.dtype, device=positions.device)
                scale[inside] = s
            # As in an undeformed render, the NeRF is empty wherever its own occupancy grid says so.
            keep = occ.occupied(p)
        if self.model.background is not None:
            # An unbounded NeRF's background (outside its inner box) is not in the inner grid: it stays.
            box = self.model.aabb
            keep |= ~inside & ~((positions >= box[0]) & (positions <= box[1])).all(dim=-1)
        # Outside every deformed tet: empty if the rest cage held it (vacated), else unchanged.
        outside = torch.nonzero(~inside & keep).squeeze(1)
        if len(outside):
            keep[outside] = ~self.rest.contains(positions[outside]).to(positions.device)
        if self.density_correction:
            return p, d, keep, scale
        return p, d, keep

    @torch.no_grad()
    def map_points(self, positions: torch.Tensor):
        """Points in deformed space, no ray (a grid's samples) → (rest positions, keep, density scale,
        rotation): `sample_transform`'s decisions (mapped through their tet, empty where vacated or
        where the NeRF's occupancy grid is), the tet's isotropic density scale |det A|^(1/3), and the
        rotation (N, 3, 3) that turns a deformed-space direction into rest space (identity outside)."""
        tet = self.deformed.locate(positions).to(positions.device)
        inside = tet >= 0
        p = positions.clone()
        scale = torch.ones(len(positions), dtype=positions.dtype, device=positions.device)
        t = self.located_tets[tet[inside]]
        p[inside] = torch.einsum("nij,nj->ni", self.linear[t], positions[inside]) + self.offset[t]
        scale[inside] = self.volume_scale[t]
        rotation = torch.eye(3, dtype=positions.dtype, device=positions.device).repeat(len(positions), 1, 1)
        rotation[inside] = self.rotation[t]
        keep = self.model.occupancy.occupied(p)
        outside = torch.nonzero(~inside & keep).squeeze(1)
        if len(outside):
            keep[outside] = ~self.rest.contains(positions[outside]).to(positions.device)
        return p, keep, scale, rotation

    def _locate_rest_cells(self):
        """Once per rest cage: the NeRF's occupied cells and the rest tet holding each of their 8 corners."""
        occ = self.model.occupancy
        r = occ.resolution
        idx = torch.nonzero(occ.mask).flatten().cpu()
        ijk = torch.stack([idx % r, (idx // r) % r, idx // (r * r)], dim=1)
        corner = ijk[:, None, :] + torch.as_tensor(_CORNERS)  # (n, 8, 3) on the (r+1)^3 lattice of cell corners
        flat = (corner[..., 2] * (r + 1) + corner[..., 1]) * (r + 1) + corner[..., 0]
        unique, cell_corner = torch.unique(flat.reshape(-1), return_inverse=True)
        lattice = torch.stack([unique % (r + 1), (unique // (r + 1)) % (r + 1), unique // ((r + 1) ** 2)], dim=1)
        box = occ.aabb.detach().cpu().double().reshape(2, 3)
        cell = (box[1] - box[0]) / r
        corner_tet = self.rest.locate((box[0] + lattice.double() * cell).to(self.device)).cpu()
        self._cell_ijk = ijk.numpy().astype(np.int64)
        self._corner_tet = corner_tet[cell_corner].reshape(-1, 8).numpy().astype(np.int64)
        self._content_tets = np.unique(self._corner_tet[self._corner_tet >= 0])
        self._rest_lo = box[0].numpy()
        self._rest_cell = cell.numpy()

    def _deformed_occupancy(self, deformed: np.ndarray, forward: np.ndarray | None = None) -> OccupancyGrid:
        """Occupancy of deformed space: every occupied cell of the NeRF's grid sent forward (rest → deformed).

        The image of a cell is bounded by the box of its 8 corners sent through
        the forward affine (T_deformed · T_rest⁻¹) of each tet that holds one of
        its corners, and through the identity for corners outside the rest cage
        (space outside the cage stays put). That box holds the whole image
        wherever the tets meeting a cell all hold one of its corners (cage tets
        are larger than the NeRF's cells). Marked on a grid with the NeRF grid's
        cell size, aligned with it, so an identity pose gives the NeRF's own mask.
        Only skipping depends on this grid: each sample's fate is decided by
        `sample_transform`. No point location per frame.
        """
        if forward is None:
            forward = (tet_matrices(deformed, self.tets) @ self._rest_inverse)[:, :3, :]
        forward = np.ascontiguousarray(forward)
        n = len(self._cell_ijk)
        model_box = self.model.aabb.detach().cpu().double().reshape(2, 3).numpy()
        if n == 0:
            return OccupancyGrid.from_mask(
                torch.as_tensor(model_box, dtype=torch.float32, device=self.device),
                torch.zeros((1, 1, 1), dtype=torch.bool, device=self.device),
            )
        if self.use_kernels:
            lo_c, hi_c = np.empty((n, 3)), np.empty((n, 3))
            bend_kernels.cell_images(
                self._cell_ijk, self._corner_tet, self._rest_lo, self._rest_cell, forward, lo_c, hi_c
            )
        else:
            lo_c, hi_c = self._cell_images_torch(forward)
        # A NaN box (a rest tet too thin to invert) would become a wild index in the marking kernel.
        finite = np.isfinite(lo_c).all(axis=1) & np.isfinite(hi_c).all(axis=1)
        if not finite.all():
            lo_c, hi_c = lo_c[finite], hi_c[finite]
        if len(lo_c) == 0:
            return OccupancyGrid.from_mask(
                torch.as_tensor(model_box, dtype=torch.float32, device=self.device),
                torch.zeros((1, 1, 1), dtype=torch.bool, device=self.device),
            )
        # A grid with the NeRF grid's cells, on its lattice, grown to hold every image (up to a size cap).
        cell = self._rest_cell
        first = np.floor((lo_c.min(0) - self._rest_lo) / cell + 1e-6)
        last = np.ceil((hi_c.max(0) - self._rest_lo) / cell - 1e-6)
        r = int(max(1, (last - first).max()))
        if r > self.max_occupancy_resolution:
            r = self.max_occupancy_resolution
            cell = (last - first) * self._rest_cell / r
        lo = self._rest_lo + first * self._rest_cell
        # Cells a box touches; the small inward tolerance keeps an unmoved cell from spilling into its neighbours.
        tol = 1e-4
        i0 = np.clip(np.floor((lo_c - lo) / cell + tol), 0, r - 1).astype(np.int64)
        i1 = np.clip(np.ceil((hi_c - lo) / cell - tol) - 1, 0, r - 1).astype(np.int64)
        i1 = np.maximum(i0, i1)
        if self.use_kernels:
            mask = np.zeros(r**3, dtype=np.bool_)
            bend_kernels.mark_boxes(i0, i1, r, mask)
            mask = torch.from_numpy(mask).reshape(r, r, r)
        else:
            mask = _mark_boxes_torch(
                torch.as_tensor(i0, device=self.device), torch.as_tensor(i1, device=self.device), r
            )
        box = torch.as_tensor(np.stack([lo, lo + r * cell]), dtype=torch.float32, device=self.device)
        return OccupancyGrid.from_mask(box, mask.to(self.device))

    def _cell_images_torch(self, forward: np.ndarray):
        """`_cell_images` without numba (CUDA, or numba missing): every corner through every corner tet."""
        dev = self.device
        ijk = torch.as_tensor(self._cell_ijk, device=dev, dtype=torch.float64)
        corners = torch.as_tensor(self._rest_lo, device=dev) + (
            ijk[:, None, :] + torch.as_tensor(_CORNERS, device=dev)
        ) * torch.as_tensor(self._rest_cell, device=dev)  # (n, 8, 3)
        tet = torch.as_tensor(self._corner_tet, device=dev)  # (n, 8)
        F = torch.as_tensor(forward, device=dev)
        eye = torch.cat([torch.eye(3, dtype=F.dtype, device=dev), torch.zeros(3, 1, dtype=F.dtype, device=dev)], 1)
        A = torch.where((tet >= 0)[..., None, None], F[tet.clamp_min(0)], eye)  # (n, 8 tets, 3, 4)
        img = torch.einsum("ntij,nkj->ntki", A[..., :3], corners) + A[:, :, None, :, 3]  # (n, 8 tets, 8 corners, 3)
        img = img.reshape(len(ijk), -1, 3)
        return img.amin(1).cpu().numpy(), img.amax(1).cpu().numpy()


def _mark_boxes_torch(i0: torch.Tensor, i1: torch.Tensor, r: int) -> torch.Tensor:
    """(r, r, r) [z, y, x] mask of the union of inclusive boxes: +-1 at box corners, then a 3D prefix sum."""
    diff = torch.zeros((r + 1) ** 3, dtype=torch.int32, device=i0.device)
    one = torch.ones(len(i0), dtype=torch.int32, device=i0.device)
    end = i1 + 1
    for cx in (0, 1):
        for cy in (0, 1):
            for cz in (0, 1):
                x = (end if cx else i0)[:, 0]
                y = (end if cy else i0)[:, 1]
                z = (end if cz else i0)[:, 2]
                sign = -1 if (cx + cy + cz) % 2 else 1
                diff.index_add_(0, (z * (r + 1) + y) * (r + 1) + x, one * sign)
    count = diff.reshape(r + 1, r + 1, r + 1).cumsum(0).cumsum(1).cumsum(2)[:r, :r, :r]
    return count > 0
