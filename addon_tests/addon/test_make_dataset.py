"""tools/make_dataset.py and tools/default_scene.py against real headless Blender.

The projection tests need no NeRF: a small bright marker sits at a known 3D
point, Blender renders it through the tool, and the point projected with the
intrinsics and camera-to-world matrices the tool wrote must land where
Blender drew the marker (its alpha-weighted centroid).
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from fixtures.scenes import PROCEDURAL_RESOLUTION, PROCEDURAL_TEST_VIEWS, PROCEDURAL_VIEWS, run_tool
from PIL import Image

MARKER = (0.45, -0.3, 0.35)  # off the optical axis of every camera (they look at the origin)
MARKER_RADIUS = 0.07


def _emission_material(bpy, colour):
    mat = bpy.data.materials.new("marker")
    if mat.node_tree is None:  # Blender < 5.0
        mat.use_nodes = True
    nodes = mat.node_tree.nodes
    nodes.clear()
    emission = nodes.new("ShaderNodeEmission")
    emission.inputs["Color"].default_value = (*colour, 1.0)
    emission.inputs["Strength"].default_value = 1.0
    output = nodes.new("ShaderNodeOutputMaterial")
    mat.node_tree.links.new(emission.outputs["Emission"], output.inputs["Surface"])
    return mat


def _marker_scene(bpy):
    """Only a small white emissive sphere at MARKER, on a black zero-strength world."""
    bpy.ops.mesh.primitive_uv_sphere_add(radius=MARKER_RADIUS, location=MARKER, segments=32, ring_count=16)
    sphere = bpy.context.active_object
    sphere.data.materials.append(_emission_material(bpy, (1.0, 1.0, 1.0)))
    world = bpy.data.worlds.new("black")
    if world.node_tree is None:
        world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Strength"].default_value = 0.0
    bpy.context.scene.world = world
    return sphere


def _project(frame, meta):
    """MARKER in continuous pixel coordinates (x right, y down; pixel i spans [i, i+1)), by
    docs/ARCHITECTURE.md's convention."""
    c2w = np.array(frame["transform_matrix"], dtype=np.float64)
    x, y, z = (np.linalg.inv(c2w) @ np.array([*MARKER, 1.0]))[:3]
    # The ray of pixel (i, j) is ((i + 0.5 - cx) / fl_x, -(j + 0.5 - cy) / fl_y, -1):
    # the point is on the ray of the continuous position (u, v) = (i + 0.5, j + 0.5).
    return meta["cx"] + meta["fl_x"] * x / -z, meta["cy"] - meta["fl_y"] * y / -z


def _centroid(path):
    alpha = np.asarray(Image.open(path), dtype=np.float64)[..., 3]
    assert alpha.sum() > 0, f"{path}: the marker is not in the picture"
    rows, cols = np.indices(alpha.shape)
    return (alpha * (cols + 0.5)).sum() / alpha.sum(), (alpha * (rows + 0.5)).sum() / alpha.sum()


def _check_marker(out, meta_check=None, tolerance=0.15):
    meta = json.loads((out / "transforms.json").read_text())
    if meta_check:
        meta_check(meta)
    errors = []
    for frame in meta["frames"]:
        image = Image.open(out / frame["file_path"])
        assert image.size == (meta["w"], meta["h"])
        u, v = _project(frame, meta)
        assert 2 <= u <= meta["w"] - 2 and 2 <= v <= meta["h"] - 2, "marker too close to the border to measure"
        cu, cv = _centroid(out / frame["file_path"])
        errors.append(math.hypot(cu - u, cv - v))
    assert max(errors) < tolerance, f"projected marker vs rendered centroid, pixels: {np.round(errors, 3)}"
    return meta, errors


CAMERA_CASES = {
    # name: (tool options, check on the written intrinsics)
    "landscape": (dict(resolution=(64, 48)), None),
    "portrait_auto_fit": (dict(resolution=(40, 60), target=(0.2, -0.1, 0.15), layout="random"), None),
    "vertical_fit_shift": (
        dict(resolution=(64, 40), sensor_fit="VERTICAL", sensor_height=20.0, shift=(0.07, -0.05)),
        None,
    ),
    "pixel_aspect": (dict(resolution=(48, 48), pixel_aspect=1.5, lens=40.0, shift=(-0.04, 0.03)), None),
}


@pytest.mark.parametrize("case", sorted(CAMERA_CASES))
def test_written_cameras_project_the_marker_where_blender_drew_it(blender, tmp_path, case):
    options, _ = CAMERA_CASES[case]
    from tools.make_dataset import make_dataset

    _marker_scene(blender)
    make_dataset(tmp_path, blend=None, progress=None, count=6, radius=4.0, samples=64, seed=3, threads=2, **options)
    meta, errors = _check_marker(tmp_path)
    assert len(meta["frames"]) == 6


def test_renders_the_requested_frame_and_restores_the_current_one(blender, tmp_path):
    from tools.make_dataset import make_dataset

    sphere = _marker_scene(blender)
    scene = blender.context.scene
    for frame, location in ((1, (-0.5, 0.5, -0.4)), (5, MARKER)):
        sphere.location = location
        sphere.keyframe_insert("location", frame=frame)
    scene.frame_set(1)
    make_dataset(tmp_path, blend=None, progress=None, count=3, resolution=(48, 40), samples=64, frame=5, threads=2)
    _check_marker(tmp_path)  # the marker is where frame 5 puts it
    assert scene.frame_current == 1 and tuple(sphere.location) == pytest.approx((-0.5, 0.5, -0.4))


def test_camera_angle_x_alone_gives_the_same_rays(blender, tmp_path):
    """A NeRF-synthetic reader that knows only camera_angle_x (no shift, square pixels) sees the same pixels."""
    from tools.make_dataset import make_dataset

    _marker_scene(blender)
    make_dataset(
        tmp_path,
        blend=None,
        progress=None,
        count=4,
        radius=3.5,
        resolution=(56, 42),
        samples=64,
        seed=11,
        hemisphere=True,
        threads=2,
    )
    meta = json.loads((tmp_path / "transforms.json").read_text())
    focal = 0.5 * meta["w"] / math.tan(0.5 * meta["camera_angle_x"])
    assert meta["fl_x"] == pytest.approx(focal) and meta["fl_y"] == pytest.approx(focal)
    assert (meta["cx"], meta["cy"]) == (meta["w"] / 2, meta["h"] / 2)
    nerf_synthetic = {"fl_x": focal, "fl_y": focal, "cx": meta["w"] / 2, "cy": meta["h"] / 2}
    for frame in meta["frames"]:
        u, v = _project(frame, nerf_synthetic)
        cu, cv = _centroid(tmp_path / frame["file_path"])
        assert math.hypot(cu - u, cv - v) < 0.15


def test_in_process_run_leaves_the_loaded_scene_as_it_was(blender, tmp_path):
    from tools.make_dataset import CAMERA_NAME, make_dataset

    _marker_scene(blender)
    scene = blender.context.scene
    scene.render.engine = "BLENDER_WORKBENCH"
    scene.render.resolution_x, scene.render.resolution_y = 320, 240
    scene.render.film_transparent = False
    before = (
        {ob.name for ob in blender.data.objects},
        len(blender.data.cameras),
        scene.camera,
        scene.view_settings.view_transform,
    )
    make_dataset(tmp_path, blend=None, progress=None, count=1, resolution=16, samples=1, threads=2)
    after = (
        {ob.name for ob in blender.data.objects},
        len(blender.data.cameras),
        scene.camera,
        scene.view_settings.view_transform,
    )
    assert after == before and CAMERA_NAME not in blender.data.objects
    assert scene.render.engine == "BLENDER_WORKBENCH"
    assert (scene.render.resolution_x, scene.render.resolution_y, scene.render.film_transparent) == (320, 240, False)


def test_straight_alpha_on_a_transparent_film(blender, tmp_path):
    """Edge pixels of a white emitter keep white colour with partial alpha (premultiplied would darken them)."""
    from tools.make_dataset import make_dataset

    _marker_scene(blender)
    make_dataset(tmp_path, blend=None, progress=None, count=2, resolution=(48, 36), samples=32, threads=2)
    meta = json.loads((tmp_path / "transforms.json").read_text())
    for frame in meta["frames"]:
        image = Image.open(tmp_path / frame["file_path"])
        assert image.mode == "RGBA"
        rgba = np.asarray(image)
        alpha = rgba[..., 3]
        assert alpha.max() == 255 and (alpha == 0).mean() > 0.9  # transparent background
        edge = (alpha > 20) & (alpha < 235)
        assert edge.any(), "no partially covered pixel at the marker's rim"
        assert rgba[..., :3][edge].min() >= 250, "rim pixels are darkened: alpha is premultiplied"


# --------------------------------------------------------------------------- the default scene's dataset


def test_procedural_dataset_files_and_keys(procedural_dataset):
    for split, views in (("", PROCEDURAL_VIEWS), ("test", PROCEDURAL_TEST_VIEWS)):
        folder = procedural_dataset / split
        meta = json.loads((folder / "transforms.json").read_text())
        for key in ("camera_angle_x", "w", "h", "fl_x", "fl_y", "cx", "cy", "frames"):
            assert key in meta, f"{split or 'train'}: transforms.json lacks {key}"
        assert (meta["w"], meta["h"]) == (PROCEDURAL_RESOLUTION, PROCEDURAL_RESOLUTION)
        assert meta["camera_angle_x"] == pytest.approx(2 * math.atan(18 / 50))  # 50 mm lens, 36 mm sensor
        assert len(meta["frames"]) == views
        assert not [p.name for p in folder.rglob("*") if p.name.startswith(".")], "temporary files left behind"
        centres = []
        for frame in meta["frames"]:
            assert not frame["file_path"].startswith("/") and frame["file_path"].endswith(".png")
            image = Image.open(folder / frame["file_path"])
            assert image.mode == "RGBA" and image.size == (meta["w"], meta["h"])
            alpha = np.asarray(image)[..., 3]
            # The cameras look at the origin, which is inside the arm: the centre is opaque object.
            c = PROCEDURAL_RESOLUTION // 2
            assert alpha[c - 1 : c + 1, c - 1 : c + 1].min() == 255
            assert alpha[0, 0] == 0 and (alpha == 0).mean() > 0.3  # transparent background
            assert ((alpha == 0) | (alpha == 255)).mean() > 0.85  # hard coverage except at silhouettes
            m = np.array(frame["transform_matrix"])
            assert m.shape == (4, 4) and np.allclose(m[3], [0, 0, 0, 1])
            rotation = m[:3, :3]
            assert np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-5) and np.linalg.det(rotation) > 0
            assert np.linalg.norm(m[:3, 3]) == pytest.approx(4.0, abs=1e-4)
            # Looking at the origin: the camera's -Z axis points from its centre to the target.
            assert np.allclose(-rotation[:, 2], -m[:3, 3] / np.linalg.norm(m[:3, 3]), atol=1e-5)
            centres.append(m[:3, 3])
        if not split:  # whole sphere, spread out: views above and below
            z = np.array(centres)[:, 2]
            assert z.max() > 3 and z.min() < -3


def test_default_scene_documents_its_deformable_part(procedural_dataset):
    """REGIONS lie in the scene box, and a point inside the documented tip (the flag) renders as object."""
    from tools.default_scene import REGIONS, SCENE_BOUNDS

    (lo, hi) = np.array(SCENE_BOUNDS)
    assert (lo >= -1.5).all() and (hi <= 1.5).all()
    for region in REGIONS.values():
        rlo, rhi = np.array(region["bounds"])
        assert (rlo >= lo).all() and (rhi <= hi).all() and (rlo < rhi).all()
    meta = json.loads((procedural_dataset / "transforms.json").read_text())
    # A point inside the flag, part of the tip: wherever it falls in the picture, the pixel is opaque.
    tip_lo, tip_hi = np.array(REGIONS["arm_tip"]["bounds"])
    point = np.array([0.8, 0.0, 0.75])
    assert (tip_lo <= point).all() and (point <= tip_hi).all()
    covered = 0
    for frame in meta["frames"]:
        c2w = np.array(frame["transform_matrix"])
        x, y, z = (np.linalg.inv(c2w) @ np.r_[point, 1.0])[:3]
        u, v = meta["cx"] + meta["fl_x"] * x / -z, meta["cy"] - meta["fl_y"] * y / -z
        rgba = np.asarray(Image.open(procedural_dataset / frame["file_path"]))
        i, j = int(u), int(v)
        if 0 <= i < meta["w"] and 0 <= j < meta["h"]:
            covered += rgba[j, i, 3] == 255
    assert covered >= 0.6 * len(meta["frames"])


def test_default_scene_blend_contents(blender, default_scene_blend):
    from tools.default_scene import REGIONS, check

    blender.ops.wm.open_mainfile(filepath=str(default_scene_blend), load_ui=False)
    names = {ob.name for ob in blender.data.objects}
    assert {"Base", "Arm", "Flag", "Camera"} <= names
    arm = blender.data.objects["Arm"]
    assert {"root", "tip"} <= {g.name for g in arm.vertex_groups}
    check(blender)  # each object fills exactly its documented box
    assert json.loads(blender.context.scene["nerf_deform_regions"]) == json.loads(json.dumps(REGIONS))


# --------------------------------------------------------------------------- bad input


def _error_line(result):
    assert result.returncode != 0
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert lines and lines[-1].startswith("error: "), result.stderr
    return lines[-1]


def test_missing_blend_is_named(tmp_path):
    missing = tmp_path / "nope.blend"
    line = _error_line(run_tool("make_dataset.py", "--blend", missing, "--out", tmp_path / "out", check=False))
    assert str(missing) in line and "no such file" in line
    assert not (tmp_path / "out").exists()


def test_a_file_that_is_not_a_blend_is_named(tmp_path):
    fake = tmp_path / "fake.blend"
    fake.write_text("not a blend file\n")
    line = _error_line(run_tool("make_dataset.py", "--blend", fake, "--out", tmp_path / "out", check=False))
    assert str(fake) in line and "not a .blend" in line


def test_a_scene_without_objects_is_refused(tmp_path):
    import subprocess
    import sys

    empty = tmp_path / "empty.blend"
    subprocess.run(
        [
            sys.executable,
            "-c",
            "import bpy; bpy.ops.wm.read_factory_settings(use_empty=True); "
            f"bpy.ops.wm.save_as_mainfile(filepath={str(empty)!r})",
        ],
        check=True,
        capture_output=True,
    )
    result = run_tool("make_dataset.py", "--blend", empty, "--out", tmp_path / "out", "--count", 2, check=False)
    line = _error_line(result)
    assert "no objects to render" in line and str(empty) in line
    assert not (tmp_path / "out" / "transforms.json").exists()


@pytest.mark.parametrize(
    "args, fault",
    [
        (["--count", "0"], "--count"),
        (["--count", "-3"], "--count"),
        (["--resolution", "0", "32"], "--resolution"),
        (["--resolution", "32", "32", "32"], "--resolution"),
        (["--radius", "0"], "--radius"),
        (["--samples", "0"], "--samples"),
        (["--test-count", "-1"], "--test-count"),
    ],
)
def test_bad_numbers_are_named(default_scene_blend, tmp_path, args, fault):
    result = run_tool("make_dataset.py", "--blend", default_scene_blend, "--out", tmp_path / "out", *args, check=False)
    line = _error_line(result)
    assert fault in line
    assert not (tmp_path / "out").exists()


def test_function_raises_dataset_error(tmp_path):
    from tools.make_dataset import DatasetError, make_dataset

    with pytest.raises(DatasetError, match="--count"):
        make_dataset(tmp_path / "out", blend=tmp_path / "x.blend", count=0)
    with pytest.raises(DatasetError, match="no such file"):
        make_dataset(tmp_path / "out", blend=tmp_path / "x.blend", count=1)
    with pytest.raises(TypeError, match="bogus"):
        make_dataset(tmp_path / "out", blend=None, bogus=1)


def test_same_seed_same_cameras_other_seed_other_cameras():
    from tools.make_dataset import camera_positions

    a = camera_positions(24, 4.0, (0.1, 0.2, 0.3), hemisphere=True, seed=5)
    assert np.array_equal(a, camera_positions(24, 4.0, (0.1, 0.2, 0.3), hemisphere=True, seed=5))
    assert not np.allclose(a, camera_positions(24, 4.0, (0.1, 0.2, 0.3), hemisphere=True, seed=6))
    assert np.allclose(np.linalg.norm(a - [0.1, 0.2, 0.3], axis=1), 4.0)
    assert (a[:, 2] >= 0.3).all()
    r = camera_positions(200, 2.0, seed=1, layout="random")
    assert np.allclose(np.linalg.norm(r, axis=1), 2.0) and r[:, 2].min() < -1 and r[:, 2].max() > 1


def test_factory_caches_and_honours_its_arguments(make_procedural_dataset, procedural_dataset):
    assert make_procedural_dataset() == procedural_dataset
    small = make_procedural_dataset(count=3, resolution=20, test_count=0, samples=2, hemisphere=True, seed=4)
    assert make_procedural_dataset(count=3, resolution=20, test_count=0, samples=2, hemisphere=True, seed=4) == small
    meta = json.loads((small / "transforms.json").read_text())
    assert (meta["w"], meta["h"], len(meta["frames"])) == (20, 20, 3)
    assert not (small / "test").exists()
    assert all(np.array(f["transform_matrix"])[2, 3] > 0 for f in meta["frames"])  # upper hemisphere


def test_out_must_be_a_folder(default_scene_blend, tmp_path):
    a_file = tmp_path / "taken"
    a_file.write_text("mine\n")
    line = _error_line(run_tool("make_dataset.py", "--blend", default_scene_blend, "--out", a_file, check=False))
    assert str(a_file) in line and "not a folder" in line
    assert a_file.read_text() == "mine\n"


def test_rerun_replaces_the_dataset(blender, tmp_path):
    from tools.make_dataset import make_dataset

    _marker_scene(blender)
    make_dataset(tmp_path, blend=None, progress=None, count=3, resolution=16, samples=1, test_count=2, threads=2)
    make_dataset(tmp_path, blend=None, progress=None, count=2, resolution=20, samples=1, threads=2)
    meta = json.loads((tmp_path / "transforms.json").read_text())
    assert (meta["w"], len(meta["frames"])) == (20, 2)
    assert all(Image.open(tmp_path / f["file_path"]).size == (20, 20) for f in meta["frames"])
    assert not (tmp_path / "test" / "transforms.json").exists()  # no stale split describing old views
