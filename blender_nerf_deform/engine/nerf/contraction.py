"""Scene contraction: the whole of space in a bounded cube, for NeRFs of unbounded scenes.

mip-NeRF 360's contraction with the L-infinity norm, as nerfacto uses it: a world
point p is first expressed in units of the inner box (u = (p - centre) / half-size,
so the inner box is [-1, 1]^3), then

    c(u) = u                              where |u|_inf <= 1   (the inner box: unchanged)
    c(u) = (2 - 1/|u|_inf) u / |u|_inf    elsewhere            (all the rest: the shell up to 2)

continuous at the inner box, monotone along every ray from the centre, and
infinity lands on the cube |c|_inf = 2. Why the L-infinity norm rather than
mip-NeRF 360's L2: the contracted cube's faces line up with the inner box's, so
the inner box is an exact block of the hash grid and of the background occupancy
grid (cells are whole cells on both sides of its boundary).

Ray bending happens in world space, before contraction: cages and edit regions
live in the inner box, where c is the identity.
"""

from __future__ import annotations

import torch

FAR_RADIUS = 1024.0  # rays stop where |u|_inf reaches this: c = 2 - 1/1024, inside the outermost grid cells
_MAX_INVERSE_RADIUS = 1e4  # uncontract clamps |c|_inf below 2 - 1e-4: a cell centre at the edge maps to a finite point


def inner_units(points: torch.Tensor, center: torch.Tensor, half: torch.Tensor) -> torch.Tensor:
    return (points - center) / half


def contract(u: torch.Tensor) -> torch.Tensor:
    """c(u) for points u (N, 3) in inner-box units; NaN stays NaN (and is rejected downstream)."""
    m = u.abs().amax(dim=-1, keepdim=True)
    outside = m > 1.0
    scale = torch.where(outside, (2.0 - 1.0 / m.clamp_min(1.0)) / m.clamp_min(1.0), torch.ones_like(m))
    return u * scale


def uncontract(c: torch.Tensor) -> torch.Tensor:
    """The inverse of `contract` on the cube |c|_inf < 2 (clamped just inside it)."""
    m = c.abs().amax(dim=-1, keepdim=True)
    outside = m > 1.0
    radius = 1.0 / (2.0 - m.clamp(1.0, 2.0 - 1.0 / _MAX_INVERSE_RADIUS))
    return c * torch.where(outside, radius / m.clamp_min(1.0), torch.ones_like(m))
