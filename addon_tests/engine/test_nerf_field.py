"""The hash-grid field: the fast encoding agrees with the obvious one, dense levels are trilinear, SH are
orthonormal."""

import math

import numpy as np
import pytest
import torch
from scipy.interpolate import RegularGridInterpolator

from blender_nerf_deform.engine import backend
from blender_nerf_deform.engine.nerf.encoding import HashEncoding, reference_hash_encode, sh_encode
from blender_nerf_deform.engine.nerf.model import NerfConfig, NerfModel

PATHS = ["torch"] + (["kernels"] if backend.HAVE_NUMBA else [])


@pytest.fixture(autouse=True)
def _code_path(request):
    """Tests parametrized by `path` run on that code path (backend.py decides it for the whole engine)."""
    callspec = getattr(request.node, "callspec", None)
    path = callspec.params.get("path") if callspec is not None else None
    with backend.forced("torch" if path == "torch" else "auto"):
        yield


def _encoding(path, **kw):
    torch.manual_seed(0)
    enc = HashEncoding(
        **{"n_levels": 6, "n_features": 4, "log2_table_size": 12, "base_resolution": 4, "finest_resolution": 96, **kw}
    )
    with torch.no_grad():
        enc.table.uniform_(-1, 1)
    return enc


@pytest.mark.parametrize("path", PATHS)
def test_encoding_matches_reference_values_and_table_gradient(path):
    enc = _encoding(path)
    assert any(enc.dense_levels) and not all(enc.dense_levels)  # both kinds of level are exercised
    x = torch.rand(3000, 3, dtype=torch.float32)
    x[:10] = torch.tensor([0.0, 1.0, 0.5])  # faces of the unit cube
    weights = torch.randn(3000, enc.out_dim)
    fast = enc(x)
    (fast * weights).sum().backward()
    g_fast = enc.table.grad.clone()
    enc.table.grad = None
    ref = reference_hash_encode(enc, x)
    (ref * weights).sum().backward()
    assert torch.allclose(fast, ref, atol=1e-5), (fast - ref).abs().max()
    assert torch.allclose(g_fast, enc.table.grad, atol=1e-4), (g_fast - enc.table.grad).abs().max()
    assert g_fast.abs().sum() > 0


@pytest.mark.parametrize("path", PATHS)
def test_reused_encoding_backward_matches_a_fresh_one(path):
    enc = _encoding(path)
    x = torch.rand(500, 3)
    w = torch.randn(500, enc.out_dim)
    with torch.no_grad():
        stored = enc(x)
    (enc.reuse(stored, x) * w).sum().backward()
    g1 = enc.table.grad.clone()
    enc.table.grad = None
    (enc(x) * w).sum().backward()
    assert torch.allclose(g1, enc.table.grad, atol=1e-5)


@pytest.mark.parametrize("path", PATHS)
def test_position_gradient_matches_the_reference_and_finite_differences(path):
    """Camera pose refinement moves rays by the gradient of the encoding in its positions: on both code
    paths it is autograd's through the reference (dense and hashed levels), agrees with central
    differences in float64, and is zero along an axis clamped at the unit cube's faces."""
    enc = _encoding(path)
    torch.manual_seed(1)
    x = torch.rand(2000, 3) * 0.98 + 0.01
    x[:5, 0] = torch.tensor([-0.5, 1.5, 2.0, -1e-3, 1.0 + 1e-3])  # outside along x: clamped
    w = torch.randn(2000, enc.out_dim)
    xa = x.clone().requires_grad_(True)
    (enc(xa) * w).sum().backward()
    xr = x.clone().requires_grad_(True)
    (reference_hash_encode(enc, xr) * w).sum().backward()
    assert (xa.grad[5:] != 0).all(dim=1).float().mean() > 0.99  # inside the cube every axis has a gradient
    assert torch.allclose(xa.grad[5:], xr.grad[5:], rtol=1e-3, atol=2e-2), (xa.grad - xr.grad).abs().max()
    assert torch.all(xa.grad[:5, 0] == 0) and torch.all(xa.grad[:5, 1:] != 0)
    # Central differences of the float64 reference, away from the cell faces of every level.
    table64 = [
        t.detach().double() for t in (enc.table[int(o) : int(o) + s] for o, s in zip(enc.offsets, enc.level_sizes))
    ]
    pts = x[5:25].double()
    h = 1e-7
    for axis in range(3):
        e = torch.zeros(3, dtype=torch.float64)
        e[axis] = h
        plus = (reference_hash_encode(enc, pts + e, table64) * w[5:25].double()).sum(dim=1)
        minus = (reference_hash_encode(enc, pts - e, table64) * w[5:25].double()).sum(dim=1)
        numeric = (plus - minus) / (2 * h)
        assert torch.allclose(xa.grad[5:25, axis].double(), numeric, rtol=1e-3, atol=1e-2), axis
    # The reused encoding (training's second pass) gives the positions the same gradient.
    with torch.no_grad():
        stored = enc(x)
    xb = x.clone().requires_grad_(True)
    (enc.reuse(stored, xb) * w).sum().backward()
    assert torch.allclose(xb.grad, xa.grad, atol=1e-5)


@pytest.mark.parametrize("path", PATHS)
def test_a_dense_level_is_exactly_trilinear_interpolation(path):
    res = 7
    enc = _encoding(path, n_levels=1, base_resolution=res, finest_resolution=res, log2_table_size=10, n_features=2)
    assert enc.dense_levels == [True] and enc.level_sizes == [(res + 1) ** 3]
    grid = np.linspace(0, 1, res + 1)
    # Row x + (R+1) y + (R+1)^2 z  <=>  values[z, y, x].
    values = enc.table.detach().numpy().reshape(res + 1, res + 1, res + 1, 2)
    x = torch.rand(2000, 3)
    got = enc(x).detach().numpy()
    for f in range(2):
        interp = RegularGridInterpolator((grid, grid, grid), values[..., f], method="linear")
        want = interp(x.numpy()[:, ::-1].astype(np.float64))  # (z, y, x) order
        np.testing.assert_allclose(got[:, f], want, atol=1e-5)


def test_hashed_levels_use_instant_ngp_hash_and_table_size():
    enc = _encoding("torch", n_levels=2, base_resolution=64, finest_resolution=128, log2_table_size=10)
    assert enc.dense_levels == [False, False] and enc.level_sizes == [1024, 1024]
    x = torch.tensor([[3.0 / 64, 5.0 / 64, 7.0 / 64]])  # exactly grid point (3, 5, 7) of level 0
    idx, w = enc.indices_and_weights(x)
    corner0 = int(idx[0, 0, int(torch.argmax(w[0, 0]))])
    assert corner0 == (3 ^ (5 * 2654435761) ^ (7 * 805459861)) % 1024
    assert float(w[0, 0].max()) == pytest.approx(1.0)


def test_spherical_harmonics_are_orthonormal_on_the_sphere():
    n = 20000
    k = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1 - 2 * k / n
    phi = k * math.pi * (3 - math.sqrt(5))
    r = torch.sqrt(1 - z * z)
    d = torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], -1)
    y = sh_encode(d, 4)
    assert y.shape == (n, 16)
    gram = (4 * math.pi / n) * y.T @ y
    assert torch.allclose(gram, torch.eye(16, dtype=torch.float64), atol=2e-3)


def test_model_density_is_nonnegative_zero_outside_and_query_shapes():
    model = NerfModel(NerfConfig(log2_table_size=12, finest_resolution=64, occ_resolution=16))
    pts = torch.rand(100, 3) * 4 - 2  # some outside [-1.5, 1.5]^3
    sigma, rgb = model.query(pts, torch.randn(100, 3))
    assert sigma.shape == (100,) and rgb.shape == (100, 3)
    assert (sigma >= 0).all() and ((rgb >= 0) & (rgb <= 1)).all()
    outside = (pts.abs() > 1.5).any(-1)
    assert outside.any() and (sigma[outside] == 0).all() and (sigma[~outside] > 0).all()
    assert torch.equal(model.density(pts), sigma.detach())
