"""Point location in a tetrahedral cage, in torch (same code on CPU and CUDA).

Why hand-written: the renderer locates millions of ray samples per frame in a
cage whose vertices move every frame, on whatever device the NeRF runs on.
libigl's `in_element` (an AABB tree, rebuilt per frame, CPU only) and
scipy/trimesh (CPU, triangle meshes) do not fit that; nothing in torch does
it. So, as NeRFshop does, a grid whose cells list the tets overlapping them:

- torch path (any device; CUDA): a coarse uniform grid, each coarse cell split
  into up to `max_sub`^3 leaves where it holds many tets (fine near the
  surface, where fTetWild makes small tets). (tet, leaf) pairs are expanded
  with `repeat_interleave` from the tets' bounding boxes, pairs whose leaf lies
  wholly outside one of the tet's face planes are dropped (a conservative
  box-vs-half-space test), then sorted by leaf into a CSR list. Query: point →
  leaf → candidates tested in rounds (round k tests the k-th candidate of every
  unresolved point in one batched barycentric test), the last few points all
  at once. No Python loop over tets or points.
- numba path (CPU tensors, when `backend.use_kernels` says so; `locate_kernels.py`): the
  same grid method in fused parallel kernels. On CPU the torch path is bound
  by materialised gathers and compactions and only matches igl's speed; the
  kernels are several times faster.

Cell size: about `cells_per_tet` cells per tet over the cage's bounding box,
the trade-off between candidates per cell (query cost) and pairs per tet
(build cost and memory); `tools/bench/geometry_locate.py` measures it.
Memory: torch queries run in chunks of `chunk` points.
"""

from __future__ import annotations

import numpy as np
import torch

from .. import backend as code_path
from ..errors import EngineError
from .locate_kernels import NumbaGrid


def _tensor(x, dtype, device) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        return x.to(device=device, dtype=dtype)
    return torch.as_tensor(np.asarray(x), dtype=dtype, device=device)


def barycentric_rows(vertices: torch.Tensor, tets: torch.Tensor) -> torch.Tensor:
    """(M, 3, 4) rows 1..3 of T⁻¹ per tet (λ_bcd = R[:, :, :3] p + R[:, :, 3]; λ_a = 1 - Σ λ_bcd).

    Closed form via the adjugate of the edge matrix D = [b-a, c-a, d-a]: the
    rows of D⁻¹ are cross products of its columns divided by det D.
    """
    P = vertices[tets]  # (M, 4, 3)
    a = P[:, 0]
    e1, e2, e3 = P[:, 1] - a, P[:, 2] - a, P[:, 3] - a
    c23, c31, c12 = torch.cross(e2, e3, dim=1), torch.cross(e3, e1, dim=1), torch.cross(e1, e2, dim=1)
    det = (e1 * c23).sum(1, keepdim=True)
    Dinv = torch.stack((c23, c31, c12), dim=1) / det[:, :, None]  # (M, 3, 3), rows of D⁻¹
    R = torch.empty((len(tets), 3, 4), dtype=vertices.dtype, device=vertices.device)
    R[:, :, :3] = Dinv
    R[:, :, 3] = -(Dinv @ a[:, :, None])[:, :, 0]
    return R


def _expand(i0: torch.Tensor, i1: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """All integer points of the boxes [i0, i1] (inclusive, (K, 3) each): (owner box index, ijk)."""
    span = i1 - i0 + 1
    n = span.prod(1)
    owner = torch.repeat_interleave(torch.arange(len(i0), device=i0.device), n)
    first = torch.cumsum(n, 0) - n
    k = torch.arange(len(owner), device=i0.device) - first[owner]
    s = span[owner]
    ijk = i0[owner] + torch.stack((k % s[:, 0], (k // s[:, 0]) % s[:, 1], k // (s[:, 0] * s[:, 1])), dim=1)
    return owner, ijk


class TetLocator:
    """Which tet of a cage contains each point: `locate(points) -> tet index or -1`.

    Built once per set of vertex positions (rebuild it for every deformed
    frame: building is cheap). `eps` is the tolerance on
    barycentric coordinates, so a point on a shared face is found in one of
    its two tets rather than in neither.
    """

    def __init__(
        self,
        vertices,
        tets,
        *,
        device: str | torch.device | None = None,
        dtype: torch.dtype = torch.float32,
        cells_per_tet: float = 0.25,
        eps: float | None = None,
        max_res: int = 256,
        leaf_tets: float = 4.0,
        max_sub: int = 2,
        flat_below: int = 65536,
        backend: str = "auto",
        numba_cells_per_tet: float | None = 2.0,
    ):
        self.flat_below = flat_below
        if device is None:
            device = vertices.device if isinstance(vertices, torch.Tensor) else "cpu"
        self.device = torch.device(device)
        self.dtype = dtype
        self.eps = eps if eps is not None else (1e-5 if dtype == torch.float32 else 1e-10)
        V = _tensor(vertices, dtype, self.device)
        T = _tensor(tets, torch.int64, self.device)
        if V.ndim != 2 or V.shape[1] != 3 or T.ndim != 2 or T.shape[1] != 4 or len(T) == 0:
            raise EngineError(
                f"a cage needs (N, 3) vertices and (M>0, 4) tets, got {tuple(V.shape)} and {tuple(T.shape)}"
            )
        # The kernels index vertices by tets and cells by coordinates without bounds checks.
        if not bool(torch.isfinite(V).all()):
            bad = int(torch.nonzero(~torch.isfinite(V).all(1))[0])
            raise EngineError(f"cage vertices must be finite: vertex {bad} is {V[bad].tolist()}")
        if int(T.min()) < 0 or int(T.max()) >= len(V):
            raise EngineError(f"cage tets index vertices outside 0..{len(V) - 1}")
        self.vertices, self.tets = V, T
        if backend == "auto":
            backend = "numba" if code_path.use_kernels(self.device) else "torch"
        if backend == "numba" and (self.device.type != "cpu" or not code_path.HAVE_NUMBA):
            raise EngineError("the numba point-location backend needs numba and a CPU device")
        self.backend = backend
        if backend == "numba":
            if eps is None:
                self.eps = 1e-10
            src = vertices.detach().cpu().numpy() if isinstance(vertices, torch.Tensor) else np.asarray(vertices)
            tsrc = tets.detach().cpu().numpy() if isinstance(tets, torch.Tensor) else np.asarray(tets)
            self._grid = NumbaGrid(
                src, tsrc, cells_per_tet if numba_cells_per_tet is None else numba_cells_per_tet, self.eps, 4 * max_res
            )
            if self._grid.n_degenerate:
                raise EngineError(
                    f"degenerate cage: {self._grid.n_degenerate} tets have zero volume, so points in them cannot "
                    "be located"
                )
            self.res = torch.as_tensor(self._grid.res)
            self.n_leaves = self._grid.n_cells
            self.cell_count = torch.from_numpy(np.diff(self._grid.cell_start))
            self.n_pairs = int(self._grid.cell_start[-1])
            return
        self.R = barycentric_rows(V, T)
        if not torch.isfinite(self.R).all():
            bad = int((~torch.isfinite(self.R)).flatten(1).any(1).sum())
            raise EngineError(f"degenerate cage: {bad} tets have zero volume, so points in them cannot be located")

        P = V[T]
        tlo, thi = P.amin(1), P.amax(1)
        del P
        self.lo = V.amin(0)
        extent = (V.amax(0) - self.lo).clamp_min(1e-12)
        # Level 1: a coarse uniform grid of about cells_per_tet * M cells.
        h = float((extent.prod() / (cells_per_tet * len(T))) ** (1.0 / 3.0))
        res = torch.clamp(torch.ceil(extent / h), 1, max_res).to(torch.int64)
        self.res = res
        self.inv_cell = res.to(dtype) / extent
        rx, ry, rz = (int(r) for r in res)
        self.n_cells = rx * ry * rz
        # Every coordinate goes through the same monotonic formula g = (x - lo) * inv,
        # for tet bounds and for query points alike, so a point inside a tet's
        # bounding box always falls in a cell of that tet's cell range.
        glo = (tlo - self.lo) * self.inv_cell
        ghi = (thi - self.lo) * self.inv_cell
        i0 = torch.minimum(glo.floor().to(torch.int64).clamp_min(0), res - 1)
        i1 = torch.minimum(ghi.floor().to(torch.int64).clamp_min(0), res - 1)
        tet1, ijk1 = _expand(i0, i1)
        cell1 = (ijk1[:, 2] * ry + ijk1[:, 1]) * rx + ijk1[:, 0]
        count1 = torch.bincount(cell1, minlength=self.n_cells)
        # Level 2: each coarse cell is split into sub^3 leaves, sub chosen from its
        # tet count so that leaves hold about leaf_tets tets: fine where the cage
        # has small tets (near the surface), coarse where it has big ones.
        sub = torch.clamp(torch.ceil((count1.to(torch.float64) / leaf_tets) ** (1.0 / 3.0)), 1, max_sub).to(torch.int64)
        self.sub = sub
        nleaf = sub**3
        self.leaf_offset = torch.cumsum(nleaf, 0) - nleaf
        self.n_leaves = int(nleaf.sum())
        sc = sub[cell1]
        scf = sc.to(dtype)[:, None]
        j0 = torch.minimum(((glo[tet1] - ijk1.to(dtype)) * scf).floor().to(torch.int64).clamp_min(0), sc[:, None] - 1)
        j1 = torch.minimum(((ghi[tet1] - ijk1.to(dtype)) * scf).floor().to(torch.int64).clamp_min(0), sc[:, None] - 1)
        del glo, ghi
        pair1, jk = _expand(j0, j1)
        tet2 = tet1[pair1]
        c1, s2 = cell1[pair1], sc[pair1]
        leaf = self.leaf_offset[c1] + (jk[:, 2] * s2 + jk[:, 1]) * s2 + jk[:, 0]
        # Drop (tet, leaf) pairs whose leaf box lies wholly outside a face plane
        # of the tet: the maximum of λ_i over a box is λ_i(centre) + Σ_j |∂λ_i/∂x_j| r_j
        # (r = half the box). Only pairs of tets spanning several leaves need it.
        multi = torch.nonzero(((j1 - j0).amax(1)[pair1] > 0) | ((i1 - i0).amax(1)[tet2] > 0)).squeeze(1)
        if len(multi):
            tm = tet2[multi]
            cell_size = 1.0 / self.inv_cell
            s2m = s2[multi].to(dtype)[:, None]
            ijk = ijk1[pair1[multi]].to(dtype)
            half = (0.5 * cell_size) / s2m  # (K, 3)
            centre = self.lo + (ijk + (jk[multi].to(dtype) + 0.5) / s2m) * cell_size
            Rp = self.R[tm]
            lam = (Rp[:, :, :3] * centre[:, None, :]).sum(2) + Rp[:, :, 3]
            reach = (Rp[:, :, :3].abs() * half[:, None, :]).sum(2)
            g0 = Rp[:, :, :3].sum(1)
            lam0 = 1.0 - lam.sum(1)
            reach0 = (g0.abs() * half).sum(1)
            drop = ((lam + reach).amin(1) < -self.eps) | (lam0 + reach0 < -self.eps)
            keep = torch.ones(len(leaf), dtype=torch.bool, device=self.device)
            keep[multi[drop]] = False
            leaf, tet2 = leaf[keep], tet2[keep]
        # Within a leaf, larger tets first: a point is more likely to lie in them,
        # so rounds resolve it earlier. One sort on the key (leaf, size rank).
        size_rank = torch.empty(len(T), dtype=torch.int64, device=self.device)
        size_rank[torch.argsort(self.R[:, :, :3].abs().sum((1, 2)))] = torch.arange(len(T), device=self.device)
        order = torch.argsort(leaf * len(T) + size_rank[tet2])
        self.cell_tets = tet2[order]
        counts = torch.bincount(leaf, minlength=self.n_leaves)
        self.cell_start = torch.cumsum(counts, 0) - counts
        self.cell_count = counts
        self.n_pairs = int(len(self.cell_tets))

    @property
    def stats(self) -> dict:
        c = self.cell_count
        return {
            "backend": self.backend,
            "tets": int(len(self.tets)),
            "grid": tuple(int(r) for r in self.res),
            "leaves": self.n_leaves,
            "pairs": self.n_pairs,
            "mean_tets_per_nonempty_cell": float(c[c > 0].float().mean()),
            "max_tets_per_cell": int(c.max()),
        }

    def _cells(self, p: torch.Tensor) -> torch.Tensor:
        """Leaf index of each point, -1 outside the grid."""
        g = (p - self.lo) * self.inv_cell
        inside = ((g >= 0) & (g <= self.res.to(g.dtype))).all(1)
        ijk = torch.minimum(g.floor().to(torch.int64), self.res - 1).clamp_min(0)
        cid = (ijk[:, 2] * int(self.res[1]) + ijk[:, 1]) * int(self.res[0]) + ijk[:, 0]
        sc = self.sub[cid]
        jk = torch.minimum(
            ((g - ijk.to(g.dtype)) * sc.to(g.dtype)[:, None]).floor().to(torch.int64).clamp_min(0), sc[:, None] - 1
        )
        leaf = self.leaf_offset[cid] + (jk[:, 2] * sc + jk[:, 1]) * sc + jk[:, 0]
        return torch.where(inside, leaf, torch.full_like(leaf, -1))

    def _test(self, tid: torch.Tensor, p: torch.Tensor):
        """Barycentric coordinates (K, 4) of points p in tets tid, and whether each lies inside."""
        R = self.R[tid]  # (K, 3, 4)
        lam = R[:, :, 0] * p[:, 0:1] + R[:, :, 1] * p[:, 1:2] + R[:, :, 2] * p[:, 2:3] + R[:, :, 3]
        lam0 = 1.0 - lam.sum(1)
        hit = (lam.amin(1) >= -self.eps) & (lam0 >= -self.eps)
        return lam0, lam, hit

    def _locate_chunk(self, p: torch.Tensor, want_bary: bool):
        n = len(p)
        out = torch.full((n,), -1, dtype=torch.int64, device=self.device)
        bary = torch.zeros((n, 4), dtype=self.dtype, device=self.device) if want_bary else None
        cid = self._cells(p)
        count = self.cell_count[cid.clamp_min(0)]
        active = torch.nonzero((cid >= 0) & (count > 0)).squeeze(1)
        cid = cid[active]
        count = count[active]
        start = self.cell_start[cid]
        pa = p[active]
        k = 0
        # Rounds while many points are unresolved (each round one batched test of
        # the k-th candidate); then the few left are expanded to all their
        # remaining candidates at once, so a long candidate list in a few cells
        # does not cost one round (a dozen tensor ops) per candidate.
        while len(active) > self.flat_below:
            tid = self.cell_tets[start + k]
            lam0, lam, hit = self._test(tid, pa)
            hit_idx = active[hit]
            out[hit_idx] = tid[hit]
            if want_bary:
                bary[hit_idx] = torch.cat((lam0[hit, None], lam[hit]), dim=1)
            k += 1
            sel = torch.nonzero((~hit) & (count > k)).squeeze(1)
            active, start, count, pa = active[sel], start[sel], count[sel], pa[sel]
        if len(active):
            rem = count - k
            pair_pt = torch.repeat_interleave(torch.arange(len(active), device=self.device), rem)
            first = torch.cumsum(rem, 0) - rem
            j = torch.arange(len(pair_pt), device=self.device) - first[pair_pt] + k
            tid = self.cell_tets[start[pair_pt] + j]
            lam0, lam, hit = self._test(tid, pa[pair_pt])
            # First hit per point (the lowest candidate rank), as the rounds would find.
            big = torch.iinfo(torch.int64).max
            rank = torch.where(hit, j, torch.full_like(j, big))
            best = torch.full((len(active),), big, dtype=torch.int64, device=self.device)
            best.scatter_reduce_(0, pair_pt, rank, reduce="amin")
            winner = torch.nonzero(hit & (rank == best[pair_pt])).squeeze(1)
            out[active[pair_pt[winner]]] = tid[winner]
            if want_bary:
                bary[active[pair_pt[winner]]] = torch.cat((lam0[winner, None], lam[winner]), dim=1)
        return out, bary

    @torch.no_grad()
    def locate(self, points, chunk: int = 1 << 20, return_barycentric: bool = False):
        """(N,) int64 index of the tet containing each point, -1 where none does.

        With `return_barycentric`, also the (N, 4) barycentric coordinates in
        that tet (zeros where none).
        """
        p = _tensor(points, self.dtype, self.device)
        if p.ndim != 2 or p.shape[1] != 3:
            raise EngineError(f"points must have shape (N, 3), got {tuple(p.shape)}")
        if self.backend == "numba":
            out, bary = self._grid.query(p.numpy(), return_barycentric)
            out = torch.from_numpy(out)
            return (out, torch.from_numpy(bary).to(self.dtype)) if return_barycentric else out
        outs, barys = [], []
        for s in range(0, len(p), chunk):
            o, b = self._locate_chunk(p[s : s + chunk], return_barycentric)
            outs.append(o)
            barys.append(b)
        out = torch.cat(outs) if outs else torch.empty(0, dtype=torch.int64, device=self.device)
        if not return_barycentric:
            return out
        bary = torch.cat(barys) if barys else torch.empty((0, 4), dtype=self.dtype, device=self.device)
        return out, bary

    def contains(self, points, chunk: int = 1 << 20) -> torch.Tensor:
        """(N,) bool: the point lies in some tet of the cage."""
        return self.locate(points, chunk) >= 0
