"""Baking the posed NeRF on a voxel grid (bend/volume.py, `bake-volume`): the grid holds the NeRF's own
density where it should, follows a pose of the cage exactly, keeps optical depth under a scale, is the
same whatever runs it, and refuses bad requests before any work."""

import subprocess
import sys

import numpy as np
import pytest
import torch
from fixtures import REPO
from fixtures.ball_model import ball_model

from blender_nerf_deform.engine.bend.baked_volume import box_of_bounds, load_baked, volume_grid
from blender_nerf_deform.engine.bend.cage_bend import CageBend
from blender_nerf_deform.engine.bend.volume import bake_box, bake_volume
from blender_nerf_deform.engine.errors import EngineError
from blender_nerf_deform.engine.geometry.cage import box_cage
from blender_nerf_deform.engine.geometry.region import region_from_dict


@pytest.fixture(scope="module")
def ball():
    return ball_model(0)


def _dense(baked, what="density"):
    values = getattr(baked, what)
    out = np.zeros(baked.grid.shape + values.shape[1:], dtype=np.float32)
    out[tuple(baked.index.T)] = values
    return out


def test_rest_bake_holds_the_nerfs_density_at_the_voxel_centres(ball):
    grid = volume_grid(box_of_bounds(ball.aabb.numpy()), 24)
    baked = bake_volume(ball, grid)
    assert grid.shape == (24, 24, 24) and baked.stats["dense_voxels"] > 100
    ijk = np.argwhere(np.ones(grid.shape, bool))
    points = torch.as_tensor(grid.points(ijk), dtype=torch.float32)
    with torch.no_grad():
        want = (ball.density(points) * ball.occupancy.occupied(points)).numpy().reshape(grid.shape)
    np.testing.assert_allclose(_dense(baked), want, rtol=1e-5, atol=1e-5)
    # Voxel (0,0,0)'s centre is half a voxel inside the box's corner.
    assert np.allclose(grid.points(np.zeros((1, 3))), ball.aabb.numpy()[0] + 0.5 * 3.0 / 24)
    # Colours are in [0, 1]; the empty voxels next to dense ones carry colour (no black fringe).
    color = baked.color
    assert color.min() >= 0 and color.max() <= 1
    shell = baked.density == 0
    assert shell.any() and (color[shell].sum(1) > 0).all()


def test_a_moved_cage_moves_the_baked_content_by_whole_voxels(ball):
    # A cage over the whole box; the pose shifts everything by exactly 3 voxels along x.
    grid = volume_grid(box_of_bounds(ball.aabb.numpy()), 24)
    rest, tets = box_cage((4, 4, 4), lo=(-1.6, -1.6, -1.6), hi=(1.6, 1.6, 1.6))
    voxel = grid.voxel_size
    plain = _dense(bake_volume(ball, grid))
    same = _dense(bake_volume(ball, grid, CageBend(ball, rest, tets).set_deformed(rest)))
    np.testing.assert_allclose(same, plain, rtol=1e-4, atol=1e-3)
    moved = _dense(bake_volume(ball, grid, CageBend(ball, rest, tets).set_deformed(rest + [3 * voxel, 0, 0])))
    np.testing.assert_allclose(moved[3:], plain[:-3], rtol=1e-3, atol=1e-2)
    assert moved[:3].max() == 0  # vacated: the rest cage held it, nothing maps there now


def test_a_scaled_pose_scales_the_density_so_optical_depth_stays(ball):
    # 49 voxels over the box: voxel centres at whole multiples of the voxel size, so the pose that
    # halves the content maps posed voxel i onto rest voxel 2i - 24 exactly.
    grid = volume_grid(box_of_bounds(ball.aabb.numpy()), 49)
    rest, tets = box_cage((4, 4, 4), lo=(-1.5, -1.5, -1.5), hi=(1.5, 1.5, 1.5))
    plain = _dense(bake_volume(ball, grid))
    half = _dense(bake_volume(ball, grid, CageBend(ball, rest, tets).set_deformed(rest * 0.5)))
    # Half the size, twice the density (|det A|^(1/3) = 2): a ray through it keeps its optical depth.
    np.testing.assert_allclose(half[12:37, 12:37, 12:37], 2 * plain[0:49:2, 0:49:2, 0:49:2], rtol=1e-3, atol=1e-3)
    assert plain.max() > 1 and half[:12].max() == 0 and half[37:].max() == 0


def test_baking_is_deterministic_and_a_region_grid_follows_the_regions_axes(ball):
    region = region_from_dict({"center": [0.2, 0, 0], "size": [0.8, 0.6, 1.4], "rotation_euler": [0.3, 0.0, 0.7]})
    grid = volume_grid(bake_box(region, ball), 20)
    assert grid.shape == (12, 9, 20)
    # Its index axes are the region's axes, its centre the region's centre.
    axes = grid.index_to_nerf[:3, :3] / grid.voxel_size
    assert np.allclose(axes, region.rotation)
    centre = grid.points(np.array([[5.5, 4.0, 9.5]]))[0]
    assert np.allclose(centre, region.center)
    a, b = bake_volume(ball, grid), bake_volume(ball, grid)
    assert a.index.tobytes() == b.index.tobytes() and a.density.tobytes() == b.density.tobytes()
    assert a.color.tobytes() == b.color.tobytes() and len(a.index) > 0


def test_bad_bakes_are_refused_before_any_work(ball):
    box = box_of_bounds(ball.aabb.numpy())
    for bad in (0, -3, 2.5, True, 10**6):
        with pytest.raises(EngineError, match="resolution must be a whole number"):
            volume_grid(box, bad)
    with pytest.raises(EngineError, match=r"a 2048x2048x2048 volume needs about .* GiB of memory"):
        bake_volume(ball, volume_grid(box, 2048))
    far = region_from_dict({"center": [9, 9, 9], "size": [1, 1, 1], "rotation_euler": [0, 0, 0]})
    with pytest.raises(EngineError, match="lies outside the NeRF's box"):
        bake_box(far, ball)
    with pytest.raises(EngineError, match="the cage's box needs a cage"):
        bake_box("cage", ball)
    with pytest.raises(EngineError, match="supersample must be a whole number"):
        bake_volume(ball, volume_grid(box, 4), supersample=0)


def _cli(*args):
    return subprocess.run(
        [sys.executable, "-m", "blender_nerf_deform.engine", *map(str, args)], cwd=REPO, capture_output=True, text=True
    )


@pytest.mark.slow
def test_cli_bakes_one_volume_per_pose(sphere_nerf, tmp_path):
    from blender_nerf_deform.engine.geometry.mesh_io import save_cage

    ckpt, _data = sphere_nerf
    rest, tets = box_cage((3, 3, 3), lo=(-1.5, -1.5, -1.5), hi=(1.5, 1.5, 1.5))
    save_cage(tmp_path / "cage.npz", rest, tets)
    poses = tmp_path / "poses"
    poses.mkdir()
    np.save(poses / "pose_2.npy", rest + [0.0, 0.0, 0.5])
    np.save(poses / "pose_1.npy", rest)
    proc = _cli(
        "bake-volume",
        "--nerf",
        ckpt,
        "--out",
        tmp_path / "vol",
        "--cage",
        tmp_path / "cage.npz",
        "--deformed",
        poses,
        "--resolution",
        "32",
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert sorted(p.name for p in (tmp_path / "vol").iterdir()) == ["pose_1.npz", "pose_2.npz"]
    first, second = load_baked(tmp_path / "vol" / "pose_1.npz"), load_baked(tmp_path / "vol" / "pose_2.npz")
    assert first.grid.shape == (32, 32, 32) and len(first.index) > 0

    # Lifted by 0.5 (16/3 voxels): the content's centre of mass rises by about that much.
    def centre_z(b):
        return float((b.index[:, 2] * b.density).sum() / b.density.sum())

    assert centre_z(second) - centre_z(first) == pytest.approx(0.5 / (3.0 / 32), abs=0.5)

    proc = _cli("bake-volume", "--nerf", ckpt, "--out", tmp_path / "rest", "--resolution", "16", "--extent", "cage")
    assert proc.returncode == 2 and "--extent cage needs --cage and --deformed" in proc.stderr
    assert not (tmp_path / "rest").exists()
    proc = _cli("bake-volume", "--nerf", ckpt, "--out", tmp_path / "rest", "--resolution", "0")
    assert (
        proc.returncode == 2 and "resolution must be a whole number" in proc.stderr and "Traceback" not in proc.stderr
    )
    proc = _cli("bake-volume", "--nerf", ckpt, "--out", tmp_path / "rest", "--resolution", "16")
    assert proc.returncode == 0 and (tmp_path / "rest" / "rest.npz").is_file()
