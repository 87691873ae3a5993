"""A frame rendered in many chunks of tiles equals the same frame rendered in one chunk (no seams), plain
and ray-bent, on both code paths; the fast frame path agrees with the legacy one."""

import numpy as np
import pytest
import torch
from fixtures.ball_model import ball_model
from fixtures.sphere_data import look_at

from blender_nerf_deform.engine import backend
from blender_nerf_deform.engine.geometry.cage import box_cage
from blender_nerf_deform.engine.nerf import renderer
from blender_nerf_deform.engine.nerf.renderer import Camera, camera_rays, render_image, render_rays

W, H = 150, 97  # not a multiple of the tile size: the last tile row and column are cut


@pytest.fixture(scope="module")
def model():
    """A ball of radius ~0.9 (through the coarsest, dense level of the hash grid) with a soft shell,
    colours and hash noise from the finer levels, so that rays end at different depths."""
    return ball_model(3, radius=0.9, table_noise=0.3, feature_noise=0.5)


def _camera():
    return Camera.from_fov(look_at((0.4, -2.4, 0.8)), W, H, 0.75, name="cam")


def _bend(model, pose):
    from blender_nerf_deform.engine.bend.cage_bend import CageBend

    rest, tets = box_cage((4, 4, 4), lo=(-1.0,) * 3, hi=(1.0,) * 3)
    if pose == "identity":
        deformed = rest
    else:  # twist the upper half about z
        a = 0.5 * np.clip(rest[:, 2], 0, None)
        deformed = np.stack(
            [
                np.cos(a) * rest[:, 0] - np.sin(a) * rest[:, 1],
                np.sin(a) * rest[:, 0] + np.cos(a) * rest[:, 1],
                rest[:, 2],
            ],
            axis=1,
        )
    bend = CageBend(model, rest, tets).set_deformed(deformed)
    return {"sample_transform": bend.sample_transform, "occupancy": bend.occupancy}


def _one_chunk(model, camera, **kw):
    """The frame as one chunk of rays in row order (what a small frame is)."""
    o, d = camera_rays(camera)
    with torch.no_grad():
        out = render_rays(model, o, d, chunk=o.shape[0], **kw)
    a = out["alpha"].clamp(0, 1)
    straight = torch.where(a[:, None] > 1e-6, out["color"] / a.clamp_min(1e-6)[:, None], torch.zeros_like(out["color"]))
    return torch.cat([straight.clamp(0, 1), a[:, None]], -1).reshape(camera.height, camera.width, 4).numpy()


def _paths():
    return ("auto", "torch") if backend.HAVE_NUMBA else ("torch",)


@pytest.mark.parametrize("pose", [None, "twist"])
@pytest.mark.parametrize("path", _paths())
def test_a_frame_in_many_chunks_equals_the_frame_in_one(model, pose, path):
    camera = _camera()
    with backend.forced(path):
        kw = _bend(model, pose) if pose else {}
        whole = _one_chunk(model, camera, **kw)
        # 211 rays per chunk: chunks end inside tiles and inside rows of tiles; and the default chunk.
        chunked = render_image(model, camera, chunk=211, **kw)
        default = render_image(model, camera, **kw)
    alpha = whole[..., 3]
    assert alpha.max() > 0.9 and alpha.min() < 0.01 and ((alpha > 0.05) & (alpha < 0.95)).any()
    for out in (chunked, default):
        diff = np.abs(out["rgba"] - whole).max(axis=-1)
        assert diff.max() <= 1e-5, diff.max()
    # No seam at the tile boundaries (rows and columns 32, 64, ...) nor at the chunk boundaries: the pixels
    # on both sides of each equal the one-chunk frame's, and the frame has content across them.
    diff = np.abs(chunked["rgba"] - whole).max(axis=-1)
    for b in range(renderer.TILE, W, renderer.TILE):
        assert diff[:, b - 1 : b + 1].max() <= 1e-5
    for b in range(renderer.TILE, H, renderer.TILE):
        assert diff[b - 1 : b + 1, :].max() <= 1e-5
    cols, rows = list(range(renderer.TILE, W, renderer.TILE)), list(range(renderer.TILE, H, renderer.TILE))
    assert (alpha[:, cols] > 0.5).any() and (alpha[rows, :] > 0.5).any()
    order = renderer.tile_order(W, H).numpy()
    ends = order[np.arange(211, W * H, 211)]  # the first pixel of each chunk after the first
    assert diff.reshape(-1)[ends].max() <= 1e-5 and (alpha.reshape(-1)[ends] > 0.5).any()
    # The same samples whatever the chunks (matrix products of other sizes may round differently).
    np.testing.assert_allclose(chunked["rgba"], default["rgba"], atol=1e-6)
    assert chunked["density_samples_per_ray"] == default["density_samples_per_ray"]
    assert chunked["color_samples_per_ray"] == default["color_samples_per_ray"]


def test_the_kernels_and_the_torch_path_render_the_same_frame(model):
    if not backend.HAVE_NUMBA:
        pytest.skip("numba is not installed: the torch path is the only one")
    camera = _camera()
    frames = {}
    for path in ("auto", "torch"):
        with backend.forced(path):
            frames[path] = render_image(model, camera, chunk=1000, **_bend(model, "twist"))
    # The two point locators (float64 kernels, float32 torch) may put a sample on a tet face in either
    # tet, whose view directions turn differently (test_bending_edits): a few pixels differ a little.
    diff = np.abs(frames["auto"]["rgba"] - frames["torch"]["rgba"])
    assert diff.max() <= 5e-3 and float(np.mean(diff)) <= 1e-5
    a, b = frames["auto"]["density_samples_per_ray"], frames["torch"]["density_samples_per_ray"]
    assert abs(a - b) <= 1e-2 * a  # their deformed occupancy grids differ by a few cells (pre-existing)
    with backend.forced("torch"):  # and without the bend, the same frame to float rounding
        plain_torch = render_image(model, camera, chunk=1000)
    plain = render_image(model, camera, chunk=1000)
    assert np.abs(plain["rgba"] - plain_torch["rgba"]).max() <= 1e-5
    assert plain["density_samples_per_ray"] == plain_torch["density_samples_per_ray"]


def test_identity_pose_equals_undeformed_and_fast_equals_legacy(model):
    camera = _camera()
    plain = render_image(model, camera)
    identity = render_image(model, camera, **_bend(model, "identity"))
    np.testing.assert_allclose(identity["rgba"], plain["rgba"], atol=1e-5)
    with renderer.render_path("legacy"):
        legacy = render_image(model, camera)
    # The paths end rays after different rounds: what a retired ray could still add (transmittance
    # below 1e-4) is all they may differ by.
    assert np.abs(legacy["rgba"] - plain["rgba"]).max() <= 2e-3
    mse = float(np.mean((legacy["rgba"].astype(np.float64) - plain["rgba"]) ** 2))
    assert -10 * np.log10(mse) >= 60
    assert plain["density_samples_per_ray"] <= legacy["density_samples_per_ray"]
