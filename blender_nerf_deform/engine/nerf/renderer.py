"""Volume rendering of a NeRF: cameras → rays → occupancy-skipped samples → RGBA + depth.

One code path serves training (with gradients), the CLI, the Blender worker and
the ray-bending stage:

- `Camera` / `camera_rays(camera)`: any camera (fx, fy, cx, cy in pixels,
  width, height, camera-to-world 4x4, optional lens distortion) in the
  Blender/OpenGL convention: the camera looks down its local -Z, +Y is up, and
  a pinhole's pixel (i, j) (column i, row j from the top) has the direction
  ((i + 0.5 - cx)/fx, -(j + 0.5 - cy)/fy, -1): rays through pixel centres, as
  Blender renders them; a distorted camera's rays go through the pixel as its
  lens bent it (lens.py).
- `render_rays(model, origins, dirs, ...)`: rays → premultiplied colour, alpha,
  depth, in chunks of `chunk` rays so memory stays bounded.
- `render_image(model, camera, ...)`: a whole frame as straight-alpha RGBA.

Sampling: each ray is clipped to the box of the occupied cells, marched with a
constant step (`config.render_step`), and only samples in occupied cells of the
occupancy grid are kept. Hooks for ray bending:

- `occupancy=`: any `OccupancyGrid` (e.g. of a deformed space) instead of the model's own;
- `sample_transform(positions[S,3], dirs[S,3]) -> (positions, dirs, keep[S])`: called
  between sampling and the field query; samples with keep False get density 0.

Early ray termination: a first pass evaluates density only and computes
transmittance; samples behind transmittance `early_stop_eps` are dropped, and
when rendering without gradients the colour MLP runs only on samples whose
weight exceeds `weight_threshold`. With gradients (training) the surviving
samples are re-evaluated with autograd.

Depth is the expected distance along the (unit) ray direction, divided by alpha;
0 where alpha is 0.
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np
import torch

from .. import backend
from . import march_kernels
from .camera import Camera  # noqa: F401  (re-exported: renderer.Camera is part of the interface)
from .lens import camera_directions
from .occupancy import OccupancyGrid


SampleTransform = Callable[[torch.Tensor, torch.Tensor], tuple]


def camera_rays(camera: Camera, device="cpu") -> tuple[torch.Tensor, torch.Tensor]:
    """World-space origins (H*W, 3) and unit directions (H*W, 3), row-major from the top-left pixel."""
    c2w = torch.as_tensor(np.asarray(camera.c2w, dtype=np.float64)[:3, :4], dtype=torch.float64)
    i = torch.arange(camera.width, dtype=torch.float64) + 0.5
    j = torch.arange(camera.height, dtype=torch.float64) + 0.5
    jj, ii = torch.meshgrid(j, i, indexing="ij")
    d = camera_directions(camera.fx, camera.fy, camera.cx, camera.cy, ii.reshape(-1), jj.reshape(-1), camera.distortion)
    d = d @ c2w[:, :3].T
    d = d / d.norm(dim=-1, keepdim=True)
    o = c2w[:, 3].expand_as(d)
    return o.to(device=device, dtype=torch.float32).contiguous(), d.to(device=device, dtype=torch.float32).contiguous()


def ray_box(origins: torch.Tensor, dirs: torch.Tensor, box: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Entry and exit distances of rays through an axis-aligned box (exit <= entry: miss)."""
    inv = 1.0 / torch.where(dirs.abs() < 1e-12, torch.full_like(dirs, 1e-12), dirs)
    t0 = (box[0] - origins) * inv
    t1 = (box[1] - origins) * inv
    near = torch.minimum(t0, t1).amax(dim=-1)
    far = torch.maximum(t0, t1).amin(dim=-1)
    return near, far


def march(origins: torch.Tensor, dirs: torch.Tensor, occupancy: OccupancyGrid, step: float,
          near: float = 0.0, perturb: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """Samples of rays in occupied cells: (ray index (S,), distance t (S,)), sorted by ray then t.

    Each ray is clipped to the occupied box and sampled at t = (k + u) * step, k integer,
    u = 0.5 (or uniform random per ray when `perturb`): the samples lie on a lattice
    measured from the ray's origin, not from where it enters the box, so which
    occupancy grid clips the ray (the NeRF's own, or one for a deformed space) does
    not move them, and moving the scene rigidly is exactly moving the camera back.
    """
    n = origins.shape[0]
    dev = origins.device
    empty = (torch.empty(0, dtype=torch.int64, device=dev), torch.empty(0, device=dev))
    if n == 0 or not occupancy.any():
        return empty
    t0, t1 = ray_box(origins, dirs, occupancy.bounds())
    t0 = t0.clamp_min(near)
    hit = t1 > t0
    if not bool(hit.any()):
        return empty
    rays = torch.nonzero(hit).flatten()
    t0, t1 = t0[rays], t1[rays]
    u = torch.rand(rays.shape[0], device=dev) if perturb else torch.full((rays.shape[0],), 0.5, device=dev)
    # The first lattice point at or after the box entry: no sample lies outside the grid.
    t0 = torch.ceil((t0 - u * step) / step) * step
    if backend.use_kernels(dev) and occupancy.mask.device.type == "cpu":
        return march_kernels.march_cpu(origins[rays], dirs[rays], t0, t1, u, step, occupancy, rays)
    k_max = int(math.ceil(float((t1 - t0).max()) / step))
    t = t0[:, None] + (torch.arange(k_max, device=dev, dtype=torch.float32)[None, :] + u[:, None]) * step  # (R, K)
    valid = t < t1[:, None]
    pts = origins[rays][:, None, :] + dirs[rays][:, None, :] * t[..., None]
    valid &= occupancy.occupied(pts.reshape(-1, 3)).reshape(valid.shape)
    r, k = torch.nonzero(valid, as_tuple=True)
    return rays[r], t[r, k]


def _exclusive_transmittance(tau: torch.Tensor, ray_idx: torch.Tensor, n_rays: int) -> torch.Tensor:
    """exp(-sum of tau over the earlier samples of the same ray); samples sorted by ray."""
    tau64 = tau.double()
    excl = torch.cumsum(tau64, 0) - tau64
    counts = torch.bincount(ray_idx, minlength=n_rays)
    starts = torch.cumsum(counts, 0) - counts
    return torch.exp(-(excl - excl[starts[ray_idx]])).to(tau.dtype)


def _segment_sum(values: torch.Tensor, ray_idx: torch.Tensor, n_rays: int) -> torch.Tensor:
    out = torch.zeros((n_rays,) + values.shape[1:], dtype=values.dtype, device=values.device)
    return out.index_add(0, ray_idx, values)


def _density_pass(model, pts, keep_encoding=False, chunk=1 << 18):
    """Density and geometry features of all samples (no grad); with keep_encoding also the encodings."""
    sig, geo, encs, xs = [], [], [], []
    for s in range(0, pts.shape[0], chunk):
        enc, inside, x = model.encode(pts[s: s + chunk])
        a, b = model.features_from_encoding(enc, inside)
        sig.append(a)
        geo.append(b)
        if keep_encoding:
            encs.append(enc)
            xs.append(x)
    if not sig:
        z = pts.new_zeros(0)
        return z, pts.new_zeros(0, model.config.geo_feat_dim + 1), pts.new_zeros(0, model.encoding.out_dim), pts.new_zeros(0, 3)
    def cat(parts):  # no copy in the common single-chunk case
        return parts[0] if len(parts) == 1 else torch.cat(parts)

    return cat(sig), cat(geo), (cat(encs) if keep_encoding else None), (cat(xs) if keep_encoding else None)


def _render_chunk(model, o, d, occ, step, sample_transform, perturb, early_stop_eps, weight_threshold, grad):
    n = o.shape[0]
    ray_idx, t = march(o, d, occ, step, perturb=perturb)
    pts = o[ray_idx] + d[ray_idx] * t[:, None]
    sdirs = d[ray_idx]
    keep = None
    if sample_transform is not None and ray_idx.numel():
        pts, sdirs, keep = sample_transform(pts, sdirs)
    n_density = ray_idx.numel()
    with torch.no_grad():
        if keep is not None and not grad:
            # Samples the transform dropped (vacated or unoccupied rest space) never reach the field.
            kept = torch.nonzero(keep).flatten()
            s_k, g_k, _, _ = _density_pass(model, pts[kept])
            sigma = s_k.new_zeros(pts.shape[0])
            geo = g_k.new_zeros(pts.shape[0], g_k.shape[1])
            sigma[kept], geo[kept] = s_k, g_k
            enc = xn = None
        else:
            sigma, geo, enc, xn = _density_pass(model, pts, keep_encoding=grad)
            if keep is not None:
                sigma = sigma * keep
        trans = _exclusive_transmittance(sigma * step, ray_idx, n)
    if grad:
        # Second pass with autograd on the samples that can still be seen; the encoding of the
        # first pass is reused (only its backward runs) where the CPU kernels apply.
        sel = torch.nonzero((trans > early_stop_eps) & (sigma > 0)).flatten()
        ray_idx, t, sdirs = ray_idx[sel], t[sel], sdirs[sel]
        xs = xn[sel]
        inside = ((xs >= 0) & (xs <= 1)).all(dim=-1)
        sigma, geo = model.features_from_encoding(model.encoding.reuse(enc[sel], xs), inside)
        if keep is not None:
            sigma = sigma * keep[sel]
        rgb = model.color(geo, sdirs)
        tau = sigma * step
        trans = _exclusive_transmittance(tau, ray_idx, n)
        w = trans * (1.0 - torch.exp(-tau))
        n_color = sel.numel()
    else:
        w_all = trans * (1.0 - torch.exp(-sigma * step))
        sel = torch.nonzero(w_all > weight_threshold).flatten()
        ray_idx, t, w = ray_idx[sel], t[sel], w_all[sel]
        rgb = model.color(geo[sel], sdirs[sel]) if sel.numel() else geo.new_zeros(0, 3)
        n_color = sel.numel()
    color = _segment_sum(w[:, None] * rgb, ray_idx, n)
    alpha = _segment_sum(w, ray_idx, n)
    depth = _segment_sum(w * t, ray_idx, n)
    return color, alpha, depth, n_density, n_color


def render_rays(model, origins: torch.Tensor, dirs: torch.Tensor, *, background=None, chunk: int = 4096,
                occupancy: OccupancyGrid | None = None, sample_transform: SampleTransform | None = None,
                step: float | None = None, perturb: bool = False, early_stop_eps: float = 1e-4,
                weight_threshold: float = 1e-4, progress: Callable[[int, int], None] | None = None) -> dict:
    """Render rays (origins (N,3), unit dirs (N,3), world frame) in chunks of `chunk` rays.

    Returns a dict: `color` (N,3) premultiplied (composited on black), `alpha` (N,),
    `depth` (N,), `rgb` (N,3) composited on `background` ((3,) or (N,3); default
    the model's config background), `n_density_samples` and `n_color_samples`
    (ints: samples whose density / colour was evaluated). Differentiable when
    called with gradients enabled (training). `progress(done, total)` is called
    after each chunk; raising from it cancels the render.
    """
    occ = occupancy if occupancy is not None else model.occupancy
    step = float(step if step is not None else model.config.render_step)
    grad = torch.is_grad_enabled()
    outs, n_den, n_col = [], 0, 0
    total = origins.shape[0]
    for s in range(0, total, chunk):
        c, a, dp, nd, nc = _render_chunk(model, origins[s: s + chunk], dirs[s: s + chunk], occ, step,
                                         sample_transform, perturb, early_stop_eps, weight_threshold, grad)
        outs.append((c, a, dp))
        n_den += nd
        n_col += nc
        if progress is not None:
            progress(min(s + chunk, total), total)
    if outs:
        color = torch.cat([x[0] for x in outs])
        alpha = torch.cat([x[1] for x in outs])
        depth = torch.cat([x[2] for x in outs])
    else:
        color, alpha, depth = origins.new_zeros(0, 3), origins.new_zeros(0), origins.new_zeros(0)
    if background is None:
        background = model.config.background
    bg = torch.as_tensor(background, dtype=color.dtype, device=color.device)
    rgb = color + (1.0 - alpha)[:, None] * bg
    depth = torch.where(alpha > 1e-6, depth / alpha.clamp_min(1e-6), torch.zeros_like(depth))
    return {"color": color, "alpha": alpha, "depth": depth, "rgb": rgb,
            "n_density_samples": n_den, "n_color_samples": n_col}


@torch.no_grad()
def render_image(model, camera: Camera, background=None, chunk: int = 4096, **kwargs) -> dict:
    """Render one frame. Returns numpy arrays: `rgba` (H,W,4) float straight alpha, `rgb` (H,W,3)
    composited on `background`, `depth` (H,W), and floats `density_samples_per_ray`,
    `color_samples_per_ray`. kwargs go to `render_rays` (occupancy, sample_transform, progress, ...).
    """
    o, d = camera_rays(camera, device=model.device)
    out = render_rays(model, o, d, background=background, chunk=chunk, **kwargs)
    h, w = camera.height, camera.width
    alpha = out["alpha"].clamp(0, 1)
    straight = torch.where(alpha[:, None] > 1e-6, out["color"] / alpha.clamp_min(1e-6)[:, None], torch.zeros_like(out["color"]))
    rgba = torch.cat([straight.clamp(0, 1), alpha[:, None]], dim=-1).reshape(h, w, 4)
    n = max(1, h * w)
    return {"rgba": rgba.cpu().numpy(), "rgb": out["rgb"].clamp(0, 1).reshape(h, w, 3).cpu().numpy(),
            "depth": out["depth"].reshape(h, w).cpu().numpy(),
            "density_samples_per_ray": out["n_density_samples"] / n, "color_samples_per_ray": out["n_color_samples"] / n}
