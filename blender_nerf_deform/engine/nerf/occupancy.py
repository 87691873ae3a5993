"""Occupancy grid (instant-ngp's density bitfield) for empty-space skipping.

A cubic grid of `resolution`^3 cells over an aabb. `density` holds a running
(EMA) estimate of each cell's density, `mask` says which cells may hold
matter. The trainer calls `update(density_fn, step)`; the renderer calls
`occupied(points)` and `bounds()`. Replace `mask` (assign a new tensor) rather
than editing it in place: `bounds()` and `any()` are cached per mask tensor. Another stage (ray
bending) can build a grid for a deformed space with `OccupancyGrid.from_mask(aabb, mask)` and hand it to
the renderer instead of the model's own.
"""

from __future__ import annotations

import torch

from .. import backend
from .contraction import contract, inner_units, uncontract


class OccupancyGrid:
    def __init__(self, aabb: torch.Tensor, resolution: int = 128):
        self.aabb = torch.as_tensor(aabb, dtype=torch.float32).reshape(2, 3).clone()
        self.resolution = int(resolution)
        n = self.resolution**3
        self.density = torch.zeros(n, dtype=torch.float32, device=self.aabb.device)
        # Everything may be occupied until the first update says otherwise.
        self.mask = torch.ones(n, dtype=torch.bool, device=self.aabb.device)
        self._bounds = None
        self._bounds_of = None
        self._any = None
        # Cells that may ever be occupied (None: all): what the training cameras see (visibility.py).
        self.allowed = None

    @classmethod
    def from_mask(cls, aabb, mask: torch.Tensor) -> OccupancyGrid:
        """A grid given by a boolean (R, R, R) mask indexed [z, y, x] (flat order has x fastest, as
        `cell_centers` reads it), e.g. for a deformed space."""
        mask = torch.as_tensor(mask, dtype=torch.bool)
        r = mask.shape[0]
        if mask.shape != (r, r, r):
            raise ValueError(f"occupancy mask must be cubic (R, R, R), got {tuple(mask.shape)}")
        grid = cls(torch.as_tensor(aabb, dtype=torch.float32).to(mask.device), r)
        grid.mask = mask.reshape(-1).clone()
        grid.density = grid.mask.float()
        return grid

    def to(self, device) -> OccupancyGrid:
        self.aabb = self.aabb.to(device)
        self.density = self.density.to(device)
        self.mask = self.mask.to(device)
        if self.allowed is not None:
            self.allowed = self.allowed.to(device)
        self._bounds = None
        return self

    @property
    def cell_size(self) -> torch.Tensor:
        return (self.aabb[1] - self.aabb[0]) / self.resolution

    def cell_index(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Flat cell index (x + R y + R^2 z) of points, and whether each point is inside the grid."""
        r = self.resolution
        g = ((points - self.aabb[0]) / (self.aabb[1] - self.aabb[0]) * r).floor().long()
        inside = ((g >= 0) & (g < r)).all(dim=-1)
        g = g.clamp(0, r - 1)
        return g[:, 0] + r * g[:, 1] + r * r * g[:, 2], inside

    def occupied(self, points: torch.Tensor) -> torch.Tensor:
        """Bool (N,): the point lies in an occupied cell (False outside the grid)."""
        idx, inside = self.cell_index(points)
        return self.mask[idx] & inside

    def bounds(self) -> torch.Tensor:
        """(2, 3) world box around the occupied cells (the whole aabb when none is occupied)."""
        if self._bounds is None or self._bounds_of is not self.mask:  # recomputed when the mask is replaced
            self._bounds_of = self.mask
            r = self.resolution
            occ = self.mask.reshape(r, r, r)  # [z, y, x] since flat = x + R y + R^2 z
            if not backend.use_kernels(self.mask.device):
                # The device path, without reading the mask back: the first and one past the last occupied
                # index per axis.
                index = torch.arange(r, device=self.mask.device)
                per_axis = torch.stack(
                    [occ.any(dim=0).any(dim=0), occ.any(dim=0).any(dim=1), occ.any(dim=2).any(dim=1)]
                )
                lo = torch.where(per_axis, index, r).amin(dim=1).to(torch.float32)
                hi = (torch.where(per_axis, index, -1).amax(dim=1) + 1).to(torch.float32)
                box = torch.stack([self.aabb[0] + lo * self.cell_size, self.aabb[0] + hi * self.cell_size])
                self._bounds = torch.where(per_axis.any(), box, self.aabb)
            elif not bool(occ.any()):
                self._bounds = self.aabb.clone()
            else:
                lo, hi = [], []
                per_axis = (occ.any(dim=0).any(dim=0), occ.any(dim=0).any(dim=1), occ.any(dim=2).any(dim=1))
                for along in per_axis:  # x, y, z
                    nz = torch.nonzero(along).flatten()
                    lo.append(int(nz.min()))
                    hi.append(int(nz.max()) + 1)
                lo = torch.tensor(lo, device=self.aabb.device, dtype=torch.float32)
                hi = torch.tensor(hi, device=self.aabb.device, dtype=torch.float32)
                self._bounds = torch.stack([self.aabb[0] + lo * self.cell_size, self.aabb[0] + hi * self.cell_size])
        return self._bounds

    def coarse_blocks(self):
        """(bool flat mask of blocks of march_kernels.COARSE^3 cells holding an occupied one, blocks per axis):
        the march jumps over the empty blocks. Cached until the mask is replaced."""
        cached = self.__dict__.get("_coarse")
        if cached is None or cached[0] is not self.mask:
            from .march_kernels import coarse_mask

            cached = self.__dict__["_coarse"] = (self.mask, *coarse_mask(self.mask, self.resolution))
        return cached[1], cached[2]

    def any(self) -> bool:
        """Whether any cell is occupied (cached until the mask changes through update/to)."""
        if self._any is None or self._any[0] is not self.mask:
            self._any = (self.mask, bool(self.mask.any()))
        return self._any[1]

    def cell_centers(self, idx: torch.Tensor, jitter: bool = True) -> torch.Tensor:
        r = self.resolution
        xyz = torch.stack([idx % r, (idx // r) % r, idx // (r * r)], dim=-1).float()
        off = torch.rand_like(xyz) if jitter else torch.full_like(xyz, 0.5)
        return self.aabb[0] + (xyz + off) * self.cell_size

    @torch.no_grad()
    def update(
        self,
        density_fn,
        step_size: float,
        threshold: float = 0.01,
        decay: float = 0.95,
        n_uniform: int | None = None,
        n_occupied: int | None = None,
        chunk: int = 1 << 16,
        block: int = 1,
    ) -> None:
        """instant-ngp's update: re-sample some cells, EMA-max their density, re-threshold.

        `n_uniform` random cells plus `n_occupied` random currently-occupied cells
        are evaluated at a jittered point (all cells when both are None). A cell
        is occupied when `density * step_size` exceeds min(threshold, mean).
        `block` > 1 (all cells only): one jittered point per block^3 cells, its
        value given to the whole block; block^3 times cheaper, for the first
        updates of training when the field is still blurry.
        """
        n = self.resolution**3
        dev = self.density.device
        r = self.resolution
        if block > 1 and n_uniform is None and n_occupied is None and r % block == 0:
            rb = r // block
            ib = torch.arange(rb**3, device=dev)
            xyz = torch.stack([ib % rb, (ib // rb) % rb, ib // (rb * rb)], dim=-1).float()
            pts = self._to_world(self.aabb[0] + (xyz + torch.rand_like(xyz)) * self.cell_size * block)
            new = torch.cat([density_fn(pts[s : s + chunk]) for s in range(0, pts.shape[0], chunk)])
            full = new.reshape(rb, 1, rb, 1, rb, 1).expand(rb, block, rb, block, rb, block).reshape(-1)
            self.density = torch.maximum(self.density * decay, full)
            self._threshold(step_size, threshold)
            return
        if n_uniform is None and n_occupied is None:
            idx = torch.arange(n, device=dev)
        else:
            parts = [torch.randint(0, n, (n_uniform or 0,), device=dev)]
            if backend.use_kernels(dev):
                occ_idx = torch.nonzero(self.mask).flatten()
                if n_occupied and occ_idx.numel():
                    parts.append(occ_idx[torch.randint(0, occ_idx.numel(), (n_occupied,), device=dev)])
            elif n_occupied:
                # The same uniform draw among the occupied cells without reading their number back: the cell
                # whose running count of occupied cells first exceeds a uniform pick (none occupied: the last).
                running = torch.cumsum(self.mask, 0)
                pick = (torch.rand(n_occupied, device=dev, dtype=torch.float64) * running[-1]).long()
                parts.append(torch.searchsorted(running, pick, right=True).clamp_max(n - 1))
            idx = torch.cat(parts)
        new = torch.empty(idx.shape[0], device=dev)
        for s in range(0, idx.shape[0], chunk):
            new[s : s + chunk] = density_fn(self.cell_centers(idx[s : s + chunk]))
        # Random cells repeat: a plain `density[idx] = ...` keeps whichever duplicate is written last,
        # which varies from run to run (parallel writes). The max over duplicates is the same in any
        # order, so a seeded training run does not depend on the order of the writes.
        self.density.scatter_reduce_(
            0, idx, torch.maximum(self.density[idx] * decay, new), reduce="amax", include_self=False
        )
        self._threshold(step_size, threshold)

    def permitted(self, points: torch.Tensor) -> torch.Tensor:
        """Bool (N,): the point may hold density (outside the grid, or in a cell `restrict` left allowed)."""
        if self.allowed is None:
            return torch.ones(points.shape[0], dtype=torch.bool, device=points.device)
        idx, inside = self.cell_index(points)
        return self.allowed[idx] | ~inside

    def restrict(self, allowed: torch.Tensor) -> None:
        """Only the cells of the flat bool mask `allowed` (and of every earlier restriction) may be occupied, from
        now on and at every update."""
        allowed = allowed.to(self.mask.device).reshape(-1)
        self.allowed = allowed if self.allowed is None else self.allowed & allowed
        self.mask = self.mask & self.allowed
        self._bounds = None

    def _threshold(self, step_size: float, threshold: float) -> None:
        opacity = self.density * step_size
        if backend.use_kernels(opacity.device):
            self.mask = opacity > min(threshold, float(opacity.mean()))
        else:  # the same, on the device
            self.mask = opacity > torch.clamp(opacity.mean(), max=threshold)
        if self.allowed is not None:
            self.mask &= self.allowed
        self._bounds = None

    def _to_world(self, grid_points: torch.Tensor) -> torch.Tensor:
        """Points in the grid's own coordinates → world (the identity here; see ContractedGrid)."""
        return grid_points


class ContractedGrid(OccupancyGrid):
    """Occupancy of an unbounded NeRF's background: a cubic grid over contracted space [-2, 2]^3
    (contraction.py) of which only the shell outside the inner box is used (the inner box has its own,
    finer world-space grid; the shell's inner face lies on cell boundaries when the resolution is a
    multiple of 4). `aabb` here is the contracted cube; `inner` is the world inner box.

    `occupied(world points)`, `cell_index(world points)`, `cell_centers` (world points) and `update`
    behave as OccupancyGrid's, through the contraction.
    """

    def __init__(self, inner: torch.Tensor, resolution: int = 128):
        inner = torch.as_tensor(inner, dtype=torch.float32).reshape(2, 3)
        super().__init__(torch.tensor([[-2.0] * 3, [2.0] * 3], device=inner.device), resolution)
        self.inner = inner.clone()
        self._shell = self._shell_cells()
        self.mask = self.mask & self._shell

    @property
    def center(self) -> torch.Tensor:
        return 0.5 * (self.inner[0] + self.inner[1])

    @property
    def half(self) -> torch.Tensor:
        return 0.5 * (self.inner[1] - self.inner[0])

    def _shell_cells(self) -> torch.Tensor:
        """Cells whose centre lies outside the inner box [-1, 1]^3 of contracted space."""
        # Per axis, then broadcast over [z, y, x]: the per-cell version (r^3 coordinates) cost 0.12 s of
        # every unbounded checkpoint's load.
        r = self.resolution
        axis = torch.arange(r, device=self.aabb.device, dtype=torch.float32) + 0.5
        outside = [(self.aabb[0, a] + axis * self.cell_size[a]).abs() > 1.0 for a in range(3)]
        shell = outside[2][:, None, None] | outside[1][None, :, None] | outside[0][None, None, :]
        return shell.reshape(-1)

    def to(self, device) -> ContractedGrid:
        super().to(device)
        self.inner = self.inner.to(device)
        self._shell = self._shell.to(device)
        return self

    def contracted(self, points: torch.Tensor) -> torch.Tensor:
        return contract(inner_units(points, self.center, self.half))

    def cell_index(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return super().cell_index(self.contracted(points))

    def cell_centers(self, idx: torch.Tensor, jitter: bool = True) -> torch.Tensor:
        return self._to_world(super().cell_centers(idx, jitter))

    def _to_world(self, grid_points: torch.Tensor) -> torch.Tensor:
        return self.center + uncontract(grid_points) * self.half

    def _threshold(self, step_size: float, threshold: float) -> None:
        opacity = self.density * step_size
        shell = self._shell
        if backend.use_kernels(opacity.device):
            mean = float(opacity[shell].mean()) if bool(shell.any()) else 0.0
            self.mask = (opacity > min(threshold, mean)) & shell
        else:  # the mean over the shell on the device, without reading it back
            mean = torch.where(shell, opacity, 0.0).sum() / shell.sum().clamp_min(1)
            self.mask = (opacity > torch.clamp(mean, max=threshold)) & shell
        if self.allowed is not None:
            self.mask &= self.allowed
        self._bounds = None
