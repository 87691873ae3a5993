"""Train NeRF from Blender: the worker trains (progress, cancel keeps the checkpoint, resume
continues), then the NeRF object appears. Real worker, the analytic sphere's small dataset."""

from __future__ import annotations

import json
import re
import subprocess
import sys
import time

import numpy as np
import pytest
from fixtures import REPO
from fixtures.sphere_data import look_at, write_sphere_dataset
from fixtures.turntable_data import write_turntable
from PIL import Image


def _eval_psnr(ckpt, data) -> float:
    proc = subprocess.run(
        [sys.executable, "-m", "blender_nerf_deform.engine", "eval", "--nerf", str(ckpt), "--data", str(data)],
        cwd=REPO,
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    return float(re.findall(r"([0-9.]+) dB", proc.stdout + proc.stderr)[-1])


def _constant_colour_psnr(data) -> float:
    """PSNR of the best constant image (the mean colour on white) against the dataset's images."""
    meta = json.loads((data / "transforms.json").read_text())
    imgs = []
    for frame in meta["frames"]:
        rgba = np.asarray(Image.open(data / frame["file_path"]).convert("RGBA"), dtype=np.float64) / 255
        imgs.append(rgba[..., :3] * rgba[..., 3:] + (1 - rgba[..., 3:]))
    imgs = np.stack(imgs)
    return float(-10 * np.log10(np.mean((imgs - imgs.mean(axis=(0, 1, 2))) ** 2)))


@pytest.mark.slow
def test_train_nerf_shows_progress_and_ends_with_a_nerf_object(addon, tmp_path, capfd):
    bpy = addon
    data = write_sphere_dataset(tmp_path / "data", n_views=12, size=24)
    assert not [o for o in bpy.data.objects if o.nerf_deform.role == "NERF"]
    assert bpy.ops.nerf_deform.train_nerf(
        data=str(data), run_folder=str(tmp_path / "run"), steps=150, seconds=0, device="cpu"
    ) == {"FINISHED"}
    printed = capfd.readouterr().out
    progress = re.findall(r"Train NeRF: +([0-9.]+)% step (\d+), PSNR", printed)
    assert len(progress) >= 2, printed[-2000:]  # several reports, advancing
    assert float(progress[-1][0]) > float(progress[0][0]) and int(progress[-1][1]) > int(progress[0][1])
    nerfs = [o for o in bpy.data.objects if o.nerf_deform.role == "NERF"]
    assert len(nerfs) == 1
    ckpt = tmp_path / "run" / "nerf.ckpt"
    assert ckpt.is_file() and bpy.path.abspath(nerfs[0].nerf_deform.checkpoint) == str(ckpt)
    # It learnt the sphere: better than the best constant colour.
    assert _eval_psnr(ckpt, data) > _constant_colour_psnr(data) + 3.0
    # Training again into the same folder without Resume is refused; nothing is touched.
    stamp = ckpt.stat().st_mtime_ns
    with pytest.raises(RuntimeError, match="already holds a NeRF: tick Resume"):
        bpy.ops.nerf_deform.train_nerf(data=str(data), run_folder=str(tmp_path / "run"), steps=10, seconds=0)
    assert ckpt.stat().st_mtime_ns == stamp


@pytest.mark.slow
def test_cancel_keeps_a_loadable_checkpoint_and_resume_continues_it(addon, tmp_path):
    bpy = addon
    from blender_nerf_deform.addon.worker import jobs

    data = write_sphere_dataset(tmp_path / "data", n_views=12, size=24)
    run = tmp_path / "run"
    client = jobs.worker(bpy.context)
    state = {"progress": [], "done": None}
    job = client.submit(
        "train",
        {"data": str(data), "out": str(run), "steps": 100000, "device": "cpu"},
        on_progress=lambda f, msg: state["progress"].append(msg),
        on_done=lambda result, arrays: state.update(done=result),
        on_error=lambda error: state.update(done=error),
    )
    deadline = time.time() + 300
    while not state["progress"] and time.time() < deadline:
        client.drain()
        time.sleep(0.05)
    assert state["progress"], "no progress from the training worker"
    client.cancel(job)
    while state["done"] is None and time.time() < deadline:
        client.drain()
        time.sleep(0.05)
    result = state["done"]
    assert isinstance(result, dict) and result["cancelled"], result
    steps_done = result["steps"]
    assert 0 < steps_done < 100000 and (run / "nerf.ckpt").is_file()
    # Loadable, and Resume continues from it: the step count goes on.
    assert bpy.ops.nerf_deform.train_nerf(
        data=str(data), run_folder=str(run), steps=steps_done + 40, seconds=0, resume=True, device="cpu"
    ) == {"FINISHED"}
    summary = json.loads((run / "train.json").read_text())
    assert summary["steps"] == steps_done + 40


def test_train_nerf_bad_input_is_reported(addon, tmp_path):
    bpy = addon
    with pytest.raises(RuntimeError, match="does not exist: pick the folder of a dataset"):
        bpy.ops.nerf_deform.train_nerf(data=str(tmp_path / "nowhere"))
    with pytest.raises(RuntimeError, match="give a time budget or a number of steps"):
        bpy.ops.nerf_deform.train_nerf(data=str(tmp_path), seconds=0, steps=0)
    (tmp_path / "junk").mkdir()
    with pytest.raises(RuntimeError, match="junk"):  # the engine names what it could not read
        bpy.ops.nerf_deform.train_nerf(
            data=str(tmp_path / "junk"), run_folder=str(tmp_path / "run"), steps=5, seconds=0
        )
    assert not (tmp_path / "run").exists()
    assert not [o for o in bpy.data.objects if o.nerf_deform.role == "NERF"]


@pytest.mark.slow
def test_an_object_cut_out_by_its_masks_trains_loads_extracts_and_renders_transparent_around_it(addon, tmp_path, capfd):
    """A turntable capture with object masks, from Blender: Train NeRF reads the masks as the object alone and
    says so, Load NeRF says what it loaded, Extract Mesh needs no edit region (nothing but the object is
    there) and F12 renders the object over transparency."""
    bpy = addon
    data = write_turntable(tmp_path / "turntable", n_views=16)
    assert bpy.ops.nerf_deform.train_nerf(
        data=str(data), run_folder=str(tmp_path / "run"), steps=200, seconds=0, device="cpu"
    ) == {"FINISHED"}
    printed = capfd.readouterr().out
    assert "masks read as the object alone (transparent around it): the masks keep a shape" in printed, printed[-2000:]
    assert "bounded, an object cut out by its masks: transparent around it" in printed, printed[-2000:]
    nerf = bpy.context.active_object
    lo, hi = np.array(nerf.nerf_deform.aabb[:3]), np.array(nerf.nerf_deform.aabb[3:])
    assert (lo <= -0.8).all() and (hi >= 0.8).all() and (hi - lo).max() < 2.4  # the sphere's box, not the cameras'
    nerf.nerf_deform.resolution = 128
    assert bpy.ops.nerf_deform.extract_mesh() == {"FINISHED"}
    verts = np.array([v.co[:] for v in nerf.nerf_deform.surface.data.vertices])
    # On the sphere's shell, and nothing outside it: no fog to cut away (the inside, never seen by a
    # photo, may hold surfaces of its own, and a short training leaves the shell in pieces).
    radius = np.linalg.norm(verts, axis=1)
    assert len(verts) > 100 and np.percentile(radius, 99.9) < 0.95, (len(verts), np.percentile(radius, [50, 99, 99.9]))
    assert np.percentile(radius, 90) > 0.7, np.percentile(radius, [50, 90])
    bpy.context.view_layer.objects.active = nerf
    assert bpy.ops.nerf_deform.build_cage() == {"FINISHED"}  # around the object alone: no region, no cut
    from blender_nerf_deform.addon.data.cage_store import load_cage

    rest, _ = load_cage(nerf.nerf_deform.cage.data)
    assert np.linalg.norm(rest, axis=1).max() < 1.6
    cam_data = bpy.data.cameras.new("Camera")
    camera = bpy.data.objects.new("Camera", cam_data)
    bpy.context.scene.collection.objects.link(camera)
    bpy.context.scene.camera = camera
    from mathutils import Matrix

    camera.matrix_world = Matrix(look_at((2.2, -2.0, 1.0)).tolist())
    scene = bpy.context.scene
    scene.render.resolution_x = scene.render.resolution_y = 40
    scene.render.resolution_percentage = 100
    scene.render.filepath = str(tmp_path / "object.png")
    assert bpy.ops.render.render(write_still=True) == {"FINISHED"}
    alpha = np.asarray(Image.open(tmp_path / "object.png").convert("RGBA"), dtype=np.float64)[..., 3] / 255
    assert alpha[17:23, 17:23].min() > 0.8  # the object in the middle
    border = np.concatenate([alpha[:3].ravel(), alpha[-3:].ravel(), alpha[:, :3].ravel(), alpha[:, -3:].ravel()])
    assert border.max() < 0.1  # and nothing around it: no fog where the masks said empty
