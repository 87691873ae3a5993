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

Sampling (march_kernels.py): each ray is clipped to the box of the occupied cells and
marched with a constant step (`config.render_step`) on a lattice measured from its
origin; only samples in occupied cells are kept. An unbounded NeRF's rays also march
through its background grid before and after the box, with steps growing with the
distance from the box, out to `contraction.FAR_RADIUS` inner half-sizes. Each sample
carries its own step length. Hooks for ray bending:

- `occupancy=`: any `OccupancyGrid` (e.g. of a deformed space) instead of the model's own
  inner grid (an unbounded NeRF's background grid is used as it is);
- `sample_transform(positions[S,3], dirs[S,3]) -> (positions, dirs, keep[S])` or
  `(positions, dirs, keep, density_scale[S])`: called between sampling and the field
  query; samples with keep False get density 0, and with a `density_scale` each sample's
  density is multiplied by it (ray bending: the rest-space length of the step, so a shell
  stretched or squashed across the ray keeps its opacity).

Early ray termination, in rounds: a chunk's live rays are marched a few occupied
samples at a time (k per ray, growing as rays retire, ~*_SAMPLES_PER_ROUND per round),
those samples' density is evaluated, and rays whose transmittance fell below
`early_stop_eps` retire before the next round. So a ray stops marching at the first
opaque surface, also in real captures where every cell is occupied. Without gradients
the colour MLP runs only on samples whose weight exceeds `weight_threshold`; with
gradients (training) the samples that can still be seen are re-evaluated with autograd.

Depth is the expected distance along the (unit) ray direction, divided by alpha;
0 where alpha is 0.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable

import numpy as np
import torch

from .. import backend
from ..launch_count import read_back, to_host
from ..memory import check_memory
from . import composite_kernels, march_kernels
from .camera import Camera  # noqa: F401  (re-exported: renderer.Camera is part of the interface)
from .contraction import FAR_RADIUS
from .lens import camera_directions
from .occupancy import OccupancyGrid
from .substeps import check_substeps

SampleTransform = Callable[[torch.Tensor, torch.Tensor], tuple]


def camera_rays(camera: Camera, device="cpu") -> tuple[torch.Tensor, torch.Tensor]:
    """World-space origins (H*W, 3) and unit directions (H*W, 3), row-major from the top-left pixel."""
    pixels = torch.arange(camera.width * camera.height, dtype=torch.int64)
    return pixel_rays(camera, pixels, device)


def pixel_rays(camera: Camera, pixels: torch.Tensor, device="cpu") -> tuple[torch.Tensor, torch.Tensor]:
    """`camera_rays` of the given pixels only (flat row-major indices j * width + i)."""
    c2w = torch.as_tensor(np.asarray(camera.c2w, dtype=np.float64)[:3, :4], dtype=torch.float64)
    ii = (pixels % camera.width).to(torch.float64) + 0.5
    jj = torch.div(pixels, camera.width, rounding_mode="floor").to(torch.float64) + 0.5
    d = camera_directions(camera.fx, camera.fy, camera.cx, camera.cy, ii, jj, camera.distortion)
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


BG_STEP_FACTOR = 2.0  # background step at the inner box: this many inner steps, growing with distance
# Samples marched per round of a chunk (k per live ray adapts to it). A ray ends inside its last round,
# so smaller rounds evaluate fewer samples past the surface but pay more rounds; frames and training
# weigh that differently.
TRAIN_SAMPLES_PER_ROUND, RENDER_SAMPLES_PER_ROUND = 1 << 16, 1 << 13
K_MIN, K_MAX = 8, 512
# Rays retire below this transmittance, and (rendering) samples below this weight skip the colour MLP.
# A larger value renders faster at the same PSNR, but consecutive frames of a slow twist then change
# less evenly: frames keep 1e-4, which an animation needs more than the speed. Callers may pass their own.
TRAIN_EARLY_STOP = RENDER_EARLY_STOP = 1e-4

# Frames (no gradients) on the "fast" path: `render_image` renders the frame in tiles of
# TILE x TILE pixels, FRAME_CHUNK rays at a time (tiles keep neighbouring rays together, so the hash
# rows of a block of samples stay in cache, and large chunks pay the per-round Python overhead once
# for many rays); a ray's k-th round marches FRAME_ROUND_K[k] samples (the last value repeats), the
# same whatever else is in its chunk, so a frame does not depend on how it is cut into chunks. A round
# evaluates at most FRAME_ROUND_BUDGET samples (k shrinks, never below FRAME_ROUND_K[0], for chunks of
# rays that all live long: memory stays bounded). "legacy": the renderer before tiles (4096-ray
# chunks in row order, k from RENDER_SAMPLES_PER_ROUND), kept to measure against.
RENDER_PATHS = ("fast", "legacy")
_render_path = "fast"
TILE = 32
FRAME_CHUNK = 1 << 16
FRAME_CHUNK_CUDA = 1 << 18  # on CUDA a round's cost is its launches: fewer, larger chunks
FRAME_ROUND_K = (4, 4, 4, 4, 8, 8, 16, 16, 32, 32, 64, 64, 128, 128, 256, 256, 512)
FRAME_ROUND_BUDGET = 1 << 20


@contextlib.contextmanager
def render_path(name: str):
    """Render frames in the block on one path: "fast" (the default) or "legacy" (benchmarks, tests)."""
    global _render_path
    if name not in RENDER_PATHS:
        raise ValueError(f"render path must be one of {RENDER_PATHS}, got {name!r}")
    previous, _render_path = _render_path, name
    try:
        yield
    finally:
        _render_path = previous


def _grids(model, occupancy: OccupancyGrid, step: float, background: bool) -> march_kernels.Grids:
    box = occupancy.aabb.reshape(2, 3)
    g = march_kernels.Grids(
        lo=box[0].contiguous(),
        scale=(occupancy.resolution / (box[1] - box[0])).contiguous(),
        res=occupancy.resolution,
        mask=occupancy.mask,
        step=float(step),
    )
    if _render_path == "fast" and occupancy.mask.device.type == "cpu":
        g.coarse, g.coarse_res = occupancy.coarse_blocks()
    bg = getattr(model, "background", None) if background else None
    if bg is not None:
        g.has_bg = True
        g.center, g.inv_half = bg.center.contiguous(), (1.0 / bg.half).contiguous()
        g.bg_res, g.bg_mask, g.bg_step = bg.resolution, bg.mask, float(step) * BG_STEP_FACTOR
    return g


def march_setup(
    origins: torch.Tensor,
    dirs: torch.Tensor,
    occupancy: OccupancyGrid,
    grids: march_kernels.Grids,
    near: float = 0.0,
    perturb: bool = False,
) -> march_kernels.MarchState:
    """Where each ray starts: its segment ends and phase (`march_kernels.MarchState`).

    In the box the samples are t = (j + u) * step, j integer, u = 0.5 (or uniform random per ray
    when `perturb`): a lattice measured from the ray's origin, not from where it enters the box,
    so which occupancy grid clips the ray (the NeRF's own, or one for a deformed space) does not
    move them, and moving the scene rigidly is exactly moving the camera back.
    """
    n, dev, step = origins.shape[0], origins.device, grids.step
    u = torch.rand(n, device=dev) if perturb else torch.full((n,), 0.5, device=dev)
    if backend.use_triton(dev) and origins.dtype == dirs.dtype == torch.float32:
        from . import march_triton

        phase, j0, j1, t, t_in, t_out, t_far = march_triton.march_setup(
            origins, dirs, u, occupancy.bounds(), grids, near, march_kernels.MAX_STEPS_PER_RAY, FAR_RADIUS
        )
        return march_kernels.MarchState(phase=phase, j=j0, j_end=j1, t=t, t_in=t_in, t_out=t_out, t_far=t_far, u=u)
    # (The device path does not ask whether any cell is occupied, a read back: with none, the bounds are the
    # whole box and the march finds no sample.)
    if not backend.use_kernels(dev) or occupancy.any():
        t_in, t_out = ray_box(origins, dirs, occupancy.bounds())
    else:
        t_in = t_out = torch.zeros(n, device=dev)
    t_in = t_in.clamp_min(near)
    hit = t_out > t_in
    # Lattice indices of the first sample at or after the entry and one past the last before the exit.
    t_in64, t_out64, u64 = t_in.double(), t_out.double(), u.double()
    j0 = torch.ceil(t_in64 / step - u64)
    j1 = torch.ceil(t_out64 / step - u64)
    bad = ~hit | ~torch.isfinite(j0) | ~torch.isfinite(j1) | (j1 - j0 > march_kernels.MAX_STEPS_PER_RAY)
    j0 = torch.where(
        bad, torch.zeros_like(j0), j0.clamp(-march_kernels.MAX_STEPS_PER_RAY, march_kernels.MAX_STEPS_PER_RAY)
    )
    j1 = torch.where(
        bad, torch.zeros_like(j1), j1.clamp(-march_kernels.MAX_STEPS_PER_RAY, march_kernels.MAX_STEPS_PER_RAY)
    )
    j0, j1 = j0.long(), torch.maximum(j0, j1).long()
    if grids.has_bg:
        far_box = torch.stack([grids.center - FAR_RADIUS / grids.inv_half, grids.center + FAR_RADIUS / grids.inv_half])
        _, t_far = ray_box(origins, dirs, far_box)
        t_far = torch.where(torch.isfinite(t_far), t_far, torch.full_like(t_far, near))
        t_in = torch.where(hit, t_in, t_far)
        t_out = torch.where(hit, t_out, t_far)
        if backend.use_kernels(dev):
            phase = torch.full((n,), march_kernels.PHASE_BEFORE, dtype=torch.int8, device=dev)
            phase[~(t_far > near)] = march_kernels.PHASE_DONE
        else:  # the same without boolean indexing (a sync on CUDA)
            phase = torch.where(t_far > near, march_kernels.PHASE_BEFORE, march_kernels.PHASE_DONE).to(torch.int8)
    else:
        t_far = t_out
        phase = torch.where(hit, march_kernels.PHASE_INNER, march_kernels.PHASE_DONE).to(torch.int8)
    return march_kernels.MarchState(
        phase=phase.contiguous(),
        j=j0.contiguous(),
        j_end=j1.contiguous(),
        t=torch.full((n,), float(near), device=dev),
        t_in=t_in.contiguous(),
        t_out=t_out.contiguous(),
        t_far=t_far.contiguous(),
        u=u.contiguous(),
    )


def _round_samples(origins, dirs, alive, state, k, grids):
    """One round of marching: the samples (ray index, t, dt), sorted by ray then t."""
    ts, dts, counts = march_kernels.march_round(origins, dirs, alive, state, k, grids)
    valid = torch.arange(k, device=origins.device)[None, :] < counts.to(origins.device)[:, None]
    a, slot = torch.nonzero(valid, as_tuple=True)
    return alive[a], ts.to(origins.device)[a, slot], dts.to(origins.device)[a, slot]


def march(
    origins: torch.Tensor,
    dirs: torch.Tensor,
    occupancy: OccupancyGrid,
    step: float,
    near: float = 0.0,
    perturb: bool = False,
    model=None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Every sample of the rays in occupied cells, without early termination: (ray index (S,), t (S,)),
    sorted by ray then t. With an unbounded `model`, its background samples too."""
    n, dev = origins.shape[0], origins.device
    grids = _grids(model, occupancy, step, background=model is not None)
    if n == 0 or not (occupancy.any() or grids.has_bg):
        return torch.empty(0, dtype=torch.int64, device=dev), torch.empty(0, device=dev)
    state = march_setup(origins, dirs, occupancy, grids, near, perturb)
    alive = torch.nonzero(state.phase < march_kernels.PHASE_DONE).flatten()
    rays, ts = [torch.empty(0, dtype=torch.int64, device=dev)], [torch.empty(0, device=dev)]
    while alive.numel():
        r, t, _ = _round_samples(origins, dirs, alive, state, K_MAX, grids)
        rays.append(r)
        ts.append(t)
        alive = alive[state.phase[alive] < march_kernels.PHASE_DONE]
    rays, ts = torch.cat(rays), torch.cat(ts)
    order = torch.sort(rays, stable=True).indices
    return rays[order], ts[order]


def _exclusive_transmittance(tau: torch.Tensor, ray_idx: torch.Tensor, n_rays: int) -> torch.Tensor:
    """exp(-sum of tau over the earlier samples of the same ray); samples sorted by ray."""
    if tau.device.type == "cpu" and not tau.requires_grad and backend.use_kernels(tau.device):
        return composite_kernels.exclusive_transmittance(tau, ray_idx)
    tau64 = tau.double()
    excl = torch.cumsum(tau64, 0) - tau64
    counts = torch.bincount(ray_idx, minlength=n_rays)
    starts = torch.cumsum(counts, 0) - counts
    return torch.exp(-(excl - excl[starts[ray_idx]])).to(tau.dtype)


def _segment_sum(values: torch.Tensor, ray_idx: torch.Tensor, n_rays: int) -> torch.Tensor:
    out = torch.zeros((n_rays,) + values.shape[1:], dtype=values.dtype, device=values.device)
    return out.index_add(0, ray_idx, values)


def _composite_samples(sigma, rgb, t, dt, ray_idx, n_rays: int, exclusive_transmittance):
    """(color (n, 3), alpha, depth, w) of a training batch's samples, sorted by ray, with autograd.
    `exclusive_transmittance(tau)`: exp(-sum of tau over each sample's earlier samples on its ray); the
    kernel path and the device path find each ray's first sample differently."""
    tau = sigma * dt
    w = exclusive_transmittance(tau) * (1.0 - torch.exp(-tau))
    color = _segment_sum(w[:, None] * rgb, ray_idx, n_rays)
    return color, _segment_sum(w, ray_idx, n_rays), _segment_sum(w * t, ray_idx, n_rays), w


def _density_pass(model, pts, keep_encoding=False, chunk=1 << 18):
    """Density and geometry features of all samples (no grad); with keep_encoding also the encodings."""
    sig, geo, encs, xs = [], [], [], []
    for s in range(0, pts.shape[0], chunk):
        enc, inside, x = model.encode(pts[s : s + chunk])
        a, b = model.features_from_encoding(enc, inside)
        sig.append(a)
        geo.append(b)
        if keep_encoding:
            encs.append(enc)
            xs.append(x)
    if not sig:
        z = pts.new_zeros(0)
        return (
            z,
            pts.new_zeros(0, model.config.geo_feat_dim + 1),
            pts.new_zeros(0, model.encoding.out_dim),
            pts.new_zeros(0, 3),
        )

    def cat(parts):  # no copy in the common single-chunk case
        return parts[0] if len(parts) == 1 else torch.cat(parts)

    return cat(sig), cat(geo), (cat(encs) if keep_encoding else None), (cat(xs) if keep_encoding else None)


def _render_chunk(
    model,
    o,
    d,
    occ,
    step,
    sample_transform,
    perturb,
    early_stop_eps,
    weight_threshold,
    grad,
    near,
    samples_out=None,
    appearance=None,
    samples_per_round=TRAIN_SAMPLES_PER_ROUND,
):
    """Rays in rounds: march a few samples per live ray, evaluate them, retire the rays whose
    transmittance is spent, march on with the others."""
    n, dev = o.shape[0], o.device
    # Rays that carry a gradient (camera pose refinement) are marched as data; the second pass below
    # places the kept samples on them again, differentiably (unbent samples only: a bent one is not a
    # function of its ray alone).
    rays_grad = grad and sample_transform is None and (o.requires_grad or d.requires_grad)
    o_rays, d_rays = o, d
    o, d = o.detach(), d.detach()
    color, alpha, depth = o.new_zeros(n, 3), o.new_zeros(n), o.new_zeros(n)
    grids = _grids(model, occ, step, background=True)
    if n == 0 or not (occ.any() or grids.has_bg):
        return color, alpha, depth, 0, 0
    state = march_setup(o, d, occ, grids, near, perturb)
    alive = torch.nonzero(state.phase < march_kernels.PHASE_DONE).flatten()
    transmittance = torch.ones(n, dtype=torch.float64, device=dev)
    n_density = n_color = 0
    kept_parts = []  # with gradients: the samples to re-evaluate, per round
    while alive.numel():
        k = int(min(K_MAX, max(K_MIN, samples_per_round // alive.numel())))
        ts, dts, counts = march_kernels.march_round(o, d, alive, state, k, grids)
        ray_idx, t, dt, pts, sdirs = march_kernels.gather_samples(o, d, alive, ts, dts, counts)
        del ts, dts
        if ray_idx.numel():
            keep = density_scale = None
            if sample_transform is not None:
                pts, sdirs, keep, *extra = sample_transform(pts, sdirs)
                density_scale = extra[0] if extra else None
            with torch.no_grad():
                if keep is not None and not grad:
                    # Samples the transform dropped (vacated or unoccupied rest space) never reach the field.
                    kept = torch.nonzero(keep).flatten()
                    s_k, g_k, _, _ = _density_pass(model, pts[kept])
                    sigma = s_k.new_zeros(pts.shape[0])
                    geo = g_k.new_zeros(pts.shape[0], g_k.shape[1])
                    sigma[kept], geo[kept] = s_k, g_k
                    enc = xn = None
                    n_density += kept.numel()
                else:
                    sigma, geo, enc, xn = _density_pass(model, pts, keep_encoding=grad)
                    if keep is not None:
                        sigma = sigma * keep
                    n_density += ray_idx.numel()
                if density_scale is not None:
                    sigma = sigma * density_scale
                    if grad:  # the second pass multiplies sigma by keep: let it carry the scale
                        keep = density_scale if keep is None else keep * density_scale
                tau = sigma * dt
                trans = _exclusive_transmittance(tau, ray_idx, n) * transmittance[ray_idx].to(tau.dtype)
            if grad:
                sel = torch.nonzero((trans > early_stop_eps) & (sigma > 0)).flatten()
                kept_parts.append(
                    (ray_idx[sel], t[sel], dt[sel], enc[sel], xn[sel], sdirs[sel], None if keep is None else keep[sel])
                )
            else:
                w_all = trans * (1.0 - torch.exp(-tau))
                sel = torch.nonzero(w_all > weight_threshold).flatten()
                if sel.numel():
                    r_s, w = ray_idx[sel], w_all[sel]
                    rgb = model.color(geo[sel], sdirs[sel], None if appearance is None else appearance[r_s])
                    color.index_add_(0, r_s, w[:, None] * rgb)
                    alpha.index_add_(0, r_s, w)
                    depth.index_add_(0, r_s, w * t[sel])
                    n_color += sel.numel()
            transmittance *= torch.exp(-_segment_sum(tau.double(), ray_idx, n))
        alive = alive[(state.phase[alive] < march_kernels.PHASE_DONE) & (transmittance[alive] > early_stop_eps)]
    if not grad:
        # The thresholds skip weight: samples below weight_threshold get no colour, and a retired ray
        # leaves its last transmittance unspent. Alpha is what the ray really absorbed (1 once retired),
        # and the skipped weight takes the colour and depth of the weight that was kept: without this a
        # foggy or cut ray would fade towards the background colour.
        absorbed = (1.0 - transmittance).to(alpha.dtype)
        absorbed = torch.where(transmittance <= early_stop_eps, torch.ones_like(absorbed), absorbed)
        scale = torch.where(alpha > 1e-6, absorbed / alpha.clamp_min(1e-6), torch.zeros_like(alpha))
        return color * scale[:, None], alpha * scale, depth * scale, n_density, n_color
    if not kept_parts:
        return color, alpha, depth, n_density, 0
    if len(kept_parts) == 1:  # one round: its samples are already sorted by ray, then t
        ray_idx, t, dt, enc, xs, sdirs, keep = kept_parts[0]
    else:
        ray_idx, t, dt, enc, xs, sdirs, keep = (torch.cat(p) if p[0] is not None else None for p in zip(*kept_parts))
        order = torch.sort(ray_idx, stable=True).indices  # rounds came ray-interleaved: back to ray, then t
        ray_idx, t, dt, enc, xs, sdirs = ray_idx[order], t[order], dt[order], enc[order], xs[order], sdirs[order]
        keep = None if keep is None else keep[order]
    # Second pass with autograd on the samples that can still be seen; the encoding of the first
    # pass is reused (only its backward runs) where the CPU kernels apply.
    if rays_grad:  # the same samples, as functions of the rays: the positions get a gradient too
        sdirs = d_rays[ray_idx]
        xs = model.normalize(o_rays[ray_idx] + sdirs * t[:, None])
    inside = ((xs >= 0) & (xs <= 1)).all(dim=-1)
    sigma, geo = model.features_from_encoding(model.encoding.reuse(enc, xs), inside)
    if keep is not None:
        sigma = sigma * keep
    rgb = model.color(geo, sdirs, None if appearance is None else appearance[ray_idx])
    color, alpha, depth, w = _composite_samples(
        sigma, rgb, t, dt, ray_idx, n, lambda tau: _exclusive_transmittance(tau, ray_idx, n)
    )
    if samples_out is not None:
        samples_out.append((ray_idx, t, dt, w))
    return color, alpha, depth, n_density, ray_idx.numel()


# The MLPs of a frame run on blocks of this many samples: a block's activations stay in cache, which
# makes both MLPs several times faster than on a whole round of samples at once.
FIELD_BLOCK = 8192


def blocked_density(model, pts):
    """Density and geometry features of samples (no grad), encoded and evaluated FIELD_BLOCK at a time."""
    n = pts.shape[0]
    if n <= FIELD_BLOCK:
        enc, inside, _ = model.encode(pts)
        return model.features_from_encoding(enc, inside)
    sigma = pts.new_empty(n)
    geo = pts.new_empty(n, model.config.geo_feat_dim + 1)
    for s in range(0, n, FIELD_BLOCK):
        enc, inside, _ = model.encode(pts[s : s + FIELD_BLOCK])
        sigma[s : s + FIELD_BLOCK], geo[s : s + FIELD_BLOCK] = model.features_from_encoding(enc, inside)
    return sigma, geo


def blocked_color(model, geo, dirs, codes=None):
    n = geo.shape[0]
    if n <= FIELD_BLOCK:
        return model.color(geo, dirs, codes)
    rgb = geo.new_empty(n, 3)
    for s in range(0, n, FIELD_BLOCK):
        rgb[s : s + FIELD_BLOCK] = model.color(
            geo[s : s + FIELD_BLOCK], dirs[s : s + FIELD_BLOCK], None if codes is None else codes[s : s + FIELD_BLOCK]
        )
    return rgb


def _split_transform(result):
    """A sample_transform's answer: (positions, dirs, keep, density_scale or None)."""
    pts, sdirs, keep, *extra = result
    return pts, sdirs, keep, (extra[0] if extra else None)


def _render_chunk_frame(
    model, o, d, occ, step, sample_transform, early_stop_eps, weight_threshold, near, appearance=None
):
    """A chunk of a frame without gradients ("fast" path): rounds of FRAME_ROUND_K samples per live ray;
    only the samples the transform keeps reach the field and the compositing (a dropped sample has no
    density: it changes neither weight nor transmittance); fused CPU kernels where they apply."""
    n, dev = o.shape[0], o.device
    color, alpha, depth = o.new_zeros(n, 3), o.new_zeros(n), o.new_zeros(n)
    grids = _grids(model, occ, step, background=True)
    if n == 0 or not (occ.any() or grids.has_bg):
        return color, alpha, depth, 0, 0
    kernels = o.device.type == "cpu" and backend.use_kernels(o.device)
    state = march_setup(o, d, occ, grids, near, False)
    alive = torch.nonzero(state.phase < march_kernels.PHASE_DONE).flatten()
    transmittance = torch.ones(n, dtype=torch.float64, device=dev)
    n_density = n_color = 0
    rounds = 0
    while alive.numel():
        k = FRAME_ROUND_K[min(rounds, len(FRAME_ROUND_K) - 1)]
        k = max(FRAME_ROUND_K[0], min(k, FRAME_ROUND_BUDGET // alive.numel()))
        rounds += 1
        ts, dts, counts = march_kernels.march_round(o, d, alive, state, k, grids)
        ray_idx, t, dt, pts, sdirs = march_kernels.gather_samples(o, d, alive, ts, dts, counts)
        del ts, dts
        if ray_idx.numel():
            scale = None
            if sample_transform is not None:
                pts, sdirs, keep, scale = _split_transform(sample_transform(pts, sdirs))
                kept = torch.nonzero(keep).flatten()
                if kept.numel() < keep.numel():
                    ray_idx, t, dt, pts, sdirs = ray_idx[kept], t[kept], dt[kept], pts[kept], sdirs[kept]
                    scale = None if scale is None else scale[kept]
            sigma, geo = blocked_density(model, pts)
            n_density += ray_idx.numel()
            if scale is not None:
                sigma = sigma * scale
            if kernels:
                w, sel = composite_kernels.composite_round(sigma, dt, ray_idx, transmittance, weight_threshold)
            else:
                tau = sigma * dt
                trans = _exclusive_transmittance(tau, ray_idx, n) * transmittance[ray_idx].to(tau.dtype)
                w = trans * (1.0 - torch.exp(-tau))
                sel = torch.nonzero(w > weight_threshold).flatten()
                transmittance *= torch.exp(-_segment_sum(tau.double(), ray_idx, n))
            if sel.numel():
                r_s = ray_idx[sel]
                rgb = blocked_color(model, geo[sel], sdirs[sel], None if appearance is None else appearance[r_s])
                if kernels:
                    composite_kernels.accumulate(sel, ray_idx, w, t, rgb, color, alpha, depth)
                else:
                    w_s = w[sel]
                    color.index_add_(0, r_s, w_s[:, None] * rgb)
                    alpha.index_add_(0, r_s, w_s)
                    depth.index_add_(0, r_s, w_s * t[sel])
                n_color += sel.numel()
        alive = alive[(state.phase[alive] < march_kernels.PHASE_DONE) & (transmittance[alive] > early_stop_eps)]
    # As in _render_chunk: alpha is what the ray absorbed, the skipped weight takes the kept colour and depth.
    absorbed = (1.0 - transmittance).to(alpha.dtype)
    absorbed = torch.where(transmittance <= early_stop_eps, torch.ones_like(absorbed), absorbed)
    scale = torch.where(alpha > 1e-6, absorbed / alpha.clamp_min(1e-6), torch.zeros_like(alpha))
    return color * scale[:, None], alpha * scale, depth * scale, n_density, n_color


# The device path (CUDA; the CPU without numba) marches a training batch in one round: a bounded ray's box
# segment ends within it, and the background gets this many steps (a ray longer than that is cut).
TRAIN_BG_STEPS = 1024


def box_steps(occupancy: OccupancyGrid, step: float) -> int:
    """A bound on the lattice steps of any ray's segment through the grid's box (its diagonal, plus rounding),
    known on the host: read from the device once per grid."""
    cached = occupancy.__dict__.get("_box_steps")
    if cached is None or cached[0] is not occupancy.aabb or cached[1] != step:
        lo, hi = (np.asarray(v, dtype=np.float64) for v in occupancy.aabb.reshape(2, 3).tolist())
        steps = int(np.ceil(np.linalg.norm(hi - lo) / step)) + 2
        cached = occupancy.__dict__["_box_steps"] = (occupancy.aabb, step, steps)
    return cached[2]


def flat_samples(o, d, alive, ts, dts, counts, size: int):
    """A round's samples, flat and sorted by ray then t, in `size` slots, sizes known on the host: (row in
    alive, ray index, t, dt, position, direction, valid, first slot of each row). Slots past the samples'
    number are not valid (their ray is the last row's, their t a sample of it); samples past `size` are cut."""
    dev = o.device
    a_n, k = ts.shape
    end = torch.cumsum(counts, 0)
    q = torch.arange(size, device=dev)
    row = torch.searchsorted(end, q, right=True).clamp_max(max(a_n - 1, 0))
    first = end - counts
    slot = (q - first[row]).clamp(0, max(k - 1, 0))
    valid = q < end[-1] if a_n else torch.zeros(size, dtype=torch.bool, device=dev)
    ray = alive[row]
    t = ts[row, slot]
    return row, ray, t, dts[row, slot], o[ray] + d[ray] * t[:, None], d[ray], valid, first


def _segment_exclusive(tau: torch.Tensor, row: torch.Tensor, first: torch.Tensor) -> torch.Tensor:
    """exp(-sum of tau over the earlier samples of the same row); samples sorted by row, `first[row]` the
    first sample of each row (no count read back, unlike bincount)."""
    tau64 = tau.double()
    excl = torch.cumsum(tau64, 0) - tau64
    return torch.exp(-(excl - excl[first.clamp_max(max(tau.shape[0] - 1, 0))[row]])).to(tau.dtype)


def _render_chunk_device(
    model,
    o,
    d,
    occ,
    step,
    sample_transform,
    perturb,
    early_stop_eps,
    weight_threshold,
    grad,
    near,
    samples_out=None,
    appearance=None,
    max_samples=None,
):
    """The device path (CUDA; the CPU without numba): what `_render_chunk` and `_render_chunk_frame` compute, with
    sizes known on the host, so that the host waits for the device once per round at most.

    Frames march in rounds (FRAME_ROUND_K samples per live ray); a round reads back two numbers, its sample
    count and how many rays march on (`read_back`), and everything else is masks, prefix sums and scatters: the
    samples the transform drops or that are too faint for colour are masked, not removed. With gradients
    (training) the whole batch is one round with no read back at all: every ray marched to its end (box
    segment, TRAIN_BG_STEPS background steps), its samples in `max_samples` slots (default: every sample
    the march can give); the samples the rays can still see carry the gradient. Counts come back as 0-dim
    tensors, read with the caller's own (`render_rays`, the trainer)."""
    n, dev = o.shape[0], o.device
    rays_grad = grad and sample_transform is None and (o.requires_grad or d.requires_grad)
    o_rays, d_rays = o, d
    o, d = o.detach(), d.detach()
    color, alpha, depth = o.new_zeros(n, 3), o.new_zeros(n), o.new_zeros(n)
    zero = torch.zeros((), dtype=torch.int64, device=dev)
    grids = _grids(model, occ, step, background=True)
    if n == 0:
        return color, alpha, depth, zero, zero
    state = march_setup(o, d, occ, grids, near, perturb)
    steps = box_steps(occ, step)
    alive = torch.arange(n, device=dev)
    active = state.phase < march_kernels.PHASE_DONE
    transmittance = torch.ones(n, dtype=torch.float64, device=dev)
    n_density, n_color = zero, zero
    rounds = 0
    while alive.numel():
        if grad:
            k = steps + (TRAIN_BG_STEPS if grids.has_bg else 0)
            bg_per_block = -(-TRAIN_BG_STEPS // max(1, -(-steps // 128)))
            ts, dts, counts = march_kernels.march_round_device(
                o, d, alive, active, state, k, grids, steps, bg_per_block=bg_per_block
            )
            size = alive.numel() * k if max_samples is None else min(int(max_samples), alive.numel() * k)
            n_live = 0
        else:
            k = FRAME_ROUND_K[min(rounds, len(FRAME_ROUND_K) - 1)]
            k = max(FRAME_ROUND_K[0], min(k, FRAME_ROUND_BUDGET // alive.numel()))
            # (Frames on the torch formulation, without Triton: the march may wait for the device per block.)
            ts, dts, counts = march_kernels.march_round_device(o, d, alive, active, state, k, grids, steps, settle=True)
            marching = active & (state.phase[alive] < march_kernels.PHASE_DONE)
            size, n_live = (int(v) for v in read_back(counts.sum(), marching.sum()))  # the round's one sync
        rounds += 1
        if size:
            row, ray_idx, t, dt, pts, sdirs, valid, first = flat_samples(o, d, alive, ts, dts, counts, size)
            keep = scale = None
            if sample_transform is not None:
                pts, sdirs, keep, scale = _split_transform(sample_transform(pts, sdirs))
            live = valid if keep is None else valid & keep
            with torch.no_grad():
                sigma, geo, enc, xn = _density_pass(model, pts, keep_encoding=grad)
                sigma = sigma * live
                if scale is not None:
                    sigma = sigma * scale
                n_density = n_density + live.sum()
            codes = None if appearance is None or grad else appearance[ray_idx]  # (training: the second pass)
            if not grad and backend.use_triton(dev):
                # The round's compositing in one kernel (weights, pixels, the transmittance carried on).
                from . import composite_triton

                rgb = blocked_color(model, geo, sdirs, codes)
                n_color = n_color + composite_triton.composite_round(
                    sigma, dt, t, rgb, first, counts, alive, transmittance, color, alpha, depth, weight_threshold
                )
            else:
                with torch.no_grad():
                    tau = sigma * dt
                    trans = _segment_exclusive(tau, row, first) * transmittance[ray_idx].to(tau.dtype)
                if grad:
                    # The samples a ray can still see: the only ones whose gradient is not ~0.
                    seen = (trans > early_stop_eps) & (sigma > 0)
                    factor = seen.to(sigma.dtype) if scale is None else seen * scale
                    kept = (ray_idx, t, dt, enc, xn, sdirs, factor, seen, row, first)
                else:
                    w = trans * (1.0 - torch.exp(-tau))
                    lit = w > weight_threshold
                    rgb = blocked_color(model, geo, sdirs, codes)
                    w = torch.where(lit, w, 0.0)
                    color.index_add_(0, ray_idx, w[:, None] * rgb)
                    alpha.index_add_(0, ray_idx, w)
                    depth.index_add_(0, ray_idx, w * t)
                    n_color = n_color + lit.sum()
                if not grad:  # (training marches one round: nothing carries on)
                    transmittance *= torch.exp(-_segment_sum(tau.double(), ray_idx, n))
        if grad:
            break
        # Rays march on unless done or spent; how many (n_live) came with the round's read back.
        marching_rows = torch.nonzero_static(marching, size=n_live).flatten()
        alive = alive[marching_rows]
        active = transmittance[alive] > early_stop_eps
    if not grad:
        # As in _render_chunk_frame: alpha is what the ray absorbed, the skipped weight takes the kept colour.
        absorbed = (1.0 - transmittance).to(alpha.dtype)
        absorbed = torch.where(transmittance <= early_stop_eps, torch.ones_like(absorbed), absorbed)
        scale = torch.where(alpha > 1e-6, absorbed / alpha.clamp_min(1e-6), torch.zeros_like(alpha))
        return color * scale[:, None], alpha * scale, depth * scale, n_density, n_color
    if not size:
        return color, alpha, depth, n_density, zero
    ray_idx, t, dt, enc, xs, sdirs, factor, seen, row, first = kept
    # Second pass with autograd on every sample, those the rays cannot see weighted 0 (masked, not removed).
    if rays_grad:
        sdirs = d_rays[ray_idx]
        xs = model.normalize(o_rays[ray_idx] + sdirs * t[:, None])
    inside = ((xs >= 0) & (xs <= 1)).all(dim=-1)
    sigma, geo = model.features_from_encoding(model.encoding.reuse(enc, xs), inside)
    sigma = sigma * factor
    rgb = model.color(geo, sdirs, None if appearance is None else appearance[ray_idx])
    if backend.use_triton(dev) and rgb.dtype == sigma.dtype == torch.float32:
        # Weights and pixels, forward and backward, in one kernel each (the batch is one round: rows are
        # rays, `counts` and `alive` that round's).
        from . import composite_triton

        color, alpha, depth, w = composite_triton.CompositeTrain.apply(sigma, rgb, dt, t, first, counts, alive, n)
    else:
        color, alpha, depth, w = _composite_samples(
            sigma, rgb, t, dt, ray_idx, n, lambda tau: _segment_exclusive(tau, row, first)
        )
    if samples_out is not None:
        samples_out.append((ray_idx, t, dt, w))
    return color, alpha, depth, n_density, seen.sum()


def render_rays(
    model,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    *,
    background=None,
    chunk: int = 4096,
    occupancy: OccupancyGrid | None = None,
    sample_transform: SampleTransform | None = None,
    step: float | None = None,
    perturb: bool = False,
    early_stop_eps: float | None = None,
    weight_threshold: float | None = None,
    near: float | None = None,
    return_samples: bool = False,
    appearance: torch.Tensor | None = None,
    progress: Callable[[int, int], None] | None = None,
    max_samples: int | None = None,
) -> dict:
    """Render rays (origins (N,3), unit dirs (N,3), world frame) in chunks of `chunk` rays.

    Returns a dict: `color` (N,3) premultiplied (composited on black), `alpha` (N,),
    `depth` (N,), `rgb` (N,3) composited on `background` ((3,) or (N,3); default
    the model's config background), `n_density_samples` and `n_color_samples`
    (ints: samples whose density / colour was evaluated). Differentiable when
    called with gradients enabled (training). `progress(done, total)` is called
    after each chunk; raising from it cancels the render. `near` defaults to the
    model's `near_plane`, the thresholds to TRAIN_EARLY_STOP / RENDER_EARLY_STOP.
    `appearance` (N, appearance_dim): each ray's image code (training; frames use the mean code).
    With `return_samples` (and gradients) also `samples`: (ray index, t, dt, weight)
    of the composited samples, sorted by ray then t (the distortion loss reads them).
    On the device path (CUDA; `backend.use_kernels` false) with gradients, the sample counts are 0-dim
    tensors (the caller reads them with its own values, in one sync), the samples include masked ones of
    weight 0, and `max_samples` bounds the samples a chunk holds (a training step sizes it from the last).
    """
    occ = occupancy if occupancy is not None else model.occupancy
    step = float(step if step is not None else model.config.render_step)
    near = float(model.config.near_plane if near is None else near)
    grad = torch.is_grad_enabled()
    if early_stop_eps is None:
        early_stop_eps = TRAIN_EARLY_STOP if grad else RENDER_EARLY_STOP
    if weight_threshold is None:
        weight_threshold = RENDER_EARLY_STOP
    samples = [] if return_samples and grad else None
    n_chunks_with_samples = 0
    outs, n_den, n_col = [], 0, 0
    total = origins.shape[0]
    frame = not grad and not perturb and _render_path == "fast"
    device_path = _render_path == "fast" and not backend.use_kernels(origins.device)
    for s in range(0, total, chunk):
        o, d = origins[s : s + chunk], dirs[s : s + chunk]
        codes = None if appearance is None else appearance[s : s + chunk]
        if device_path:
            c, a, dp, nd, nc = _render_chunk_device(
                model,
                o,
                d,
                occ,
                step,
                sample_transform,
                perturb,
                early_stop_eps,
                weight_threshold,
                grad,
                near,
                samples,
                codes,
                max_samples,
            )
        elif frame:
            c, a, dp, nd, nc = _render_chunk_frame(
                model,
                o,
                d,
                occ,
                step,
                sample_transform,
                early_stop_eps,
                weight_threshold,
                near,
                codes,
            )
        else:
            c, a, dp, nd, nc = _render_chunk(
                model,
                o,
                d,
                occ,
                step,
                sample_transform,
                perturb,
                early_stop_eps,
                weight_threshold,
                grad,
                near,
                samples,
                codes,
                TRAIN_SAMPLES_PER_ROUND if grad else RENDER_SAMPLES_PER_ROUND,
            )
        if samples is not None and len(samples) > n_chunks_with_samples:
            n_chunks_with_samples = len(samples)
            samples[-1] = (samples[-1][0] + s,) + samples[-1][1:]  # ray indices of the whole batch
        outs.append((c, a, dp))
        n_den += nd
        n_col += nc
        if progress is not None:
            progress(min(s + chunk, total), total)
    if device_path and not grad:
        n_den, n_col = (int(v) for v in read_back(n_den, n_col))
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
    out = {
        "color": color,
        "alpha": alpha,
        "depth": depth,
        "rgb": rgb,
        "n_density_samples": n_den,
        "n_color_samples": n_col,
    }
    if samples is not None:
        # With gradients: the samples that were composited (ray index, t, dt, weight), sorted by ray then t.
        out["samples"] = tuple(torch.cat(p) for p in zip(*samples)) if samples else None
    return out


def tile_order(width: int, height: int, tile: int = TILE) -> torch.Tensor:
    """Flat pixel indices (row-major j * width + i) in tile order: tiles of tile x tile pixels row by row,
    row-major inside each tile (the edge tiles are cut to the frame)."""
    j = torch.arange(height, dtype=torch.int64)
    i = torch.arange(width, dtype=torch.int64)
    tiles_x = (width + tile - 1) // tile
    tile_of = (j[:, None] // tile) * tiles_x + i[None, :] // tile
    inside = (j[:, None] % tile) * tile + i[None, :] % tile
    return torch.argsort((tile_of * tile * tile + inside).reshape(-1))


# Peak bytes a frame holds per pixel: `render` to PNG's outputs, tile order and the PNG's copy
# (tools/bench/frame_memory.py measures them), and the worker's answer to Blender in shared memory.
FRAME_BYTES_PER_PIXEL = 120


def check_frame_memory(width: int, height: int) -> None:
    """EngineError, before anything is allocated, for a frame too large for this machine's memory (a frame's
    outputs live in host memory also on CUDA, which holds one chunk's work)."""
    check_memory(
        float(width) * float(height) * FRAME_BYTES_PER_PIXEL,
        f"a {width}x{height} frame",
        "render it smaller (lower the resolution or its percentage)",
    )


@torch.no_grad()
def render_image(model, camera: Camera, background=None, chunk: int | None = None, substeps: int = 1, **kwargs) -> dict:
    """Render one frame. Returns numpy arrays: `rgba` (H,W,4) float straight alpha, `rgb` (H,W,3)
    composited on `background`, `depth` (H,W), and floats `density_samples_per_ray`,
    `color_samples_per_ray`. kwargs go to `render_rays` (occupancy, sample_transform, progress, ...).
    `chunk`: rays per chunk (default FRAME_CHUNK; 4096 on the legacy path). On the fast path the rays
    are made chunk by chunk, in tile order (the memory of a frame is its outputs and one chunk's work).
    `substeps`: samples per step of the march (the `step` given, else the NeRF's render step): final
    frames take `substeps.FINAL_SUBSTEPS`, previews 1.
    """
    h, w = camera.height, camera.width
    check_frame_memory(w, h)
    if check_substeps(substeps) > 1:
        kwargs["step"] = float(kwargs.get("step") or model.config.render_step) / substeps
    if _render_path == "legacy":
        o, d = camera_rays(camera, device=model.device)
        out = render_rays(model, o, d, background=background, chunk=chunk or 4096, **kwargs)
        color, alpha, depth, rgb = out["color"], out["alpha"], out["depth"], out["rgb"]
        n_den, n_col = out["n_density_samples"], out["n_color_samples"]
    else:
        chunk = int(chunk or (FRAME_CHUNK_CUDA if model.device.type == "cuda" else FRAME_CHUNK))
        if chunk < 1:
            raise ValueError(f"chunk must be a positive number of rays, got {chunk}")
        progress = kwargs.pop("progress", None)
        order = tile_order(w, h)
        total = h * w
        color = torch.zeros(total, 3)
        alpha, depth = torch.zeros(total), torch.zeros(total)
        rgb = torch.zeros(total, 3)
        n_den = n_col = 0
        for s in range(0, total, chunk):
            pixels = order[s : s + chunk]
            o, d = pixel_rays(camera, pixels, device=model.device)
            out = render_rays(model, o, d, background=background, chunk=pixels.numel(), **kwargs)
            if backend.use_kernels(model.device):
                color[pixels], alpha[pixels] = out["color"].cpu(), out["alpha"].cpu()
                depth[pixels], rgb[pixels] = out["depth"].cpu(), out["rgb"].cpu()
            else:  # one copy to the host per chunk (on CUDA each copy waits for the device)
                packed = to_host(torch.cat([out["color"], out["alpha"][:, None], out["depth"][:, None], out["rgb"]], 1))
                color[pixels], alpha[pixels] = packed[:, :3], packed[:, 3]
                depth[pixels], rgb[pixels] = packed[:, 4], packed[:, 5:]
            n_den += out["n_density_samples"]
            n_col += out["n_color_samples"]
            if progress is not None:
                progress(min(s + chunk, total), total)
    alpha = alpha.clamp(0, 1)
    straight = torch.where(alpha[:, None] > 1e-6, color / alpha.clamp_min(1e-6)[:, None], torch.zeros_like(color))
    rgba = torch.cat([straight.clamp(0, 1), alpha[:, None]], dim=-1).reshape(h, w, 4)
    n = max(1, h * w)
    return {
        "rgba": rgba.cpu().numpy(),
        "rgb": rgb.clamp(0, 1).reshape(h, w, 3).cpu().numpy(),
        "depth": depth.reshape(h, w).cpu().numpy(),
        "density_samples_per_ray": n_den / n,
        "color_samples_per_ray": n_col / n,
    }
