"""Lens distortion: OpenCV's radial-tangential and fisheye models, and the ray of a distorted pixel."""

import math

import numpy as np
import pytest
import torch

from blender_nerf_deform.engine.nerf.camera import Distortion
from blender_nerf_deform.engine.nerf.lens import camera_directions, distort, ray_directions

FOX = Distortion("opencv", k1=0.0578421, k2=-0.0805099, p1=-0.000980296, p2=0.00015141)  # instant-ngp's fox
STRONG = Distortion("opencv", k1=-0.28, k2=0.09, k3=-0.01, p1=0.001, p2=-0.002)
FISHEYE = Distortion("fisheye", k1=0.05, k2=-0.01, k3=0.002, k4=-0.0003)


@pytest.mark.parametrize("lens", [FOX, STRONG, FISHEYE], ids=["fox", "strong", "fisheye"])
def test_a_projected_point_and_its_ray_round_trip(lens):
    g = torch.Generator().manual_seed(0)
    x = (torch.rand(20000, generator=g, dtype=torch.float64) - 0.5) * 1.4
    y = (torch.rand(20000, generator=g, dtype=torch.float64) - 0.5) * 1.0
    xd, yd = distort(lens, x, y)
    assert (xd - x).abs().max() > 1e-3  # the lens does bend these points
    d = ray_directions(lens, xd, yd)
    assert torch.allclose(d.norm(dim=-1), torch.ones_like(x))
    assert torch.allclose(d[:, 0] / d[:, 2], x, atol=1e-10) and torch.allclose(d[:, 1] / d[:, 2], y, atol=1e-10)


def test_the_radial_tangential_model_is_opencvs():
    lens = Distortion("opencv", k1=0.1, k2=0.01, k3=0.001, p1=0.002, p2=0.003)
    x, y = torch.tensor([0.3], dtype=torch.float64), torch.tensor([-0.2], dtype=torch.float64)
    r2 = 0.13
    s = 1 + 0.1 * r2 + 0.01 * r2**2 + 0.001 * r2**3
    expect_x = 0.3 * s + 2 * 0.002 * 0.3 * -0.2 + 0.003 * (r2 + 2 * 0.09)
    expect_y = -0.2 * s + 0.002 * (r2 + 2 * 0.04) + 2 * 0.003 * 0.3 * -0.2
    xd, yd = distort(lens, x, y)
    assert float(xd) == pytest.approx(expect_x, abs=1e-15) and float(yd) == pytest.approx(expect_y, abs=1e-15)


def test_fisheye_sees_past_ninety_degrees():
    lens = Distortion("fisheye")  # equidistant: distance from the centre is the angle
    rd = torch.tensor([0.0, 1.0, math.pi / 2, 1.9], dtype=torch.float64)
    d = ray_directions(lens, rd, torch.zeros_like(rd))
    angles = torch.atan2(d[:, 0], d[:, 2])
    assert torch.allclose(angles, rd, atol=1e-12) and d[3, 2] < 0  # 1.9 rad: looking slightly backwards


def test_pinhole_directions_are_the_design_cards():
    i, j = torch.tensor([0.5, 10.5]), torch.tensor([0.5, 3.5])
    d = camera_directions(50.0, 40.0, 8.0, 6.0, i, j, None)
    assert torch.allclose(
        d, torch.tensor([[(0.5 - 8) / 50, -(0.5 - 6) / 40, -1.0], [(10.5 - 8) / 50, -(3.5 - 6) / 40, -1.0]])
    )
    # A distorted camera's ray through a pixel points where the lens maps that pixel from.
    dd = camera_directions(50.0, 40.0, 8.0, 6.0, i, j, FOX).double()
    xd, yd = distort(FOX, -dd[:, 0] / dd[:, 2], dd[:, 1] / dd[:, 2])  # back to OpenCV axes, then distort
    assert np.allclose(xd.numpy(), ((i - 8) / 50).numpy(), atol=1e-6) and np.allclose(
        yd.numpy(), ((j - 6) / 40).numpy(), atol=1e-6
    )


def test_unknown_lens_model_is_refused():
    with pytest.raises(ValueError, match="unknown lens model 'kannala'"):
        Distortion("kannala")
