"""Lens distortion: OpenCV's radial-tangential and fisheye models, and rays through distorted pixels.

Real photos are distorted; a ray must go through the pixel as the lens bent it,
or training learns a blurred scene and `eval` scores the NeRF against photos it
cannot reproduce. The models are OpenCV's (what COLMAP, instant-ngp and
nerfstudio write), in OpenCV's normalized camera coordinates (x right, y down,
looking down +z):

- "opencv" (radial-tangential; COLMAP's OPENCV / SIMPLE_RADIAL / RADIAL):
      r² = x² + y²,  s = 1 + k1 r² + k2 r⁴ + k3 r⁶
      x_d = s x + 2 p1 x y + p2 (r² + 2 x²),  y_d = s y + p1 (r² + 2 y²) + 2 p2 x y
- "fisheye" (equidistant; COLMAP's OPENCV_FISHEYE, instant-ngp's `is_fisheye`):
      θ = atan(r),  θ_d = θ (1 + k1 θ² + k2 θ⁴ + k3 θ⁶ + k4 θ⁸),  (x_d, y_d) = (θ_d / r) (x, y)

A pixel's ray inverts the model: Newton's method on the 2x2 system (radial-
tangential, as OpenCV's undistortPoints and nerfstudio do) or on θ_d(θ) = |x_d|
(fisheye, which can see past 90 degrees, so its ray is built from θ rather than
from tan θ). Pure torch, float64, on any device; a handful of iterations reach
1e-12 on real lenses (the tests check the round trip).
"""

from __future__ import annotations

import torch

from .camera import Distortion

NEWTON_STEPS = 10


def distort(lens: Distortion, x: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Normalized undistorted (x, y) = (X/Z, Y/Z) → distorted (x_d, y_d)."""
    if lens.model == "fisheye":
        r = torch.sqrt(x * x + y * y)
        theta = torch.atan(r)
        scale = torch.where(r > 1e-12, _theta_d(lens, theta) / r.clamp_min(1e-12), torch.ones_like(r))
        return x * scale, y * scale
    r2 = x * x + y * y
    s = 1 + r2 * (lens.k1 + r2 * (lens.k2 + r2 * lens.k3))
    xd = s * x + 2 * lens.p1 * x * y + lens.p2 * (r2 + 2 * x * x)
    yd = s * y + lens.p1 * (r2 + 2 * y * y) + 2 * lens.p2 * x * y
    return xd, yd


def _theta_d(lens: Distortion, t: torch.Tensor) -> torch.Tensor:
    t2 = t * t
    return t * (1 + t2 * (lens.k1 + t2 * (lens.k2 + t2 * (lens.k3 + t2 * lens.k4))))


def ray_directions(lens: Distortion, xd: torch.Tensor, yd: torch.Tensor) -> torch.Tensor:
    """Unit directions (N, 3) in OpenCV camera coordinates (+z forward) of distorted normalized points."""
    if lens.model == "fisheye":
        rd = torch.sqrt(xd * xd + yd * yd)
        theta = rd.clone()  # θ_d ≈ θ for small distortion: a good start
        for _ in range(NEWTON_STEPS):
            t2 = theta * theta
            f = _theta_d(lens, theta) - rd
            df = 1 + t2 * (3 * lens.k1 + t2 * (5 * lens.k2 + t2 * (7 * lens.k3 + t2 * 9 * lens.k4)))
            theta = theta - f / torch.where(df.abs() > 1e-12, df, torch.ones_like(df))
        sin = torch.sin(theta)
        ux = torch.where(rd > 1e-12, xd / rd.clamp_min(1e-12), torch.zeros_like(rd))
        uy = torch.where(rd > 1e-12, yd / rd.clamp_min(1e-12), torch.zeros_like(rd))
        return torch.stack([sin * ux, sin * uy, torch.cos(theta)], dim=-1)
    x, y = undistort(lens, xd, yd)
    d = torch.stack([x, y, torch.ones_like(x)], dim=-1)
    return d / d.norm(dim=-1, keepdim=True)


def undistort(lens: Distortion, xd: torch.Tensor, yd: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Radial-tangential: the undistorted (x, y) whose distortion is (xd, yd), by Newton's method."""
    x, y = xd.clone(), yd.clone()
    k1, k2, k3, p1, p2 = lens.k1, lens.k2, lens.k3, lens.p1, lens.p2
    for _ in range(NEWTON_STEPS):
        r2 = x * x + y * y
        s = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        ds = k1 + r2 * (2 * k2 + 3 * k3 * r2)  # d s / d(r²)
        fx = s * x + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) - xd
        fy = s * y + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y - yd
        # Jacobian of (fx, fy) with respect to (x, y).
        a = s + 2 * x * x * ds + 2 * p1 * y + 6 * p2 * x
        b = 2 * x * y * ds + 2 * p1 * x + 2 * p2 * y
        c = 2 * x * y * ds + 2 * p2 * y + 2 * p1 * x
        d = s + 2 * y * y * ds + 6 * p1 * y + 2 * p2 * x
        det = a * d - b * c
        det = torch.where(det.abs() > 1e-12, det, torch.ones_like(det))
        x = x - (d * fx - b * fy) / det
        y = y - (a * fy - c * fx) / det
    return x, y


def camera_directions(fx, fy, cx, cy, i: torch.Tensor, j: torch.Tensor, distortion: Distortion | None) -> torch.Tensor:
    """Camera-space directions (N, 3), Blender/OpenGL convention (-z forward, +y up), of pixel
    positions (i, j) (column, row from the top; +0.5 is a pixel's centre). Pinhole directions have
    z = -1 (planar depth 1); distorted ones are unit vectors."""
    x = (i - cx) / fx
    y = (j - cy) / fy  # OpenCV's y runs down, as rows do
    if distortion is None or distortion.is_identity:
        return torch.stack([x, -y, -torch.ones_like(x)], dim=-1)
    d = ray_directions(distortion, x.double(), y.double()).to(x.dtype)
    return torch.stack([d[..., 0], -d[..., 1], -d[..., 2]], dim=-1)
