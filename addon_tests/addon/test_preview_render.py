"""Background preview: coarse-to-fine frames streamed into "NeRF Preview", without blocking, cancellable."""

import json
import time

import numpy as np
import pytest
from fixtures.blender_objects import engine_render, scene_with_nerf
from PIL import Image


def _pump(job, seconds=120):
    """Run what Blender's timer would run on the main thread until the job stops."""
    deadline = time.monotonic() + seconds
    while job.state == "running" and time.monotonic() < deadline:
        job.client.drain()
        time.sleep(0.02)
    return job.state


def _linear_to_srgb(c):
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.power(np.clip(c, 0, None), 1 / 2.4) - 0.055)


@pytest.mark.slow
def test_preview_streams_coarse_to_fine_and_ends_with_the_full_frame(addon, sphere_nerf, tmp_path):
    bpy = addon
    from blender_nerf_deform.addon.render import preview_render

    ckpt, data = sphere_nerf
    meta = json.loads((data / "transforms.json").read_text())
    frame = meta["frames"][2]
    scene_with_nerf(bpy, ckpt, frame, meta["camera_angle_x"], meta["w"])

    started = time.monotonic()
    assert bpy.ops.nerf_deform.preview_render() == {"FINISHED"}
    assert time.monotonic() - started < 5.0  # returns at once: the work is in the worker
    job = preview_render.current_job()
    assert _pump(job) == "finished", job.error
    assert job.delivered == [(4, 4), (8, 8), (16, 16), (32, 32)]

    (tmp_path / "one.json").write_text(json.dumps({**meta, "frames": [frame]}))
    engine_render(ckpt, tmp_path / "one.json", tmp_path / "cli")
    name = frame["file_path"].rsplit("/", 1)[-1].rsplit(".", 1)[0]
    expected = np.asarray(Image.open(tmp_path / "cli" / f"{name}.png").convert("RGBA"), dtype=np.float64) / 255
    image = bpy.data.images[preview_render.IMAGE_NAME]
    pixels = np.empty(32 * 32 * 4, dtype=np.float32)
    image.pixels.foreach_get(pixels)
    got = pixels.reshape(32, 32, 4)[::-1]  # Blender images are stored bottom row first
    got = np.concatenate([_linear_to_srgb(got[..., :3]), got[..., 3:]], -1)
    visible = expected[..., 3] > 0.03
    assert np.abs(got[..., 3] - expected[..., 3]).max() < 0.01
    assert np.abs(got[..., :3] - expected[..., :3])[visible].max() < 0.01


@pytest.mark.slow
def test_cancelled_preview_stops_and_the_next_one_works(addon, sphere_nerf):
    bpy = addon
    from blender_nerf_deform.addon.render import preview_render

    ckpt, data = sphere_nerf
    meta = json.loads((data / "transforms.json").read_text())
    scene_with_nerf(bpy, ckpt, meta["frames"][1], meta["camera_angle_x"], meta["w"])
    bpy.ops.nerf_deform.preview_render()
    job = preview_render.current_job()
    assert bpy.ops.nerf_deform.cancel_preview() == {"FINISHED"}
    assert _pump(job, 10) == "cancelled"
    assert len(job.delivered) < 4
    assert not bpy.ops.nerf_deform.cancel_preview.poll()

    bpy.ops.nerf_deform.preview_render()
    assert _pump(preview_render.current_job()) == "finished"


def test_preview_without_a_nerf_reports_why(addon):
    bpy = addon
    with pytest.raises(RuntimeError, match="no NeRF object in the scene to preview"):
        bpy.ops.nerf_deform.preview_render()
