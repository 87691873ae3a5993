"""Training loop: random rays from all images, random backgrounds, occupancy-skipped rendering, Adam.

`Trainer(model, dataset, options)` then `trainer.train()`; or call `trainer.step()`
yourself. Budget: `options.max_seconds` (training time: the time spent in
callbacks such as validation is not counted) and/or `options.steps`.

What makes it fast on CPU:
- the fused hash-encoding kernels (encoding_kernels.py) and a lazy (sparse) Adam (adam_kernels.py) on
  the hash table that touches only the rows that received a gradient;
- a constant number of *samples* per step (the ray batch adapts), as nerfacc does;
- the occupancy grid and early ray termination (renderer.py), so only samples
  near the visible surfaces get a gradient.

Random backgrounds: every ray composites prediction and target on the same
random colour, so the background is not baked into the density. Photos without
alpha are opaque everywhere: there the random colour is what makes the NeRF model
what lies behind the object (an unbounded NeRF, `scene_model="unbounded"`), never
a flat colour.

Which model (`scene_model`): "bounded" (the field lives in the dataset's box; RGBA
objects), "unbounded" (the dataset's inner box plus a contracted background:
contraction.py), or "auto": unbounded for photos without alpha, bounded otherwise.
"""

from __future__ import annotations

import json
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from .. import backend
from ..errors import EngineError
from ..files import atomic_write, check_writable, folder_lock, interrupts_deferred, remove_stale_temporaries
from ..launch_count import read_back
from . import adam_kernels
from .checkpoint import load_nerf, read_checkpoint, save_nerf
from .dataset import NerfDataset, load_dataset
from .lens import camera_directions
from .model import NerfConfig, NerfModel, resolve_device
from .renderer import render_image, render_rays
from .silhouettes import MASK_LABELS, carve
from .visibility import model_depth, paid_for, photos_seeing_through

log = logging.getLogger(__name__)

OCC_UPDATE_EVERY_PER_GRID = 16
VISIBILITY_MARKS = (0.3, 0.6)  # fractions of the budget at which free space is judged by the photos seeing through
ERROR_TILE = 8  # pixels on a side of an error-map tile


@dataclass
class TrainOptions:
    max_seconds: float | None = None
    steps: int | None = None
    lr: float = 1e-2
    lr_final_factor: float = 0.05  # lr decays exponentially to lr * this at the end of the budget
    warmup_steps: int = 50
    target_samples: int = 1 << 15  # samples with gradients per step; the ray batch adapts to it
    init_rays: int = 1024
    max_rays: int = 1 << 14
    # Steps between occupancy updates; None: 16 per grid, so an unbounded model (an inner and a background
    # grid) updates every 32 steps and spends what a bounded one does: more steps in the same time and a
    # better validation PSNR than both grids every 16; every 64 is worse, the grid goes stale.
    occ_update_every: int | None = None
    occ_warmup_steps: int = 128  # every cell is re-evaluated during these steps
    occ_fraction: float = 1 / 16  # afterwards: this fraction uniformly + as many among occupied cells
    random_background: bool = True
    pixel_jitter: bool = True  # a random point in the pixel (the images are box-filtered)
    checkpoint_path: str | None = None
    checkpoint_every_s: float = 120.0
    seed: int = 0
    distortion_weight: float | None = None  # None: 0.01 for unbounded NeRFs, 0 for bounded ones
    # instant-ngp's error map: this fraction of each step's rays is drawn from tiles of ERROR_TILE^2 pixels in
    # proportion to their recent loss, the rest uniformly (datasets with masks: all uniformly). Off: it
    # helps early in a training and is level with uniform rays by the end of a full one.
    error_rays: float = 0.0
    # Camera pose refinement (as instant-ngp and nerfacto do): each training photo's pose gets a small
    # rotation about its centre and a translation, learned with the field at pose_lr (in radians, and in
    # half-widths of the scene's inner box, per step at the peak) once pose_start of the budget has passed.
    # Off: on held-out photos a large rate from the start costs much (a few rays per photo per step make
    # the poses wander), and these defaults are at best level with fixed poses.
    refine_poses: bool = False
    pose_lr: float = 1e-4
    pose_start: float = 0.3
    # Inner cells that fewer training photos than this see through (and at least one) are ruled out
    # (visibility.py); 0 or 1: no limit.
    min_views: int = 0


def distortion_loss(
    ray_idx: torch.Tensor, t: torch.Tensor, dt: torch.Tensor, w: torch.Tensor, n_rays: int, scale: float
) -> torch.Tensor:
    """mip-NeRF 360's distortion loss, mean over rays: sum_ij w_i w_j |s_i - s_j| + 1/3 sum_i w_i^2 ds_i.

    It pulls each ray's weights together (a surface, not a fog), which is what lets rays of a
    real capture terminate after a few samples. Distances are warped, s = 1 - 1 / (1 + t / scale),
    so the far background does not dominate. Samples sorted by ray then t; O(samples) through
    per-ray exclusive prefix sums: sum_ij = 2 sum_i w_i (s_i W_<i - (ws)_<i).
    """
    s = 1.0 - 1.0 / (1.0 + t / scale)
    ds = dt / scale / (1.0 + t / scale) ** 2
    if backend.use_kernels(ray_idx.device):
        counts = torch.bincount(ray_idx, minlength=n_rays)
        starts = (torch.cumsum(counts, 0) - counts)[ray_idx]
    else:  # the device path: each sample's ray's first sample, with no count read back
        starts = torch.searchsorted(ray_idx, ray_idx)

    def exclusive(x):
        c = torch.cumsum(x, 0) - x
        return c - c[starts]

    cross = 2.0 * (w * (s * exclusive(w) - exclusive(w * s))).sum()
    own = (w * w * ds).sum() / 3.0
    return (cross + own) / max(n_rays, 1)


class Trainer:
    def __init__(self, model: NerfModel, dataset: NerfDataset, options: TrainOptions | None = None):
        if dataset.images is None or len(dataset) == 0:
            raise ValueError("the dataset has no images")
        self.model = model
        self.opt = options or TrainOptions()
        dev = model.device
        self.device = dev
        torch.manual_seed(self.opt.seed)
        n, h, w = dataset.images.shape[:3]
        self.n_images, self.h, self.w = n, h, w
        self.pixels = torch.from_numpy(dataset.images.reshape(-1, 4)).to(dev)
        # Pixels a mask excludes (nerfstudio's mask_path: 0 = ignore) are never drawn.
        self.valid_pixels = None
        if dataset.masks is not None:
            self.valid_pixels = torch.nonzero(torch.from_numpy(np.asarray(dataset.masks).reshape(-1))).flatten().to(dev)
            if self.valid_pixels.numel() == 0:
                raise EngineError("the dataset's masks exclude every pixel: nothing to train on")
        self.c2w = torch.tensor(np.stack([c.c2w[:3, :4] for c in dataset.cameras]), dtype=torch.float32, device=dev)
        self.intr = torch.tensor([[c.fx, c.fy, c.cx, c.cy] for c in dataset.cameras], dtype=torch.float32, device=dev)
        # Distorted cameras: each distinct lens, and which one each image has (-1: pinhole).
        self.lenses = sorted(
            {c.distortion for c in dataset.cameras if c.distortion is not None and not c.distortion.is_identity},
            key=repr,
        )
        self.lens_of_image = torch.tensor(
            [self.lenses.index(c.distortion) if c.distortion in self.lenses else -1 for c in dataset.cameras],
            dtype=torch.int64,
            device=dev,
        )
        enc = model.encoding
        self.lazy_table = backend.use_kernels(dev)  # the table's lazy Adam needs the fused encoding kernels
        enc.fused_grad = self.lazy_table
        mlp_params = list(model.density_net.parameters()) + list(model.color_net.parameters())
        if model.appearance is not None:
            if model.config.appearance_count < n:
                raise EngineError(
                    f"the NeRF has appearance codes for {model.config.appearance_count} images, the dataset has {n}"
                )
            mlp_params += list(model.appearance.parameters())
        params = mlp_params if self.lazy_table else [enc.table] + mlp_params
        # The device path: all parameters in one fused kernel.
        self.optimizer = torch.optim.Adam(
            params, lr=self.opt.lr, betas=(0.9, 0.99), eps=1e-15, fused=not self.lazy_table
        )
        # Per photo: a rotation vector (radians, world axes, about the camera's centre) and a translation
        # in units of pose_scale; zero is the photo's own pose.
        self.pose_scale = float((model.aabb[1] - model.aabb[0]).max()) / 2
        self.pose_delta = None
        if self.opt.refine_poses:
            self.pose_delta = torch.nn.Parameter(torch.zeros(n, 6, device=dev))
            scale = self.opt.pose_lr / self.opt.lr if self.opt.lr else 0.0  # follows the field's warm-up and decay
            self.optimizer.add_param_group({"params": [self.pose_delta], "lr_scale": scale})
        if self.lazy_table:
            self.table_m = torch.zeros_like(enc.table.detach())
            self.table_v = torch.zeros_like(enc.table.detach())
        self.step_count = 0
        self.elapsed = 0.0  # training seconds (callbacks excluded)
        # First batch: as if every ray took half a diagonal of samples (the grid starts all occupied).
        self.n_rays = max(64, min(self.opt.init_rays, 2 * self.opt.target_samples // model.config.steps_per_diagonal))
        self.last = {}
        self.grids = [model.occupancy] + ([model.background] if model.background is not None else [])
        # When the inner grid's free space is judged by the photos that see through it (visibility.py): once the
        # geometry has formed, and again once it has sharpened. The background grid is left alone.
        self.cameras = dataset.cameras
        self.visibility_marks = list(VISIBILITY_MARKS) if self.opt.min_views > 1 else []
        if dataset.mask_meaning == "object" and not model.unbounded:
            # Object masks: nothing outside the silhouettes' hull is ever occupied.
            grid = model.occupancy
            cells = grid.cell_centers(torch.arange(grid.resolution**3, device=dev), jitter=False).cpu().numpy()
            grid.restrict(
                torch.from_numpy(carve(cells, dataset.cameras, [img[..., 3] > 0.5 for img in dataset.images]))
            )
        dw = self.opt.distortion_weight
        self.distortion = float(dw if dw is not None else (0.01 if model.background is not None else 0.0))
        self.distortion_scale = float((model.aabb[1] - model.aabb[0]).max()) / 2
        # Error map: each tile's running loss; 1 (above any loss of colours in [0, 1]) until first drawn, so
        # that every tile is visited. Not kept in checkpoints: a resumed run rebuilds it within a few steps.
        if not 0.0 <= self.opt.error_rays <= 1.0:
            raise ValueError(f"error_rays = {self.opt.error_rays!r}: a fraction of the rays, from 0 to 1")
        self.tiles_y, self.tiles_x = -(-h // ERROR_TILE), -(-w // ERROR_TILE)
        self.tile_error = None
        if self.opt.error_rays > 0 and self.valid_pixels is None:
            self.tile_error = torch.ones(n * self.tiles_y * self.tiles_x, device=dev)

    # --- pieces of a step ---------------------------------------------------------------------
    def draw_pixels(self, n_rays: int) -> torch.Tensor:
        """Flat indices of the pixels a step trains on: uniformly among the valid ones, and with an error
        map, a fraction of them in tiles drawn in proportion to their error."""
        dev = self.device
        n_error = int(n_rays * self.opt.error_rays) if self.tile_error is not None else 0
        n_uniform = n_rays - n_error
        if self.valid_pixels is None:
            idx = torch.randint(0, self.pixels.shape[0], (n_uniform,), device=dev)
        else:
            idx = self.valid_pixels[torch.randint(0, self.valid_pixels.numel(), (n_uniform,), device=dev)]
        if not n_error:
            return idx
        tile = torch.multinomial(self.tile_error, n_error, replacement=True)
        per_image = self.tiles_y * self.tiles_x
        img, ty, tx = tile // per_image, (tile % per_image) // self.tiles_x, tile % self.tiles_x
        y0, x0 = ty * ERROR_TILE, tx * ERROR_TILE
        # A pixel uniformly inside the tile (the last row and column of tiles may be cut by the image's edge).
        y = y0 + (torch.rand(n_error, device=dev) * (self.h - y0).clamp(max=ERROR_TILE)).long()
        x = x0 + (torch.rand(n_error, device=dev) * (self.w - x0).clamp(max=ERROR_TILE)).long()
        return torch.cat([idx, (img * self.h + y) * self.w + x])

    def record_errors(self, idx: torch.Tensor, errors: torch.Tensor) -> None:
        """Fold the squared errors (N,) of the pixels idx (N,) into their tiles' running error."""
        if self.tile_error is None:
            return
        img, pix = idx // (self.h * self.w), idx % (self.h * self.w)
        tile = (img * self.tiles_y + (pix // self.w) // ERROR_TILE) * self.tiles_x + (pix % self.w) // ERROR_TILE
        tiles, which = torch.unique(tile, return_inverse=True)
        mean = torch.zeros(tiles.numel(), device=idx.device).index_add_(0, which, errors.float())
        mean /= torch.bincount(which, minlength=tiles.numel())
        # Half the old value, half the new: a tile's error follows training without one noisy ray deciding it.
        self.tile_error[tiles] = (0.5 * self.tile_error[tiles] + 0.5 * mean).clamp_min(1e-8)

    def sample_rays(self, n_rays: int, idx: torch.Tensor | None = None):
        """Rays (origins, unit directions), their target RGBA and image index, through the pixels idx (default:
        `draw_pixels(n_rays)`), each at a random point of its pixel when jittering."""
        dev = self.device
        if idx is None:
            idx = self.draw_pixels(n_rays)
        n_rays = idx.numel()
        img = idx // (self.h * self.w)
        pix = idx % (self.h * self.w)
        j = (pix // self.w).float()
        i = (pix % self.w).float()
        if self.opt.pixel_jitter:
            i = i + torch.rand(n_rays, device=dev)
            j = j + torch.rand(n_rays, device=dev)
        else:
            i, j = i + 0.5, j + 0.5
        fx, fy, cx, cy = self.intr[img].unbind(-1)
        d_cam = torch.stack([(i - cx) / fx, -(j - cy) / fy, -torch.ones_like(i)], dim=-1)
        for k, lens in enumerate(self.lenses):  # rays through the pixels as each lens bent them
            if not self.lazy_table:  # the device path: masked, the rays' number is not read back
                sel = (self.lens_of_image[img] == k)[:, None]
                d_cam = torch.where(sel, camera_directions(fx, fy, cx, cy, i, j, lens), d_cam)
                continue
            sel = torch.nonzero(self.lens_of_image[img] == k).squeeze(1)
            if len(sel):
                d_cam[sel] = camera_directions(fx[sel], fy[sel], cx[sel], cy[sel], i[sel], j[sel], lens)
        c2w = self.c2w[img]
        d = (c2w[:, :, :3] @ d_cam[:, :, None])[:, :, 0]
        o = c2w[:, :, 3]
        if self.poses_move():  # (before, every correction is still zero)
            rot, shift = self.pose_corrections()
            d = (rot[img] @ d[:, :, None])[:, :, 0]
            o = o + shift[img]
        d = d / d.norm(dim=-1, keepdim=True)
        return o.contiguous(), d.contiguous(), self.pixels[idx], img

    def poses_move(self) -> bool:
        """Whether this step learns the photos' pose corrections (refine_poses, past pose_start)."""
        return self.pose_delta is not None and self.progress_fraction() >= self.opt.pose_start

    def pose_corrections(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Each photo's learned correction: rotations (N, 3, 3) applied to its rays' directions and world
        translations (N, 3) added to their origins (identity and zero without pose refinement)."""
        if self.pose_delta is None:
            return (
                torch.eye(3, device=self.device).expand(self.n_images, 3, 3),
                torch.zeros(self.n_images, 3, device=self.device),
            )
        w = self.pose_delta[:, :3]
        zero = torch.zeros_like(w[:, 0])
        skew = torch.stack([zero, -w[:, 2], w[:, 1], w[:, 2], zero, -w[:, 0], -w[:, 1], w[:, 0], zero], dim=-1).reshape(
            -1, 3, 3
        )
        return torch.linalg.matrix_exp(skew), self.pose_delta[:, 3:] * self.pose_scale

    def progress_fraction(self) -> float:
        p = 0.0
        if self.opt.steps:
            p = max(p, self.step_count / self.opt.steps)
        if self.opt.max_seconds:
            p = max(p, self.elapsed / self.opt.max_seconds)
        return min(p, 1.0)

    def learning_rate(self) -> float:
        warm = min(1.0, (self.step_count + 1) / max(1, self.opt.warmup_steps))
        return self.opt.lr * warm * self.opt.lr_final_factor ** self.progress_fraction()

    def update_occupancy(self) -> None:
        m = self.model
        if self.step_count % (self.opt.occ_update_every or OCC_UPDATE_EVERY_PER_GRID * len(self.grids)):
            return
        step = m.config.render_step
        was = m.training
        m.eval()
        if self.step_count < self.opt.occ_warmup_steps:
            # Every cell, but through blocks of 2^3 cells for the first half of the warmup (8x cheaper).
            block = 2 if self.step_count < self.opt.occ_warmup_steps // 2 else 1
            for grid in self.grids:
                grid.update(m.density, step, m.config.occ_threshold, block=block)
        else:
            for grid in self.grids:
                k = int(grid.resolution**3 * self.opt.occ_fraction)
                grid.update(m.density, step, m.config.occ_threshold, n_uniform=k, n_occupied=k)
        m.train(was)

    def _optimizer_step(self, lr: float) -> None:
        for g in self.optimizer.param_groups:
            g["lr"] = lr * g.get("lr_scale", 1.0)
        self.optimizer.step()
        if self.poses_move():
            # No common motion of all photos: it would move the scene away from photos that are not refined
            # (held-out views, frames placed by the dataset's cameras).
            with torch.no_grad():
                self.pose_delta -= self.pose_delta.mean(dim=0)
        if self.lazy_table:
            enc = self.model.encoding
            t = self.step_count + 1
            adam_kernels.sparse_adam(
                enc.table.detach().numpy(),
                enc.grad_buffer().numpy(),
                self.table_m.numpy(),
                self.table_v.numpy(),
                enc.touched_rows(),
                lr,
                0.9,
                0.99,
                1e-15,
                1 - 0.9**t,
                1 - 0.99**t,
            )

    # The device path: slots for the samples of a step's batch (None: every sample the march can give), sized
    # from the last step's samples per ray with room to spare; a full step (samples were cut) doubles them.
    sample_cap: int | None = None
    SAMPLE_CAP_ROOM, SAMPLE_CAP_QUANTUM = 1.5, 1 << 12

    def _next_sample_cap(self, n_density: float, rays: int) -> int:
        cap = self.SAMPLE_CAP_ROOM * n_density / max(rays, 1) * self.n_rays
        cap = self.SAMPLE_CAP_QUANTUM * (int(cap) // self.SAMPLE_CAP_QUANTUM + 1)
        if self.sample_cap is not None and n_density >= self.sample_cap:
            cap = max(cap, 2 * self.sample_cap)
        return cap

    def step(self) -> dict:
        """One optimisation step; returns loss, psnr (of the batch), rays and samples."""
        t_start = time.perf_counter()
        self.model.encoding.fused_grad = self.lazy_table
        if self.visibility_marks and self.progress_fraction() >= self.visibility_marks[0]:
            self.visibility_marks.pop(0)
            counts = photos_seeing_through(self.model.occupancy, self.cameras, lambda c: model_depth(self.model, c))
            self.model.occupancy.restrict(paid_for(counts, self.opt.min_views))
        self.update_occupancy()
        m = self.model
        m.train()
        pixels = self.draw_pixels(self.n_rays)
        o, d, target, images = self.sample_rays(self.n_rays, pixels)
        if self.opt.random_background:
            bg = torch.rand(self.n_rays, 3, device=self.device)
        else:
            bg = torch.as_tensor(m.config.background, dtype=torch.float32, device=self.device).expand(self.n_rays, 3)
        tgt = target[:, :3] * target[:, 3:4] + bg * (1.0 - target[:, 3:4])
        codes = m.appearance(images) if m.appearance is not None else None
        out = render_rays(
            m,
            o,
            d,
            background=bg,
            chunk=self.n_rays,
            perturb=True,
            return_samples=self.distortion > 0,
            appearance=codes,
            max_samples=self.sample_cap,
        )
        squared = (out["rgb"] - tgt) ** 2
        loss = mse = torch.mean(squared)
        if self.distortion > 0 and out.get("samples") is not None:
            r, t, dt, w = out["samples"]
            loss = loss + self.distortion * distortion_loss(r, t, dt, w, self.n_rays, self.distortion_scale)
        self.optimizer.zero_grad(set_to_none=True)
        if self.lazy_table:
            n_samples, n_density = out["n_color_samples"], out["n_density_samples"]
            if n_samples:
                loss.backward()
                self._optimizer_step(self.learning_rate())
            lv = float(mse.detach())
        else:
            # The device path: no sample count is known before the step's one sync, which reads the loss
            # and both counts together after the update.
            if loss.requires_grad:
                loss.backward()
                self._optimizer_step(self.learning_rate())
            lv, n_samples, n_density = read_back(mse, out["n_color_samples"], out["n_density_samples"])
        self.record_errors(pixels, squared.detach().mean(dim=-1))
        # Keep the number of samples per step near the target (nerfacc's dynamic batch).
        rays = self.n_rays
        per_ray = max(n_samples / self.n_rays, 1e-3)
        den_per_ray = max(n_density / self.n_rays, 1e-3)
        want = min(self.opt.target_samples / per_ray, 4 * self.opt.target_samples / den_per_ray)
        self.n_rays = int(min(self.opt.max_rays, 2 * self.n_rays, max(64, 0.7 * self.n_rays + 0.3 * want)))
        if not self.lazy_table:
            self.sample_cap = self._next_sample_cap(n_density, rays)
        self.step_count += 1
        self.elapsed += time.perf_counter() - t_start
        self.last = {
            "loss": lv,
            "psnr": -10 * math.log10(max(lv, 1e-10)),
            "rays": o.shape[0],
            "samples_per_ray": per_ray,
            "density_samples_per_ray": den_per_ray,
        }
        return self.last

    def done(self) -> bool:
        if self.opt.steps is not None and self.step_count >= self.opt.steps:
            return True
        if self.opt.max_seconds is not None and self.elapsed >= self.opt.max_seconds:
            return True
        return False

    def render_preview(self, camera, progress=None) -> dict:
        """`render_image` of the model as it is now, between two steps (the worker's training preview):
        eval mode, no gradients, the random state forked and the optimizer untouched, so that the
        training goes on exactly as it would have without it."""
        m = self.model
        was = m.training
        m.eval()
        try:
            with torch.random.fork_rng(devices=[m.device] if m.device.type == "cuda" else []):
                return render_image(m, camera, progress=progress)
        finally:
            m.train(was)

    # --- resume ------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        s = {
            "step": self.step_count,
            "elapsed": self.elapsed,
            "n_rays": self.n_rays,
            "optimizer": self.optimizer.state_dict(),
        }
        if self.lazy_table:
            s["table_m"], s["table_v"] = self.table_m.clone(), self.table_v.clone()
        if self.pose_delta is not None:
            s["pose_delta"] = self.pose_delta.detach().clone()
        return s

    def load_state_dict(self, s: dict, where: str = "the trainer state") -> None:
        try:
            step, elapsed, n_rays = int(s["step"]), float(s.get("elapsed", 0.0)), int(s.get("n_rays", self.n_rays))
        except (KeyError, TypeError, ValueError) as exc:
            raise EngineError(f"{where}: the trainer state to resume is unreadable ({exc!r})") from None
        if step < 0 or n_rays < 1 or not math.isfinite(elapsed):
            raise EngineError(
                f"{where}: the trainer state to resume is invalid (step {step}, rays {n_rays}, elapsed {elapsed})"
            )
        self.step_count, self.elapsed, self.n_rays = step, elapsed, min(n_rays, self.opt.max_rays)
        try:
            self.optimizer.load_state_dict(s["optimizer"])
        except (ValueError, KeyError, TypeError, RuntimeError):
            pass  # a checkpoint from the other optimizer layout: restart the moments
        deltas = s.get("pose_delta")
        if self.pose_delta is not None and isinstance(deltas, torch.Tensor):
            if deltas.shape != self.pose_delta.shape or not bool(torch.isfinite(deltas).all()):
                raise EngineError(
                    f"{where}: the pose corrections to resume have shape {tuple(deltas.shape)} or are "
                    f"not finite; this dataset's {self.n_images} photos need ({self.n_images}, 6)"
                )
            with torch.no_grad():
                self.pose_delta.copy_(deltas)
        if self.lazy_table and "table_m" in s:
            m, v = s["table_m"], s.get("table_v")
            if (
                isinstance(m, torch.Tensor)
                and isinstance(v, torch.Tensor)
                and m.shape == v.shape == self.table_m.shape
                and bool(torch.isfinite(m).all())
                and bool(torch.isfinite(v).all())
            ):
                self.table_m.copy_(m)
                self.table_v.copy_(v)

    def save(self, path) -> None:
        """Write the checkpoint, unless training diverged: NaN weights would replace the last good one."""
        for name, value in self.model.state_dict().items():
            if value.is_floating_point() and not bool(torch.isfinite(value).all()):
                raise EngineError(
                    f"training diverged at step {self.step_count}: `{name}` holds NaN or inf; "
                    f"{path} keeps the last good checkpoint (lower the learning rate or check the data)"
                )
        save_nerf(self.model, path, trainer_state=self.state_dict())

    # --- the loop ----------------------------------------------------------------------------
    def train(
        self,
        progress: bool = True,
        callback: Callable[[Trainer], None] | None = None,
        should_stop: Callable[[], bool] | None = None,
    ) -> dict:
        """Train until the budget is spent. `callback(trainer)` runs after every step (its time is not
        counted); `should_stop()` returning True cancels (a checkpoint is still written)."""
        if self.opt.steps is None and self.opt.max_seconds is None:
            raise ValueError("give a step count or a time budget")
        bar = None
        if progress:
            from tqdm import tqdm

            if self.opt.steps is not None:
                bar = tqdm(total=self.opt.steps, initial=self.step_count, unit="step", dynamic_ncols=True)
            else:
                bar = tqdm(
                    total=round(self.opt.max_seconds),
                    unit="s",
                    dynamic_ncols=True,
                    bar_format="{l_bar}{bar}| {n:.0f}/{total_fmt}s [{elapsed}<{remaining}{postfix}]",
                )
        last_ckpt = time.perf_counter()
        try:
            while not self.done():
                info = self.step()
                if bar is not None:
                    if self.opt.steps is not None:
                        bar.update(1)
                    else:
                        bar.n = min(self.elapsed, self.opt.max_seconds)
                        bar.refresh()
                    if self.step_count % 10 == 0:
                        bar.set_postfix(
                            loss=f"{info['loss']:.4f}",
                            psnr=f"{info['psnr']:.2f}",
                            rays=info["rays"],
                            spr=f"{info['samples_per_ray']:.1f}",
                            refresh=False,
                        )
                if callback is not None:
                    callback(self)
                if self.opt.checkpoint_path and time.perf_counter() - last_ckpt > self.opt.checkpoint_every_s:
                    self.save(self.opt.checkpoint_path)
                    last_ckpt = time.perf_counter()
                if should_stop is not None and should_stop():
                    break
        finally:
            # Ctrl-C waits while the last checkpoint is written: a second press must not lose the run.
            with interrupts_deferred():
                if bar is not None:
                    bar.close()
                self.model.encoding.fused_grad = False  # back to ordinary .grad for whoever uses the model next
                if self.opt.checkpoint_path:
                    self.save(self.opt.checkpoint_path)
        return {"steps": self.step_count, "seconds": self.elapsed, **self.last}


DEFAULT_SECONDS = 300.0
SCENE_MODELS = ("auto", "bounded", "unbounded")


# An unbounded NeRF's cell is occupied when its opacity over one render step (inner diagonal / 256)
# exceeds 0.1: about instant-ngp's density threshold (0.01 over sqrt(3)/1024 of its unit cube) on the
# fox. The bounded default 0.01 left most of a real capture's cells occupied, so training rays marched
# through fog that nothing pruned; on photos never tuned on, 0.1 gave the best PSNR among the values
# tried, with far fewer samples per ray and faster frames.
UNBOUNDED_OCC_THRESHOLD = 0.1


def config_for(ds: NerfDataset, scene_model: str = "auto") -> NerfConfig:
    """The model for a dataset: bounded in its box, or unbounded around its inner box (see the module
    docstring). The unbounded hash grid spans the contracted cube, of which the inner box is the
    middle half per axis: its finest resolution doubles so the inner box keeps the bounded one's."""
    unbounded = scene_model == "unbounded" or (scene_model == "auto" and not ds.has_alpha)
    masks = ds.mask_meaning or "none"
    if not unbounded:
        return NerfConfig(aabb=[float(v) for v in ds.aabb.reshape(-1)], masks=masks)
    inner = np.asarray(ds.inner_aabb if ds.inner_aabb is not None else ds.aabb, dtype=np.float64).reshape(2, 3)
    base = NerfConfig()
    half = float((inner[1] - inner[0]).max() / 2)
    # Half the bounded model's samples per diagonal: the same PSNR as 512 with fewer samples per ray.
    return NerfConfig(
        aabb=[float(v) for v in inner.reshape(-1)],
        contraction="linf",
        steps_per_diagonal=256,
        finest_resolution=2 * base.finest_resolution,
        near_plane=0.05 * half,
        occ_threshold=UNBOUNDED_OCC_THRESHOLD,
        masks=masks,
    )


SEED_RANGE = (-(1 << 63), (1 << 64) - 1)  # what torch.manual_seed accepts
LOCK_NAME = ".train.lock"


def check_budget(steps=None, max_seconds=None, seed: int = 0, checkpoint_every: float = 120.0) -> None:
    """EngineError for a budget or seed that cannot run, before anything is created."""
    if steps is not None and (isinstance(steps, bool) or not isinstance(steps, int) or steps < 1):
        raise EngineError(f"--steps must be a positive integer, got {steps!r}")
    for flag, value in (("--max-seconds", max_seconds), ("--checkpoint-every", checkpoint_every)):
        if value is not None and not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
            raise EngineError(f"{flag} must be a positive finite number of seconds, got {value!r}")
    if isinstance(seed, bool) or not isinstance(seed, int) or not SEED_RANGE[0] <= seed <= SEED_RANGE[1]:
        raise EngineError(f"--seed must be an integer from {SEED_RANGE[0]} to {SEED_RANGE[1]} (64 bits), got {seed!r}")


def run_training(
    data,
    out_dir,
    max_seconds=None,
    steps=None,
    device="auto",
    downscale=1,
    resume=False,
    checkpoint_every=120.0,
    progress=True,
    config_overrides: dict | None = None,
    should_stop=None,
    seed: int = 0,
    overwrite: bool = False,
    scene_model: str = "auto",
    drop_blurry: float = 0.0,
    callback=None,
    masks: str = "auto",
) -> dict:
    """Train and write out_dir/nerf.ckpt; returns a summary dict (also written to out_dir/train.json).
    `callback(trainer)` runs after every step (the worker reports progress from it).

    `seed` seeds the initial weights as well as the trainer's sampling, so that a run of a fixed
    number of steps on the CPU repeats on the same machine (a time budget cannot: it depends on
    the machine's speed).

    A run folder that already holds nerf.ckpt is continued with `resume` or replaced with
    `overwrite`, never silently. One process at a time trains in a folder (a lock file in it,
    released when the process ends, however it ends). Everything is checked before the folder is
    created; a run refused later removes the folder again if it made it and left it empty.
    """
    check_budget(steps, max_seconds, seed, checkpoint_every)
    if scene_model not in SCENE_MODELS:
        raise EngineError(f"--scene {scene_model!r}: one of {', '.join(SCENE_MODELS)}")
    dev = resolve_device(device)
    if steps is None and max_seconds is None:
        max_seconds = DEFAULT_SECONDS
    ds = load_dataset(data, downscale=downscale, min_sharpness_quantile=drop_blurry, masks=masks)
    if progress:
        log.info("read %s", ds.describe())
        if ds.mask_meaning:
            log.info("masks: %s: %s", MASK_LABELS[ds.mask_meaning], ds.mask_reason)
    out = Path(out_dir)
    ckpt = out / "nerf.ckpt"
    _check_replace(ckpt, resume, overwrite)
    check_writable(out, folder=True)
    created = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    try:
        with folder_lock(out, LOCK_NAME, holder="another train process"):
            return _train_locked(
                ds,
                out,
                ckpt,
                dev,
                max_seconds,
                steps,
                resume,
                overwrite,
                checkpoint_every,
                progress,
                config_overrides,
                should_stop,
                seed,
                scene_model,
                callback,
            )
    except EngineError:
        if created:
            try:
                out.rmdir()  # only when empty: nothing of this run is left behind
            except OSError:
                pass
        raise


def _check_replace(ckpt: Path, resume: bool, overwrite: bool) -> None:
    if ckpt.exists() and not resume and not overwrite:
        raise EngineError(
            f"{ckpt} already holds a trained NeRF: pass --resume to continue it or --overwrite to replace it"
        )


def _train_locked(
    ds,
    out,
    ckpt,
    dev,
    max_seconds,
    steps,
    resume,
    overwrite,
    checkpoint_every,
    progress,
    config_overrides,
    should_stop,
    seed,
    scene_model="auto",
    callback=None,
) -> dict:
    _check_replace(ckpt, resume, overwrite)  # again: another process may have finished here meanwhile
    # A process killed while writing left its temporary files; with the lock held none is in use.
    for name in (ckpt, out / "train.json"):
        remove_stale_temporaries(name)
    state = None
    if resume and ckpt.exists():
        state = read_checkpoint(ckpt).get("trainer")
        model = load_nerf(ckpt, device=dev).train()
    else:
        cfg = config_for(ds, scene_model)
        for k, v in (config_overrides or {}).items():
            setattr(cfg, k, v)
        torch.manual_seed(seed)
        model = NerfModel(cfg).to(dev)
    opts = TrainOptions(
        max_seconds=max_seconds, steps=steps, checkpoint_path=str(ckpt), checkpoint_every_s=checkpoint_every, seed=seed
    )
    trainer = Trainer(model, ds, opts)
    if state:
        trainer.load_state_dict(state, where=str(ckpt))
        trainer.elapsed = 0.0  # --max-seconds counts this run
    t0 = time.perf_counter()
    summary = trainer.train(progress=progress, should_stop=should_stop, callback=callback)
    summary.update(
        {
            "checkpoint": str(ckpt),
            "device": str(dev),
            "wall_seconds": time.perf_counter() - t0,
            "images": len(ds),
            "width": ds.width,
            "height": ds.height,
            "masks": ds.mask_meaning,
            "masks_reason": ds.mask_reason,
        }
    )
    text = json.dumps(summary, indent=1).encode()
    atomic_write(out / "train.json", lambda f: f.write(text))
    return summary
