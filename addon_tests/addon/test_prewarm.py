"""Start Worker on Open (addon/render/prewarm.py): opening a file with NeRFs in Blender's UI starts the
worker on a thread and loads the file's NeRFs into it, so the first F12 renders on that worker without
waiting for its start; in background mode (`blender -b`, these tests) opening a file starts nothing."""

import json
import os
import threading

import numpy as np
from fixtures.blender_objects import scene_with_nerf
from PIL import Image


def test_opening_a_file_in_background_starts_nothing_and_prewarm_readies_the_worker_for_f12(
    addon, sphere_nerf, tmp_path
):
    bpy = addon
    from blender_nerf_deform.addon.render import prewarm
    from blender_nerf_deform.addon.worker import jobs

    ckpt, data = sphere_nerf
    meta = json.loads((data / "transforms.json").read_text())
    nerf, _ = scene_with_nerf(bpy, ckpt, meta["frames"][3], meta["camera_angle_x"], meta["w"])
    twin = nerf.copy()  # a second NeRF object on the same checkpoint: loaded once
    bpy.context.scene.collection.objects.link(twin)
    gone = nerf.copy()  # and one whose checkpoint file is not there: left to its render to report
    gone.nerf_deform.checkpoint = str(tmp_path / "moved_away.ckpt")
    bpy.context.scene.collection.objects.link(gone)
    gone.hide_render = True
    blend = tmp_path / "scene.blend"
    assert bpy.ops.wm.save_as_mainfile(filepath=str(blend)) == {"FINISHED"}

    client = jobs.worker(bpy.context)
    client.stop()
    assert bpy.ops.wm.open_mainfile(filepath=str(blend)) == {"FINISHED"}
    # The handler ran and left it: no start thread (it would live for the worker's start), no worker.
    assert "nerf-worker-prewarm" not in [t.name for t in threading.enumerate()]
    assert not client.running and "warm" not in [op for op, _ in client.sent]

    checkpoints = prewarm.file_nerfs()
    assert checkpoints == [os.path.normpath(str(ckpt))]
    thread = prewarm.start(client, checkpoints)
    assert thread.is_alive()  # back at once: the worker's start (a torch import) runs on the thread
    thread.join(timeout=300)
    assert not thread.is_alive() and client.running and client.sent[-1][0] == "warm"
    pid = client.call("info")[0]["pid"]  # answered after warm's: the worker serves in order

    bpy.context.scene.render.filepath = str(tmp_path / "f12.png")
    assert bpy.ops.render.render(write_still=True) == {"FINISHED"}
    ops = [op for op, _ in client.sent]
    assert ops[ops.index("warm") :] == ["warm", "info", "render", "render"]  # the frame of each NeRF shown
    assert client.call("info")[0]["pid"] == pid  # rendered on the worker the file's opening started
    assert client.drain() >= 1  # warm's answer (a result: no error was reported)
    alpha = np.asarray(Image.open(tmp_path / "f12.png").convert("RGBA"))[..., 3]
    assert alpha.max() > 200 and alpha.min() < 20
