"""Load NeRF with a real capture's NeRF: unbounded (a background around an inner box), any scale."""

from __future__ import annotations

import json

import numpy as np
import pytest
from fixtures.blender_objects import engine_render, scene_with_nerf
from fixtures.sphere_data import look_at
from PIL import Image

SMALL = dict(
    n_levels=4,
    n_features=2,
    log2_table_size=12,
    base_resolution=8,
    finest_resolution=64,
    density_hidden=16,
    geo_feat_dim=7,
    color_hidden=16,
    occ_resolution=32,
)


def _unbounded_checkpoint(path, aabb, seed=0):
    """An unbounded NeRF whose random field fills all of space (every ray ends somewhere)."""
    import torch

    from blender_nerf_deform.engine.nerf.checkpoint import save_nerf
    from blender_nerf_deform.engine.nerf.model import NerfConfig, NerfModel

    torch.manual_seed(seed)
    m = NerfModel(NerfConfig(contraction="linf", aabb=list(aabb), **SMALL))
    with torch.no_grad():
        m.encoding.table.uniform_(-1, 1)
    m.occupancy.update(m.density, m.config.render_step, 0.0)
    m.background.update(m.density, m.config.render_step, 0.0)
    save_nerf(m, path)
    return path


def test_load_nerf_shows_the_inner_box_of_an_unbounded_nerf_and_says_so(addon, tmp_path):
    bpy = addon
    ckpt = _unbounded_checkpoint(tmp_path / "room" / "nerf.ckpt", [-1.0, -2.0, -1.5, 1.0, 2.0, 1.5])
    assert bpy.ops.nerf_deform.load_nerf(filepath=str(ckpt)) == {"FINISHED"}
    nerf = bpy.context.active_object
    assert list(nerf.nerf_deform.aabb) == pytest.approx([-1.0, -2.0, -1.5, 1.0, 2.0, 1.5])
    assert nerf.empty_display_size == pytest.approx(2.0) and tuple(nerf.scale) == pytest.approx((1, 1, 1))


def test_load_nerf_brings_a_capture_in_odd_units_to_a_workable_size(addon, tmp_path):
    bpy = addon
    ckpt = _unbounded_checkpoint(tmp_path / "colmap_units" / "nerf.ckpt", [-400.0, -300.0, -200.0, 400.0, 300.0, 200.0])
    assert bpy.ops.nerf_deform.load_nerf(filepath=str(ckpt)) == {"FINISHED"}
    nerf = bpy.context.active_object
    assert tuple(nerf.scale) == pytest.approx((3 / 800,) * 3)
    # The box on screen is what the NeRF's inner region is, scaled: 3 units across.
    corners = [nerf.matrix_world @ __import__("mathutils").Vector(c) for c in ((-400, -300, -200), (400, 300, 200))]
    assert (corners[1] - corners[0]).x == pytest.approx(3.0)


@pytest.mark.slow
def test_f12_of_an_unbounded_nerf_matches_the_engine_and_fills_the_frame(addon, tmp_path):
    bpy = addon
    ckpt = _unbounded_checkpoint(tmp_path / "room" / "nerf.ckpt", [-1.5, -1.5, -1.5, 1.5, 1.5, 1.5])
    frame = {"file_path": "images/v.png", "transform_matrix": look_at((0.4, -2.6, 0.5)).tolist()}
    meta = {"camera_angle_x": 1.0, "w": 24, "h": 24, "frames": [frame]}
    (tmp_path / "one.json").write_text(json.dumps(meta))
    engine_render(ckpt, tmp_path / "one.json", tmp_path / "cli")
    expected = np.asarray(Image.open(tmp_path / "cli" / "v.png").convert("RGBA"), dtype=np.int16)
    scene_with_nerf(bpy, ckpt, frame, 1.0, 24)
    bpy.context.scene.render.filepath = str(tmp_path / "blender.png")
    assert bpy.ops.render.render(write_still=True) == {"FINISHED"}
    got = np.asarray(Image.open(tmp_path / "blender.png").convert("RGBA"), dtype=np.int16)
    assert expected[..., 3].min() > 200  # the background is part of the NeRF: nothing is transparent
    assert np.abs(got[..., 3] - expected[..., 3]).max() <= 2
    assert np.abs(got[..., :3] - expected[..., :3]).max() <= 3
