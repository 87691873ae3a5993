"""A tiny analytic NeRF dataset for the engine's tests, made in milliseconds without Blender or ../shared.

A sphere of radius 0.8 at the origin whose colour is 0.5 + 0.5 * normal,
ray-cast exactly (with 2x2 supersampling, so edges have fractional alpha) from
cameras on a sphere of radius 3 looking at the origin, Blender/OpenGL
convention, NeRF-synthetic `camera_angle_x` form, RGBA PNGs with straight alpha.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
from PIL import Image

RADIUS = 0.8
ANGLE_X = 0.9


def look_at(eye, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world 4x4 of a camera at eye looking at target (looks down its -Z, +Y up)."""
    eye, target, up = (np.asarray(v, np.float64) for v in (eye, target, up))
    z = eye - target
    z /= np.linalg.norm(z)
    x = np.cross(up, z)
    if np.linalg.norm(x) < 1e-8:
        x = np.cross((0.0, 1.0, 0.0), z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, y, z, eye
    return m


def sphere_cameras(n: int, radius: float = 3.0, seed: int = 0) -> list[np.ndarray]:
    """n camera-to-world matrices spread over a sphere (Fibonacci lattice, slightly jittered)."""
    rng = np.random.default_rng(seed)
    mats = []
    for k in range(n):
        zc = 1 - 2 * (k + 0.5) / n
        phi = k * math.pi * (3 - math.sqrt(5)) + rng.uniform(0, 0.2)
        r = math.sqrt(1 - zc * zc)
        mats.append(look_at(radius * np.array([r * math.cos(phi), r * math.sin(phi), zc])))
    return mats


def render_sphere(c2w: np.ndarray, size: int, angle_x: float = ANGLE_X, ss: int = 2) -> np.ndarray:
    """Exact RGBA (straight alpha) image of the sphere, size x size, ss x ss samples per pixel."""
    f = 0.5 * size / math.tan(0.5 * angle_x)
    sub = (np.arange(size * ss) + 0.5) / ss
    jj, ii = np.meshgrid(sub, sub, indexing="ij")
    d = np.stack([(ii - size / 2) / f, -(jj - size / 2) / f, -np.ones_like(ii)], -1) @ c2w[:3, :3].T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    o = c2w[:3, 3]
    b = d @ o
    c = o @ o - RADIUS**2
    disc = b * b - c
    hit = disc > 0
    t = -b - np.sqrt(np.maximum(disc, 0))
    p = o + d * t[..., None]
    rgb = np.where(hit[..., None], 0.5 + 0.5 * p / RADIUS, 0.0)
    a = hit.astype(np.float64)
    pre = np.concatenate([rgb * a[..., None], a[..., None]], -1).reshape(size, ss, size, ss, 4).mean((1, 3))
    alpha = pre[..., 3:]
    col = np.where(alpha > 0, pre[..., :3] / np.maximum(alpha, 1e-9), 0)
    return np.concatenate([col, alpha], -1)


def write_sphere_dataset(folder, n_views: int = 24, size: int = 32, seed: int = 0, names_prefix: str = "r_") -> Path:
    """Write folder/transforms.json + folder/images/*.png; returns the folder."""
    folder = Path(folder)
    (folder / "images").mkdir(parents=True, exist_ok=True)
    frames = []
    for k, c2w in enumerate(sphere_cameras(n_views, seed=seed)):
        img = render_sphere(c2w, size)
        name = f"images/{names_prefix}{k}.png"
        Image.fromarray((np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8), "RGBA").save(folder / name)
        frames.append({"file_path": name, "transform_matrix": c2w.tolist()})
    meta = {"camera_angle_x": ANGLE_X, "w": size, "h": size, "frames": frames}
    (folder / "transforms.json").write_text(json.dumps(meta))
    return folder
