"""Multiresolution hash encoding (instant-ngp) and spherical-harmonics direction encoding.

Pure PyTorch, same code on CPU and CUDA. The fast path computes the indices of
all levels x 8 corners at once and does the gather + trilinear weighting of the
whole encoding in ONE `torch.nn.functional.embedding_bag(mode="sum",
per_sample_weights=...)` call over a single concatenated table: one fused gather
forward, one fused scatter-add backward, instead of L x 8 separate gathers.
Coarse levels whose (res+1)^3 grid fits the table are indexed densely (no hash,
no collisions) and get a table of exactly (res+1)^3 rows, as instant-ngp does.

`reference_hash_encode` is the straightforward per-level, per-corner
implementation; the tests check the fast path against it and the benchmark
measures both.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from .. import backend
from . import encoding_kernels

# instant-ngp's spatial hash primes (the first is 1: coherent along x).
PRIMES = (1, 2654435761, 805459861)

# The 8 corners of a cell, as (8, 3) offsets in {0, 1}.
_CORNERS = torch.tensor([[(c >> 0) & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)], dtype=torch.int64)


def level_resolutions(n_levels: int, base_resolution: int, finest_resolution: int) -> list[int]:
    """Grid resolution of each level: geometric from base to finest (instant-ngp's growth factor b)."""
    if n_levels == 1:
        return [int(base_resolution)]
    b = math.exp((math.log(finest_resolution) - math.log(base_resolution)) / (n_levels - 1))
    return [int(math.floor(base_resolution * b**lvl + 1e-6)) for lvl in range(n_levels)]


class HashEncoding(torch.nn.Module):
    """Multiresolution hash encoding of points in [0, 1]^3 → (N, n_levels * n_features).

    Level l has resolution R_l (cells per axis) and (R_l + 1)^3 grid points. A
    level with (R_l + 1)^3 <= 2^log2_table_size is dense: point (x, y, z) has
    row x + y (R+1) + z (R+1)^2. Finer levels hash: row = (x*1 ^ y*p1 ^ z*p2) mod T.
    All levels share one parameter `table` of shape (sum of level sizes, F);
    `offsets[l]` is the first row of level l.
    """

    def __init__(
        self,
        n_levels: int = 8,
        n_features: int = 4,
        log2_table_size: int = 18,
        base_resolution: int = 16,
        finest_resolution: int = 1024,
        init_scale: float = 1e-4,
    ):
        super().__init__()
        self.n_levels = n_levels
        self.n_features = n_features
        self.table_size = 2**log2_table_size
        self.resolutions = level_resolutions(n_levels, base_resolution, finest_resolution)
        sizes, dense = [], []
        for res in self.resolutions:
            n_points = (res + 1) ** 3
            dense.append(n_points <= self.table_size)
            sizes.append(min(n_points, self.table_size))
        self.level_sizes = sizes
        self.dense_levels = dense
        offsets = [0]
        for s in sizes:
            offsets.append(offsets[-1] + s)
        self.n_params_rows = offsets[-1]
        self.table = torch.nn.Parameter(torch.empty(offsets[-1], n_features).uniform_(-init_scale, init_scale))
        self.register_buffer("offsets", torch.tensor(offsets[:-1], dtype=torch.int64), persistent=False)
        self.register_buffer("res_f", torch.tensor(self.resolutions, dtype=torch.float32), persistent=False)
        n_dense = sum(dense)
        self.n_dense = n_dense
        # Dense levels first (geometric growth makes the coarse levels the dense ones).
        assert all(dense[:n_dense]) and not any(dense[n_dense:]), "dense levels must be the coarsest"
        strides = torch.tensor([[1, r + 1, (r + 1) ** 2] for r in self.resolutions[:n_dense]], dtype=torch.int64)
        self.register_buffer("dense_strides", strides.reshape(1, n_dense, 1, 3), persistent=False)
        self.register_buffer("primes", torch.tensor(PRIMES, dtype=torch.int64), persistent=False)
        self.register_buffer("corners", _CORNERS.clone(), persistent=False)

    @property
    def out_dim(self) -> int:
        return self.n_levels * self.n_features

    def indices_and_weights(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Global table rows (N, L, 8) int64 and trilinear weights (N, L, 8) of points x in [0,1]^3
        (clamped; NaN counts as 0, as in the CPU kernels, so no row falls outside the table)."""
        x = torch.nan_to_num(x, nan=0.0).clamp(0.0, 1.0)
        pos = x[:, None, :] * self.res_f[None, :, None]  # (N, L, 3)
        base = pos.floor()
        frac = pos - base  # (N, L, 3)
        base = base.to(torch.int64)
        # Trilinear weights of the 8 corners: prod over axes of (frac if bit else 1 - frac).
        c = self.corners.to(x.dtype)  # (8, 3)
        f = frac[:, :, None, :]  # (N, L, 1, 3)
        w = (c * f + (1 - c) * (1 - f)).prod(dim=-1)  # (N, L, 8)
        pts = base[:, :, None, :] + self.corners  # (N, L, 8, 3)
        nd = self.n_dense
        parts = []
        if nd:
            # Clamp so that points exactly on the upper face stay in the grid (their weight there is 0 or 1 anyway).
            res = self.res_f[:nd].to(torch.int64).reshape(1, nd, 1, 1)
            p = torch.minimum(pts[:, :nd], res)
            parts.append((p * self.dense_strides).sum(-1))
        if nd < self.n_levels:
            p = pts[:, nd:]
            h = (p[..., 0] * self.primes[0]) ^ (p[..., 1] * self.primes[1]) ^ (p[..., 2] * self.primes[2])
            parts.append(h & (self.table_size - 1))
        idx = torch.cat(parts, dim=1) if len(parts) > 1 else parts[0]
        idx = idx + self.offsets.reshape(1, -1, 1)
        return idx, w

    # --- fused CPU kernels (encoding_kernels.py; backend.py decides when they run) ----------
    fused_grad = False  # set by the trainer: gradients go to `grad_buffer()` for `sparse_adam_step`

    @property
    def _kernel_arrays(self):
        arrs = self.__dict__.get("_karrs")
        if arrs is None:
            arrs = self.__dict__["_karrs"] = encoding_kernels.LevelArrays(self)
        return arrs

    def grad_buffer(self) -> torch.Tensor:
        """Gradient of the table. In `fused_grad` mode a persistent buffer that the lazy Adam zeroes."""
        if not self.fused_grad:
            return torch.zeros_like(self.table)
        buf = self.__dict__.get("_gbuf")
        if buf is None or buf.shape != self.table.shape:
            buf = self.__dict__["_gbuf"] = torch.zeros_like(self.table.detach())
            self.__dict__["_touched"] = np.zeros(self.table.shape[0], dtype=np.uint8)
        return buf

    def touched_rows(self) -> np.ndarray:
        """uint8 mask of the rows that received a gradient since the last optimizer step."""
        if not self.fused_grad:
            return np.zeros(self.table.shape[0], dtype=np.uint8)
        self.grad_buffer()
        return self.__dict__["_touched"]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Encode points x (N, 3) in [0, 1]^3 (clamped) → (N, n_levels * n_features), level-major.

        CPU float32: the fused numba kernels; on the torch path (CUDA) the Triton kernels where they run
        (hash_triton.py), else torch. All are differentiable in the table; numba and torch in the positions too.
        """
        if encoding_kernels.kernels_apply(x, self.table):
            return encoding_kernels.HashEncodeCPU.apply(x, self.table, self)
        if self._triton_applies(x):
            from . import hash_triton

            return hash_triton.HashEncode.apply(x, self.table, self)
        return self.torch_forward(x)

    def _triton_applies(self, x: torch.Tensor) -> bool:
        """The Triton kernels (backend.use_triton): float32, a power-of-two feature count, and no gradient in
        the positions (the torch path carries that one)."""
        f = self.n_features
        return (
            backend.use_triton(x.device)
            and x.dtype == torch.float32
            and self.table.dtype == torch.float32
            and not x.requires_grad
            and f & (f - 1) == 0
        )

    def reuse(self, encoded: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """The encoding of x, given `encoded` = self(x) computed without gradients: on the CPU kernel path
        it is reused (only the backward runs); elsewhere it is recomputed with autograd."""
        if encoding_kernels.kernels_apply(x, self.table):
            return encoding_kernels.HashReuseCPU.apply(encoded, x, self.table, self)
        if self._triton_applies(x):
            from . import hash_triton

            return hash_triton.HashReuse.apply(encoded, x, self.table, self)
        return self(x)

    def torch_forward(self, x: torch.Tensor) -> torch.Tensor:
        """The torch formulation (CUDA, and CPU without numba): one embedding_bag over all levels x corners."""
        n = x.shape[0]
        idx, w = self.indices_and_weights(x)
        out = F.embedding_bag(
            idx.reshape(n * self.n_levels, 8),
            self.table,
            per_sample_weights=w.reshape(n * self.n_levels, 8).to(self.table.dtype),
            mode="sum",
        )
        return out.reshape(n, self.n_levels * self.n_features)


def reference_hash_encode(enc: HashEncoding, x: torch.Tensor, tables: list[torch.Tensor] | None = None) -> torch.Tensor:
    """The obvious implementation: loop over levels and corners, one gather each.

    Reads the same parameters as `enc` (its table split per level, or `tables`,
    one (size_l, F) tensor per level) so the two can be compared exactly.
    """
    if tables is None:
        tables = [enc.table[int(o) : int(o) + s] for o, s in zip(enc.offsets, enc.level_sizes)]
    x = x.clamp(0.0, 1.0)
    feats = []
    for lvl, res in enumerate(enc.resolutions):
        pos = x * res
        base = pos.floor()
        frac = pos - base
        base = base.long()
        acc = torch.zeros(x.shape[0], enc.n_features, dtype=tables[lvl].dtype, device=x.device)
        for c in range(8):
            bits = [(c >> a) & 1 for a in range(3)]
            corner = base + torch.tensor(bits, device=x.device)
            w = torch.ones(x.shape[0], dtype=x.dtype, device=x.device)
            for a in range(3):
                w = w * (frac[:, a] if bits[a] else 1 - frac[:, a])
            if enc.dense_levels[lvl]:
                corner = corner.clamp(max=res)
                row = corner[:, 0] + corner[:, 1] * (res + 1) + corner[:, 2] * (res + 1) ** 2
            else:
                row = (corner[:, 0] * PRIMES[0]) ^ (corner[:, 1] * PRIMES[1]) ^ (corner[:, 2] * PRIMES[2])
                row = row % enc.table_size
            acc = acc + w[:, None] * tables[lvl][row]
        feats.append(acc)
    return torch.cat(feats, dim=1)


def sh_encode(d: torch.Tensor, degree: int = 4) -> torch.Tensor:
    """Real spherical harmonics of unit directions d (N, 3) up to `degree` (1..4) → (N, degree^2).

    The basis and constants of instant-ngp / tiny-cuda-nn's SphericalHarmonics encoding.
    """
    if (
        d.device.type == "cpu"
        and d.dtype == torch.float32
        and not d.requires_grad
        and backend.use_kernels(d.device)
        and 1 <= degree <= 4
    ):
        return encoding_kernels.sh_forward(d, degree)
    if d.dtype == torch.float32 and not d.requires_grad and 1 <= degree <= 4 and backend.use_triton(d.device):
        from . import sh_triton

        return sh_triton.sh_encode(d, degree)
    x, y, z = d.unbind(-1)
    out = [torch.full_like(x, 0.28209479177387814)]
    if degree > 1:
        out += [-0.48860251190291987 * y, 0.48860251190291987 * z, -0.48860251190291987 * x]
    if degree > 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [
            1.0925484305920792 * xy,
            -1.0925484305920792 * yz,
            0.94617469575755997 * zz - 0.31539156525251999,
            -1.0925484305920792 * xz,
            0.54627421529603959 * xx - 0.54627421529603959 * yy,
        ]
    if degree > 3:
        out += [
            0.59004358992664352 * y * (-3.0 * xx + yy),
            2.8906114426405538 * xy * z,
            0.45704579946446572 * y * (1.0 - 5.0 * zz),
            0.3731763325901154 * z * (5.0 * zz - 3.0),
            0.45704579946446572 * x * (1.0 - 5.0 * zz),
            1.4453057213202769 * z * (xx - yy),
            0.59004358992664352 * x * (-xx + 3.0 * yy),
        ]
    return torch.stack(out, dim=-1)
