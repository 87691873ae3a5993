"""Preview (Train panel): a small frame of the NeRF being trained, asked while the training runs in the
worker, comes back before the training ends (the training answers it between steps); after the
training, the same button renders the run's checkpoint. Real worker, the analytic sphere's dataset."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from fixtures.sphere_data import write_sphere_dataset


def _pixels(image) -> np.ndarray:
    width, height = image.size
    pixels = np.empty(width * height * 4, dtype=np.float32)
    image.pixels.foreach_get(pixels)
    return pixels.reshape(height, width, 4)


def _preview_report(bpy, **kwargs) -> str:
    """Run Preview from Python (blocking); its INFO report, which Blender also prints."""
    from blender_nerf_deform.addon.train import training_preview

    assert bpy.ops.nerf_deform.preview_training(**kwargs) == {"FINISHED"}
    return training_preview._last["message"]


@pytest.mark.slow
def test_a_preview_asked_while_training_comes_back_before_it_ends_then_renders_the_checkpoint(addon, tmp_path):
    bpy = addon
    from blender_nerf_deform.addon.train.training_preview import IMAGE_NAME
    from blender_nerf_deform.addon.worker import jobs

    assert not bpy.ops.nerf_deform.preview_training.poll()  # nothing trains, the panel's run has no checkpoint
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
    try:

        def steps_reported() -> int:
            return max([int(m.split("step ")[1].split(",")[0]) for m in state["progress"]] or [0])

        while steps_reported() < 80 and time.time() < deadline:  # far enough for the sphere to show
            client.drain()
            time.sleep(0.05)
        assert steps_reported() >= 80, f"the training worker reported {state['progress'][-3:]}"
        assert bpy.ops.nerf_deform.preview_training.poll()  # a training runs: the button is enabled

        # No scene camera: a view of the NeRF's box, at the render resolution's aspect (16:9), 64 px wide.
        message = _preview_report(bpy, max_size=64)
        step = int(message.split("step ")[1].split(",")[0])
        assert message.startswith("64x36 preview of training at step") and step > 0, message
        image = bpy.data.images[IMAGE_NAME]
        assert tuple(image.size) == (64, 36)
        box_view = _pixels(image)
        assert box_view[..., 3].std() > 0.1 and box_view[..., :3].std() > 0.02  # the sphere's disc, not a constant

        # The scene camera, looking at the sphere from -Y: the sphere fills the middle, the corners are empty.
        camera = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
        bpy.context.scene.collection.objects.link(camera)
        bpy.context.scene.camera = camera
        camera.location = (0.0, -3.0, 0.0)
        camera.rotation_euler = (math.pi / 2, 0.0, 0.0)
        bpy.context.scene.render.resolution_x = bpy.context.scene.render.resolution_y = 320
        message = _preview_report(bpy, max_size=40)
        assert message.startswith("40x40 preview of training at step"), message
        later = int(message.split("step ")[1].split(",")[0])
        # Not later than the first: the worker answers between steps, and on a loaded machine the second
        # request can arrive before the next step ends (the training still advances: its steps below).
        assert later >= step
        front = _pixels(bpy.data.images[IMAGE_NAME])
        assert front.shape == (40, 40, 4)
        assert front[15:25, 15:25, 3].mean() > 0.5 and front[:4, :4, 3].mean() < 0.2, front[..., 3].round(1)

        # The training was still running all along: it goes on past the previews' steps, and ends only
        # when cancelled.
        while steps_reported() <= later and state["done"] is None and time.time() < deadline:
            client.drain()
            time.sleep(0.05)
        assert state["done"] is None and steps_reported() > later, state["progress"][-3:]
        client.cancel(job)
        while state["done"] is None and time.time() < deadline:
            client.drain()
            time.sleep(0.05)
        result = state["done"]
        assert isinstance(result, dict) and result["cancelled"] and result["steps"] > later, result
    finally:  # a failed assertion must not leave the training running in the module's worker
        if state["done"] is None:
            client.cancel(job)
            while state["done"] is None and time.time() < deadline + 60:
                client.drain()
                time.sleep(0.05)

    # Finished: the panel's run folder holds a checkpoint, and Preview renders it.
    assert not bpy.ops.nerf_deform.preview_training.poll()  # the panel names no run yet
    bpy.context.scene.nerf_deform_training.run_folder = str(run)
    assert bpy.ops.nerf_deform.preview_training.poll()
    message = _preview_report(bpy, max_size=40)
    assert message == f"40x40 preview of the checkpoint {run / 'nerf.ckpt'}", message
    from_checkpoint = _pixels(bpy.data.images[IMAGE_NAME])
    assert from_checkpoint[15:25, 15:25, 3].mean() > 0.5 and from_checkpoint[:4, :4, 3].mean() < 0.2


def test_preview_with_nothing_to_preview_says_why(addon, tmp_path):
    bpy = addon
    bpy.context.scene.nerf_deform_training.data = str(tmp_path / "data")  # its run has no checkpoint
    with pytest.raises(RuntimeError, match="No training runs, and the Train panel's run folder holds no checkpoint"):
        bpy.ops.nerf_deform.preview_training()
