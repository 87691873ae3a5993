"""Edit regions, picking and the pinned cut, on an analytic scene with a known geometry.

The scene: a statue (a column with a ball on it) standing on a floor slab, a box beside it
and a wall behind, as one density field (a soft step of width SOFT across each surface), so
that the statue is fused with the floor as in a real capture. The region is an oriented box
around the statue whose bottom face lies just above the floor: it cuts the statue's foot.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from blender_nerf_deform.engine.errors import EngineError
from blender_nerf_deform.engine.geometry.cage import PIN_DEPTH, build_cage, check_closed_mesh, cut_from_region, cut_pins
from blender_nerf_deform.engine.geometry.embedding import embed_points
from blender_nerf_deform.engine.geometry.extract import extract_mesh
from blender_nerf_deform.engine.geometry.handle_pose import RegionDeformer
from blender_nerf_deform.engine.geometry.mesh_io import load_cage, read_ply, save_cage, write_ply
from blender_nerf_deform.engine.geometry.region import euler_xyz_matrix, load_region, region_from_dict

BOUNDS = [[-1.5, -1.5, -1.5], [1.5, 1.5, 1.5]]
SOFT = 0.02
FLOOR_TOP = -1.0
ISO = SOFT * np.log(9.0)  # the surface at density 10 lies this far outside the shapes (100 / (1 + 9) = 10)


def statue_sdf(p):
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    column = np.maximum(np.hypot(x, y) - 0.25, np.abs(z + 0.4) - 0.6)  # z -1.0 .. 0.2
    ball = np.linalg.norm(p - [0.0, 0.0, 0.5], axis=1) - 0.4  # z 0.1 .. 0.9
    return np.minimum(column, ball)


def scene_sdf(p):
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    floor = np.maximum(np.abs(z - (FLOOR_TOP - 0.1)) - 0.1, np.maximum(np.abs(x) - 1.4, np.abs(y) - 1.4))
    box = np.max(np.abs(p - [0.75, 0.0, -0.7]), axis=1) - 0.15  # stands on the floor, inside the region
    wall = np.maximum(np.abs(y - 1.1) - 0.1, np.maximum(np.abs(x) - 1.4, np.abs(z + 0.2) - 0.9))
    return np.minimum.reduce([floor, statue_sdf(p), box, wall])


def density(p):
    return 100.0 / (1.0 + np.exp(np.clip(scene_sdf(p) / SOFT, -50, 50)))


# Around the statue and the box, turned 0.3 rad about z; its bottom at z = -0.95 (the floor's top is -1).
REGION = {"center": [0.2, 0.0, 0.0], "size": [1.5, 1.2, 1.9], "rotation_euler": [0.0, 0.0, 0.3]}


@pytest.fixture(scope="module")
def picked():
    region = region_from_dict(REGION)
    return region, extract_mesh(density, BOUNDS, resolution=96, region=region, pick=[0.0, 0.0, 0.92])


def test_euler_follows_blenders_xyz_order():
    angles = [0.3, -1.1, 2.0]
    expected = Rotation.from_euler("xyz", angles).as_matrix()  # extrinsic x, y, z: Blender's XYZ
    assert np.allclose(euler_xyz_matrix(*angles), expected, atol=1e-12)
    region = region_from_dict({"center": [1, 2, 3], "size": [1, 2, 3], "rotation_euler": angles})
    back = region_from_dict(region.to_dict())
    assert np.allclose(back.rotation, region.rotation, atol=1e-9) and np.allclose(back.center, [1, 2, 3])


def test_region_box_overlap():
    region = region_from_dict({"center": [2.0, 0, 0], "size": [1.0, 1.0, 1.0], "rotation_euler": [0, 0, np.pi / 4]})
    # The turned unit box reaches x = 2 - sqrt(0.5) = 1.29 < 1.5: it overlaps the box.
    assert region.overlaps_box(BOUNDS)
    far = region_from_dict({"center": [2.3, 0, 0], "size": [1.0, 1.0, 1.0], "rotation_euler": [0, 0, np.pi / 4]})
    assert not far.overlaps_box(BOUNDS)
    # Overlapping in each axis's extent but apart along a diagonal: only the rotated axes separate them.
    diag = region_from_dict({"center": [2.0, 2.0, 0], "size": [0.2, 1.3, 0.2], "rotation_euler": [0, 0, np.pi / 4]})
    assert np.all(diag.world_bounds()[0][:2] < 1.5) and not diag.overlaps_box(BOUNDS)


def test_extraction_stays_in_the_region_and_closes_the_cut(picked):
    region, res = picked
    check_closed_mesh(res.vertices, res.faces)  # the cage can be built on it
    local = region.to_local(res.vertices)
    spacing = float(region.size.max()) / 95
    assert np.all(np.abs(local) <= region.half + spacing + 1e-9)
    # The cut is where the region's bottom crosses the column: a disc of radius 0.25 at z = -0.95.
    cut = res.vertices[res.cut]
    assert len(cut) > 50
    assert np.all(np.abs(cut[:, 2] - (-0.95)) <= spacing + 1e-9)
    assert np.hypot(cut[:, 0], cut[:, 1]).max() <= 0.25 + ISO + spacing
    # The resolution was spent in the region: finer than sampling the whole box at 96.
    assert spacing < (BOUNDS[1][0] - BOUNDS[0][0]) / 95 / 1.5
    assert "picked the part connected to" in res.report() and "closed along the cut" in res.report()


def test_pick_keeps_the_statue_not_the_box_floor_or_wall(picked):
    _region, res = picked
    d_statue = np.abs(statue_sdf(res.vertices) - ISO)
    on_cap = res.cut
    # Every vertex is on the statue's surface (within a voxel), bar the cap.
    assert np.all(d_statue[~on_cap] < 0.02), d_statue[~on_cap].max()
    # The statue is there entirely above the cut: its top and its sides.
    assert res.vertices[:, 2].max() > 0.85 and np.hypot(res.vertices[:, 0], res.vertices[:, 1]).max() > 0.37
    # Without the pick, the box beside it is kept as well (the floater filter keeps big parts).
    region = region_from_dict(REGION)
    whole = extract_mesh(density, BOUNDS, resolution=96, region=region)
    near_box = np.max(np.abs(whole.vertices - [0.75, 0.0, -0.7]), axis=1) < 0.2
    assert near_box.sum() > 100 and not np.any(np.max(np.abs(res.vertices - [0.75, 0.0, -0.7]), axis=1) < 0.2)


def test_cage_is_pinned_at_the_cut_and_the_foot_stays(picked):
    _region, res = picked
    cage = build_cage(res.vertices, res.faces)
    pins = cut_pins(cage.vertices, res.vertices, res.cut, cage.margin)
    assert len(pins) > 10
    assert cage.vertices[pins][:, 2].max() < -0.95 + PIN_DEPTH * cage.margin + 0.01  # at the foot, not up the statue
    embedding = embed_points(res.vertices, cage.vertices, cage.tets)
    top = np.flatnonzero(res.vertices[:, 2] > 0.6)
    lift = np.eye(4)
    lift[:3, :3] = euler_xyz_matrix(0.0, 0.0, np.radians(30))
    lift[2, 3] = 0.3
    foot = cage.vertices[:, 2] < -0.9
    pinned_pose, stats = RegionDeformer(cage.vertices, cage.tets, embedding, [top], cage_pins=pins).solve([lift])
    assert stats["converged"] and stats["min_det_f"] > 0
    # The cut's pins are soft (surface_arap): they stay within a thousandth of the cage's size.
    diag = np.linalg.norm(np.ptp(cage.vertices, axis=0))
    assert np.linalg.norm(pinned_pose[pins] - cage.vertices[pins], axis=1).max() < 1e-3 * diag
    assert np.linalg.norm(pinned_pose[foot] - cage.vertices[foot], axis=1).max() < 0.05
    # The top followed its handle: its cage vertices near the target.
    tip = cage.vertices[:, 2] > 0.8
    moved_tip = cage.vertices[tip] @ lift[:3, :3].T + lift[:3, 3]
    assert np.linalg.norm(pinned_pose[tip] - moved_tip, axis=1).max() < 0.1
    # Without the pins the whole statue (foot included) flies off with its handle.
    free_pose, _ = RegionDeformer(cage.vertices, cage.tets, embedding, [top]).solve([lift])
    assert np.linalg.norm(free_pose[foot] - cage.vertices[foot], axis=1).min() > 0.25


def test_cut_travels_through_the_ply_and_the_cage_file(picked, tmp_path):
    _region, res = picked
    write_ply(tmp_path / "m.ply", res.vertices, res.faces, res.colors, cut=res.cut)
    v, f, _c, cut = read_ply(tmp_path / "m.ply", with_cut=True)
    assert np.array_equal(cut, res.cut) and len(v) == len(res.vertices)
    # A mesh without flags (exported by another tool) gets its cut back from the region.
    write_ply(tmp_path / "plain.ply", res.vertices, res.faces)
    assert read_ply(tmp_path / "plain.ply", with_cut=True)[3] is None
    from_region = cut_from_region(res.vertices, region_from_dict(REGION))
    assert from_region[res.cut].mean() > 0.95 and from_region[~res.cut].mean() < 0.01
    V, T = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]]), np.array([[0, 1, 2, 3]])
    save_cage(tmp_path / "c.npz", V, T, pinned_vertices=np.array([1, 2]))
    assert load_cage(tmp_path / "c.npz")["pinned_vertices"].tolist() == [1, 2]
    save_cage(tmp_path / "bad.npz", V, T, pinned_vertices=np.array([1, 7]))
    with pytest.raises(EngineError, match="pinned_vertices"):
        load_cage(tmp_path / "bad.npz")


@pytest.mark.parametrize(
    "data, message",
    [
        ({"center": [0, 0, 0], "size": [1, 0, 1], "rotation_euler": [0, 0, 0]}, "degenerate"),
        ({"center": [0, 0, 0], "size": [1, 1, 1]}, "lacks `rotation_euler`"),
        ({"center": [0, 0, float("nan")], "size": [1, 1, 1], "rotation_euler": [0, 0, 0]}, "finite"),
        ({"center": [0, 0], "size": [1, 1, 1], "rotation_euler": [0, 0, 0]}, "three numbers"),
        ([1, 2, 3], "JSON object"),
    ],
)
def test_bad_regions_are_named(data, message):
    with pytest.raises(EngineError, match=message):
        region_from_dict(data)


def test_bad_region_files(tmp_path):
    (tmp_path / "r.json").write_text("{not json")
    with pytest.raises(EngineError, match="not valid JSON"):
        load_region(tmp_path / "r.json")
    with pytest.raises(EngineError, match="does not exist"):
        load_region(tmp_path / "missing.json")
    (tmp_path / "ok.json").write_text(json.dumps(REGION))
    assert np.allclose(load_region(tmp_path / "ok.json").size, [1.5, 1.2, 1.9])


def test_empty_outside_and_empty_space_picks_are_errors():
    empty_air = region_from_dict({"center": [-1.0, -1.0, 1.2], "size": [0.4, 0.4, 0.4], "rotation_euler": [0, 0, 0]})
    with pytest.raises(EngineError, match=r"empty: the largest density .* is [0-9.e-]+, not above the threshold 10"):
        extract_mesh(density, BOUNDS, resolution=32, region=empty_air)
    outside = region_from_dict({"center": [4.0, 0.0, 0.0], "size": [1.0, 1.0, 1.0], "rotation_euler": [0, 0, 0]})
    with pytest.raises(EngineError, match="lies outside the NeRF's box"):
        extract_mesh(density, BOUNDS, resolution=32, region=outside)
    with pytest.raises(EngineError, match=r"pick point \(-1, -1, 0.5\) is in empty space"):
        extract_mesh(density, BOUNDS, resolution=48, pick=[-1.0, -1.0, 0.5])
    with pytest.raises(EngineError, match="outside the sampled region"):
        extract_mesh(density, BOUNDS, resolution=48, region=region_from_dict(REGION), pick=[-1.4, -1.4, -1.4])


def test_a_region_past_the_box_is_cut_by_the_box_too():
    # Half of this region lies above the box's top (z > 1.5): the wall-free column of a tall
    # object would be cut there; here the ball is sampled whole and nothing beyond 1.5 is asked.
    asked = []

    def tall(p):
        asked.append(p)
        return 100.0 / (1.0 + np.exp(np.clip((np.linalg.norm(p - [0, 0, 1.3], axis=1) - 0.4) / SOFT, -50, 50)))

    region = region_from_dict({"center": [0.0, 0.0, 1.4], "size": [1.2, 1.2, 1.2], "rotation_euler": [0, 0, 0]})
    res = extract_mesh(tall, BOUNDS, resolution=48, region=region)
    assert max(float(a[:, 2].max()) for a in asked) <= 1.5
    check_closed_mesh(res.vertices, res.faces)
    assert res.cut.any() and np.all(res.vertices[res.cut][:, 2] > 1.4)
    assert "outside the NeRF's box" in res.report()


STATUE_REGION = {"center": [0.0, 0.0, 0.0], "size": [0.9, 0.9, 1.9], "rotation_euler": [0.0, 0.0, 0.0]}
BOX_REGION = {"center": [0.75, 0.0, -0.7], "size": [0.5, 0.5, 0.5], "rotation_euler": [0.0, 0.0, 0.2]}


def test_two_regions_give_two_objects_each_with_its_own_cage():
    from blender_nerf_deform.engine.geometry.cage import build_part_cages, part_cut_pins
    from blender_nerf_deform.engine.geometry.embedding import embed_points_by_part
    from blender_nerf_deform.engine.geometry.extract import extract_regions

    regions = [region_from_dict(STATUE_REGION), region_from_dict(BOX_REGION)]
    res = extract_regions(
        lambda region, pick: extract_mesh(density, BOUNDS, resolution=64, region=region, pick=pick), regions
    )
    assert set(np.unique(res.part)) == {0, 1}
    box_part = np.max(np.abs(res.vertices - [0.75, 0.0, -0.7]), axis=1) < 0.2
    assert np.array_equal(box_part, res.part == 1)
    assert res.cut[res.part == 0].any() and not res.cut[res.part == 1].any()  # the box stands free
    cage, cage_part = build_part_cages(res.vertices, res.faces, res.part, lambda V, F, i: build_cage(V, F))
    embedding = embed_points_by_part(res.vertices, res.part, cage.vertices, cage.tets, cage_part)
    assert np.all(cage_part[embedding.corners] == res.part[:, None])  # each object in its own cage
    pins = part_cut_pins(cage.vertices, cage_part, res.vertices, res.part, res.cut, cage.margin)
    assert len(pins) and np.all(cage_part[pins] == 0)
    # A handle on the statue's top: the statue turns, the box (no handle, no pin) stays put.
    top = np.flatnonzero((res.part == 0) & (res.vertices[:, 2] > 0.6))
    turn = np.eye(4)
    turn[:3, :3] = euler_xyz_matrix(0.0, 0.3, 0.0)
    posed, stats = RegionDeformer(cage.vertices, cage.tets, embedding, [top], cage_pins=pins).solve([turn])
    assert stats["converged"]
    assert (
        np.abs(posed[cage_part == 1] - cage.vertices[cage_part == 1]).max() < 1e-12
    )  # no handle, no pin: held at rest
    assert np.linalg.norm(posed[cage_part == 0] - cage.vertices[cage_part == 0], axis=1).max() > 0.1
    # And a handle on the box moves only the box.
    box_handle = np.flatnonzero(res.part == 1)
    lift = np.eye(4)
    lift[2, 3] = 0.2
    posed, _ = RegionDeformer(cage.vertices, cage.tets, embedding, [box_handle], cage_pins=pins).solve([lift])
    assert np.abs(posed[cage_part == 0] - cage.vertices[cage_part == 0]).max() < 1e-9
    assert np.allclose(posed[cage_part == 1][:, 2] - cage.vertices[cage_part == 1][:, 2], 0.2, atol=1e-6)


def test_overlapping_regions_and_a_pick_outside_them_are_refused():
    from blender_nerf_deform.engine.geometry.extract import extract_regions

    one = lambda region, pick: extract_mesh(density, BOUNDS, resolution=32, region=region, pick=pick)  # noqa: E731
    with pytest.raises(EngineError, match="edit regions 1 and 2 overlap"):
        extract_regions(one, [region_from_dict(REGION), region_from_dict(BOX_REGION)])
    with pytest.raises(EngineError, match="lies in none of the 2 edit regions"):
        extract_regions(one, [region_from_dict(STATUE_REGION), region_from_dict(BOX_REGION)], pick=[-1.2, -1.2, 0.0])


def test_cages_of_two_regions_that_meet_are_reported():
    from blender_nerf_deform.engine.geometry.cage import box_cage, overlapping_pieces

    a_v, a_t = box_cage((2, 2, 2), lo=(0.0, 0.0, 0.0), hi=(1.0, 1.0, 1.0))
    b_v, b_t = box_cage((2, 2, 2), lo=(0.8, 0.2, 0.2), hi=(1.8, 0.8, 0.8))  # 0.2 into the first
    V, T = np.concatenate([a_v, b_v]), np.concatenate([a_t, b_t + len(a_v)])
    part = np.r_[np.zeros(len(a_v), int), np.ones(len(b_v), int)]
    lines = overlapping_pieces(V, T, part)
    assert len(lines) == 1 and "edit regions 1 and 2 overlap" in lines[0]
    apart = np.concatenate([a_v, b_v + [0.5, 0.0, 0.0]])
    assert overlapping_pieces(apart, T, part) == []
