"""Capture Dataset (`nerf_deform.capture_dataset`) against real headless Blender.

The scene: a cube and a UV sphere (selected), and a small decoy cube (not selected) between
some cameras and them; Cycles with few samples as the scene's engine. The operator saves a
copy of the scene and renders it in a separate process (the `bpy` module's Python running
capture_runner.py). The written cameras must reproduce Blender's: the selected objects'
vertices, projected with the written intrinsics and matrices, land on opaque pixels, and the
opaque pixels' extent is the projected vertices' extent.
"""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from blender_nerf_deform.addon.capture.dataset import project

DECOY_LOCATION = (0.0, 0.0, -2.2)


def _world_vertices(obj) -> np.ndarray:
    co = np.empty(3 * len(obj.data.vertices))
    obj.data.vertices.foreach_get("co", co)
    m = np.array(obj.matrix_world)
    return (np.c_[co.reshape(-1, 3), np.ones(len(co) // 3)] @ m.T)[:, :3]


@pytest.fixture
def scene(addon):
    bpy = addon
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    scene.cycles.samples = 4
    bpy.ops.mesh.primitive_cube_add(size=1.0, location=(0.55, -0.1, 0.0), rotation=(0.3, 0.2, 0.5))
    cube = bpy.context.active_object
    bpy.ops.mesh.primitive_uv_sphere_add(radius=0.45, location=(-0.5, 0.3, 0.15), segments=32, ring_count=16)
    sphere = bpy.context.active_object
    bpy.ops.mesh.primitive_cube_add(size=0.3, location=DECOY_LOCATION)
    decoy = bpy.context.active_object
    decoy.name = "Decoy"
    bpy.ops.object.select_all(action="DESELECT")
    cube.select_set(True)
    sphere.select_set(True)
    bpy.context.view_layer.objects.active = sphere
    bpy.context.view_layer.update()
    return bpy, cube, sphere, decoy


def _alpha(path) -> np.ndarray:
    image = Image.open(path)
    assert image.mode == "RGBA"
    return np.asarray(image, dtype=np.float64)[..., 3] / 255.0


def _check_cameras(folder: Path, selected: np.ndarray, decoy: np.ndarray) -> int:
    """Every selected vertex on an opaque pixel (or next to one), the opaque pixels spanning exactly the projected
    vertices, the decoy (hidden: Selected Only) transparent wherever it would be seen; the frames checked."""
    meta = json.loads((folder / "transforms.json").read_text())
    decoy_seen = 0
    for frame in meta["frames"]:
        alpha = _alpha(folder / frame["file_path"])
        assert alpha.shape == (meta["h"], meta["w"])
        intr = (meta["fl_x"], meta["fl_y"], meta["cx"], meta["cy"])
        uv = project(selected, frame["transform_matrix"], *intr)
        assert (uv >= 1).all() and (uv[:, 0] <= meta["w"] - 1).all() and (uv[:, 1] <= meta["h"] - 1).all(), (
            f"{frame['file_path']}: the selection is not inside the picture"
        )
        i, j = np.floor(uv).astype(int).T
        near = np.max(
            [
                alpha[np.clip(j + dj, 0, meta["h"] - 1), np.clip(i + di, 0, meta["w"] - 1)]
                for di in (-1, 0, 1)
                for dj in (-1, 0, 1)
            ],
            axis=0,
        )
        assert (near > 0.5).all(), (
            f"{frame['file_path']}: {(near <= 0.5).sum()} vertices project onto transparent pixels"
        )
        rows, cols = np.nonzero(alpha > 0.5)
        opaque = np.array([[cols.min(), rows.min()], [cols.max() + 1, rows.max() + 1]], dtype=np.float64)
        drawn = np.array([uv.min(0), uv.max(0)])
        assert np.abs(opaque - drawn).max() < 1.5, f"{frame['file_path']}: opaque extent {opaque} vs projected {drawn}"
        # The decoy's corners that fall in the picture, away from the selection's extent (where it would show).
        d = project(decoy, frame["transform_matrix"], *intr)
        inside = (d[:, 0] > 0) & (d[:, 0] < meta["w"]) & (d[:, 1] > 0) & (d[:, 1] < meta["h"])
        apart = ((d < drawn[0] - 1.5) | (d > drawn[1] + 1.5)).any(axis=1)
        if (inside & apart).any():
            decoy_seen += 1
            di, dj = np.floor(d[inside & apart]).astype(int).T
            assert alpha[dj, di].max() == 0.0, f"{frame['file_path']}: the unselected decoy was rendered"
    return decoy_seen


def test_cameras_reproduce_blenders_and_fit_the_selection(scene, tmp_path, capfd):
    bpy, cube, sphere, decoy = scene
    out = tmp_path / "data"
    result = bpy.ops.nerf_deform.capture_dataset(output=str(out), count=10, test_count=2, resolution=(48, 40), seed=2)
    assert result == {"FINISHED"}
    printed = capfd.readouterr().out
    assert "Capture Dataset: 12/12 views" in printed  # progress, one line per view
    selected = np.concatenate([_world_vertices(cube), _world_vertices(sphere)])
    corners = _world_vertices(decoy)
    seen = _check_cameras(out, selected, corners) + _check_cameras(out / "test", selected, corners)
    assert seen >= 2, "the decoy is in no view: the test does not test Selected Only"

    meta = json.loads((out / "transforms.json").read_text())
    assert (meta["w"], meta["h"], len(meta["frames"])) == (48, 40, 10)
    assert len(json.loads((out / "test" / "transforms.json").read_text())["frames"]) == 2
    gen = meta["generator"]
    # The scene's engine and its samples (Engine: Scene's Engine), not the tool's 16.
    assert (gen["engine"], gen["engine_option"], gen["samples"]) == ("CYCLES", "KEEP", 4)
    assert sorted(gen["selection"]) == sorted([cube.name, sphere.name])
    # Target: the centre of the selection's box; the box written as aabb holds it with a small margin, not the decoy.
    lo, hi = selected.min(0), selected.max(0)
    target = np.array(gen["target"])
    assert np.allclose(target, 0.5 * (lo + hi), atol=1e-5)
    a_lo, a_hi = np.array(meta["aabb"])
    margin = 0.1 * (hi - lo).max()
    assert (a_lo < lo).all() and (a_hi > hi).all() and (a_lo > lo - margin).all() and (a_hi < hi + margin).all()
    assert not ((corners > a_lo) & (corners < a_hi)).all(axis=1).any()
    # Cameras on the automatic radius around the target, looking at it, outside the selection's sphere.
    radius = gen["radius"]
    assert radius > 0.5 * np.linalg.norm(hi - lo)
    for frame in meta["frames"]:
        m = np.array(frame["transform_matrix"])
        assert np.linalg.norm(m[:3, 3] - target) == pytest.approx(radius, rel=1e-5)
        assert np.allclose(-m[:3, 2], (target - m[:3, 3]) / radius, atol=1e-5)
    # Train NeRF is the next click; the open scene is untouched (no camera added, engine and selection kept).
    assert bpy.path.abspath(bpy.context.scene.nerf_deform_training.data) == str(out)
    assert decoy.hide_render is False and bpy.context.scene.camera is None
    assert {o.name for o in bpy.context.selected_objects} == {cube.name, sphere.name}
    assert not [p.name for p in tmp_path.iterdir() if p.name != "data"], "staging folders left behind"


def test_radius_hemisphere_and_cycles_option(scene, tmp_path):
    bpy, *_ = scene
    out = tmp_path / "data"
    assert bpy.ops.nerf_deform.capture_dataset(
        output=str(out), count=4, resolution=(24, 24), radius=6.0, hemisphere=True, engine="CYCLES", samples=2
    ) == {"FINISHED"}
    meta = json.loads((out / "transforms.json").read_text())
    gen = meta["generator"]
    assert (gen["engine"], gen["engine_option"], gen["samples"], gen["device"]) == ("CYCLES", "CYCLES", 2, "CPU")
    target = np.array(gen["target"])
    for frame in meta["frames"]:
        centre = np.array(frame["transform_matrix"])[:3, 3]
        assert np.linalg.norm(centre - target) == pytest.approx(6.0) and centre[2] >= target[2]
    assert bpy.context.scene.cycles.samples == 4  # the open scene's settings are not touched


def test_opaque_capture_keeps_the_background(scene, tmp_path):
    bpy, *_ = scene
    world = bpy.data.worlds.new("grey")
    if world.node_tree is None:
        world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (0.5, 0.5, 0.5, 1.0)
    bpy.context.scene.world = world
    out = tmp_path / "data"
    assert bpy.ops.nerf_deform.capture_dataset(output=str(out), count=2, resolution=(16, 16), transparent=False) == {
        "FINISHED"
    }
    meta = json.loads((out / "transforms.json").read_text())
    image = Image.open(out / meta["frames"][0]["file_path"])
    assert image.mode == "RGB" and np.asarray(image)[0, 0].min() > 100  # the grey world, opaque


def test_saved_file_relative_paths_and_default_folder(scene, tmp_path):
    """A saved .blend with a texture by a // path: the copy the renderer opens still finds it; the dataset
    goes to //nerf_datasets/<scene name>, which the Dataset field then shows."""
    bpy, cube, sphere, _ = scene
    project_dir = tmp_path / "project"
    project_dir.mkdir()
    texture = bpy.data.images.new("red", 4, 4)
    texture.pixels = [1.0, 0.0, 0.0, 1.0] * 16
    texture.filepath_raw = str(project_dir / "red.png")
    texture.file_format = "PNG"
    texture.save()
    mat = bpy.data.materials.new("textured")
    if mat.node_tree is None:
        mat.use_nodes = True
    nodes, links = mat.node_tree.nodes, mat.node_tree.links
    nodes.clear()
    tex = nodes.new("ShaderNodeTexImage")
    tex.image = texture
    emission = nodes.new("ShaderNodeEmission")
    output = nodes.new("ShaderNodeOutputMaterial")
    links.new(tex.outputs["Color"], emission.inputs["Color"])
    links.new(emission.outputs["Emission"], output.inputs["Surface"])
    for obj in (cube, sphere):
        obj.data.materials.append(mat)
    bpy.ops.wm.save_as_mainfile(filepath=str(project_dir / "scene.blend"))
    texture.filepath = "//red.png"
    texture.reload()
    bpy.context.scene.name = "My Scene"

    assert bpy.ops.nerf_deform.capture_dataset(count=2, resolution=(24, 24)) == {"FINISHED"}
    out = project_dir / "nerf_datasets" / "My Scene"
    meta = json.loads((out / "transforms.json").read_text())
    rgba = np.asarray(Image.open(out / meta["frames"][0]["file_path"]), dtype=np.float64)
    surface = rgba[..., 3] == 255
    assert surface.any()
    red, green, blue = (rgba[..., c][surface].mean() for c in range(3))
    assert red > 200 and green < 30 and blue < 30, "the texture was not found (Blender's magenta) or is wrong"
    assert bpy.context.scene.nerf_deform_training.data == str(out)
    assert texture.filepath == "//red.png" and bpy.data.filepath == str(project_dir / "scene.blend")
    assert sorted(p.name for p in project_dir.iterdir()) == ["nerf_datasets", "red.png", "scene.blend"]


# --------------------------------------------------------------------------- background, cancel, failure


def _old_dataset(folder: Path) -> dict:
    (folder / "images").mkdir(parents=True)
    (folder / "transforms.json").write_text('{"frames": [], "old": true}\n')
    (folder / "images" / "r_0.png").write_bytes(b"not really a png, but the user's")
    return _snapshot(folder)


def _snapshot(folder: Path) -> dict:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _running_job(bpy, out: Path, count: int, at_least: int = 2):
    from blender_nerf_deform.addon.capture import operators as capture_ops

    settings = bpy.context.scene.nerf_deform_capture
    settings.output, settings.count, settings.resolution = str(out), count, (48, 48)
    job = capture_ops.start_capture(bpy.context, settings)
    deadline = time.monotonic() + 120
    while not job.poll() and job.done < at_least and time.monotonic() < deadline:
        time.sleep(0.02)
    assert job.state == "running" and job.done >= at_least, (job.state, job.done, job.error)
    assert any(p.name.startswith(".data.capturing-") for p in out.parent.iterdir())  # rendering into the staging folder
    return job


def test_cancel_midway_leaves_the_existing_dataset_as_it_was(scene, tmp_path):
    bpy, *_ = scene
    out = tmp_path / "data"
    before = _old_dataset(out)
    job = _running_job(bpy, out, count=300)
    job.cancel()
    assert job.state == "cancelled" and job._proc.poll() is not None  # the renderer is gone
    assert job.poll() is True and job.state == "cancelled"
    assert _snapshot(out) == before
    assert [p.name for p in tmp_path.iterdir()] == ["data"]  # no staging folder left
    assert not os.path.exists(job.workdir)
    assert bpy.context.scene.nerf_deform_training.data == ""


def test_a_second_capture_into_the_same_folder_is_refused_while_one_runs(scene, tmp_path):
    bpy, *_ = scene
    from blender_nerf_deform.addon.capture import operators as capture_ops

    out = tmp_path / "data"
    before = _old_dataset(out)
    job = _running_job(bpy, out, count=300)
    assert capture_ops._live == {job}
    with pytest.raises(RuntimeError, match=rf"a capture into {out} is already running: wait for it or cancel it"):
        bpy.ops.nerf_deform.capture_dataset(output=str(out), count=1)
    job.cancel()
    assert not capture_ops._live and _snapshot(out) == before


def test_opening_another_file_cancels_the_capture(scene, tmp_path):
    bpy, *_ = scene
    other = tmp_path / "other.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(other), copy=True)
    out = tmp_path / "data"
    before = _old_dataset(out)
    job = _running_job(bpy, out, count=300)
    bpy.ops.wm.open_mainfile(filepath=str(other))
    assert job.state == "cancelled" and job._proc.poll() is not None
    assert _snapshot(out) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data", "other.blend"]


def test_a_renderer_that_dies_is_a_failure_that_changes_nothing(scene, tmp_path):
    bpy, *_ = scene
    out = tmp_path / "data"
    before = _old_dataset(out)
    job = _running_job(bpy, out, count=300)
    os.kill(job._proc.pid, signal.SIGKILL)
    assert job.wait(timeout=60) == "failed"
    assert "exit status" in job.error and "\n" not in job.error
    assert _snapshot(out) == before
    assert [p.name for p in tmp_path.iterdir()] == ["data"]


def test_background_run_to_the_end_replaces_the_old_dataset(scene, tmp_path):
    bpy, *_ = scene
    from blender_nerf_deform.addon.capture import operators as capture_ops

    out = tmp_path / "data"
    _old_dataset(out)
    # What a Blender that died while capturing left (its pid is gone), and a live Blender's capture.
    dead, live = tmp_path / ".data.capturing-4194999-x1", tmp_path / ".data.capturing-1-x2"
    for folder in (dead, live):
        (folder / "images").mkdir(parents=True)
    job = _running_job(bpy, out, count=4, at_least=1)
    assert not dead.exists() and live.is_dir()
    live.joinpath("images").rmdir()
    live.rmdir()
    assert job.wait(timeout=120) == "done", job.error
    assert 0 < job.fraction <= 1 and job.done == 4
    assert "4 views" in capture_ops.finish(job)
    meta = json.loads((out / "transforms.json").read_text())
    assert "old" not in meta and len(meta["frames"]) == 4
    assert sorted(p.name for p in (out / "images").iterdir()) == [f"r_{k}.png" for k in range(4)]
    assert [p.name for p in tmp_path.iterdir()] == ["data"]  # the old one removed, no staging left
    assert bpy.path.abspath(bpy.context.scene.nerf_deform_training.data) == str(out)


def test_api_captures_the_given_objects(scene, tmp_path):
    bpy, cube, sphere, decoy = scene
    from blender_nerf_deform.addon import api

    folder = api.capture_dataset(tmp_path / "cube", objects=[cube], count=3, resolution=(24, 24), min_elevation=10.0)
    assert folder == str(tmp_path / "cube")
    meta = json.loads((Path(folder) / "transforms.json").read_text())
    assert meta["generator"]["selection"] == [cube.name] and meta["generator"]["min_elevation"] == 10.0
    assert np.allclose(meta["generator"]["target"], _world_vertices(cube).mean(0), atol=1e-5)


# --------------------------------------------------------------------------- bad input


def test_no_selection_is_refused_with_a_clear_message(scene, tmp_path):
    bpy, *_ = scene
    bpy.ops.object.select_all(action="DESELECT")
    with pytest.raises(RuntimeError, match=r"Capture Dataset: no objects selected: select the objects to capture") as e:
        bpy.ops.nerf_deform.capture_dataset(output=str(tmp_path / "data"))
    assert "Traceback" not in str(e.value)
    bpy.ops.object.light_add(type="POINT")  # selected, but nothing that renders
    with pytest.raises(RuntimeError, match=r"none of the selected objects renders \(selected: light\)"):
        bpy.ops.nerf_deform.capture_dataset(output=str(tmp_path / "data"))
    assert list(tmp_path.iterdir()) == []


def _read_only_folder(tmp_path: Path) -> Path:
    """A folder this process cannot write in: a chmod'ed one, or /sys where permissions do not bind (root)."""
    folder = tmp_path / "locked"
    folder.mkdir()
    folder.chmod(0o555)
    try:
        (folder / "probe").mkdir()
    except OSError:
        return folder
    (folder / "probe").rmdir()
    return Path("/sys")


def test_read_only_output_folder_is_refused_with_a_clear_message(scene, tmp_path):
    bpy, *_ = scene
    parent = _read_only_folder(tmp_path)
    try:
        with pytest.raises(
            RuntimeError,
            match=rf"Capture Dataset: cannot write in {parent} \(.+\): pick an output "
            rf"folder you can write to",
        ):
            bpy.ops.nerf_deform.capture_dataset(output=str(parent / "data_never_made"))
    finally:
        (tmp_path / "locked").chmod(0o755)
    assert not (parent / "data_never_made").exists()


def test_outputs_that_would_lose_the_users_files_are_refused(scene, tmp_path):
    bpy, *_ = scene
    a_file = tmp_path / "notes.txt"
    a_file.write_text("mine\n")
    with pytest.raises(RuntimeError, match=rf"output {a_file} exists and is not a folder"):
        bpy.ops.nerf_deform.capture_dataset(output=str(a_file))
    home = tmp_path / "home"
    home.mkdir()
    (home / "thesis.tex").write_text("years of work\n")
    with pytest.raises(RuntimeError, match=r"holds other files than a dataset \(thesis.tex\): pick an empty"):
        bpy.ops.nerf_deform.capture_dataset(output=str(home))
    assert a_file.read_text() == "mine\n" and [p.name for p in home.iterdir()] == ["thesis.tex"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["home", "notes.txt"]


def test_an_add_on_engine_is_refused_when_keeping_the_scenes_engine(scene, tmp_path):
    bpy, *_ = scene
    bpy.context.scene.render.engine = "NERF_DEFORM"
    with pytest.raises(RuntimeError, match=r"render engine 'NERF_DEFORM' comes from an add-on.*set Engine to Cycles"):
        bpy.ops.nerf_deform.capture_dataset(output=str(tmp_path / "data"))
    assert bpy.ops.nerf_deform.capture_dataset(
        output=str(tmp_path / "data"), engine="CYCLES", samples=1, count=1, resolution=(16, 16)
    ) == {"FINISHED"}
