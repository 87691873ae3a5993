"""Handles drive the cage by ARAP in the worker: the live preview follows, and F12 renders the pose."""

import time

import numpy as np
import pytest
from fixtures.blender_objects import nerf_with_built_cage, select_in_edit_mode


def _preview(surface):
    keys = surface.data.shape_keys
    if keys is None or "NeRF Deform" not in keys.key_blocks:
        return None
    co = np.empty(3 * len(surface.data.vertices), dtype=np.float32)
    keys.key_blocks["NeRF Deform"].data.foreach_get("co", co)
    return co.reshape(-1, 3)


def _pump_until(condition, seconds=60):
    """Run what Blender's timer runs on the main thread (the worker's answers) until `condition`."""
    from blender_nerf_deform.addon.worker import client as worker_client

    deadline = time.monotonic() + seconds
    while not condition() and time.monotonic() < deadline:
        worker_client._drain_timer()
        time.sleep(0.02)
    return condition()


@pytest.mark.slow
def test_arap_preview_follows_a_moved_handle_and_keeps_the_pin(addon, sphere_nerf):
    bpy = addon
    ckpt, _ = sphere_nerf
    nerf, surface, rest = nerf_with_built_cage(bpy, ckpt)
    z = rest[:, 2]  # quarters of the mesh's own height: the fixture's mesh varies per session
    top, bottom = np.flatnonzero(z > z.min() + 0.75 * np.ptp(z)), np.flatnonzero(z < z.min() + 0.25 * np.ptp(z))
    select_in_edit_mode(bpy, surface, bottom)
    assert bpy.ops.nerf_deform.pin_selection() == {"FINISHED"}
    select_in_edit_mode(bpy, surface, top)
    assert bpy.ops.nerf_deform.add_handle() == {"FINISHED"}
    handle = bpy.context.active_object

    handle.location.z += 0.3
    bpy.context.view_layer.update()

    from blender_nerf_deform.addon.deform import live_preview as preview

    solver = preview._solvers[nerf.name]
    assert _pump_until(lambda: not solver.in_flight and solver.waiting is None)
    moved = _preview(surface)
    assert np.allclose(moved[top, 2] - rest[top, 2], 0.3, atol=0.02)
    assert np.abs(moved[bottom] - rest[bottom]).max() < 0.02
    middle = np.flatnonzero(np.abs(rest[:, 2]) < 0.1)
    assert 0.02 < np.mean(moved[middle, 2] - rest[middle, 2]) < 0.28  # in between: as rigid as possible
