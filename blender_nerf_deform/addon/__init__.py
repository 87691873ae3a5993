"""The Blender half: bpy and numpy only, never torch (docs/ARCHITECTURE.md).

Properties, operators, panels and the RenderEngine live here; heavy work is
sent to the engine in a worker process.
"""

import atexit

from . import (cage_ops, capture_ops, composite, extract_ops, handles, nerf_ops, panel, pick_ops, preferences, preview, preview_render,
               photos_ops, properties, region_ops, render_engine, scene_panel, train_ops, training_preview, worker_client,
               worker_setup)

# composite after panel: its sub-panel hangs under the main NeRF Deform panel.
_modules = (preferences, worker_setup, properties, nerf_ops, region_ops, pick_ops, extract_ops, cage_ops, handles, preview, render_engine, preview_render, panel, scene_panel,
            composite, train_ops, capture_ops, training_preview, photos_ops)


def register():
    for module in _modules:
        module.register()
    # The bpy module of Blender 4.2 and 4.5 runs Blender's exit (which disables add-ons, in 4.5)
    # only once Python frees `bpy`, after atexit; a worker reader thread still holding callbacks
    # would keep it alive (exit 139 in 4.2, a hang in 4.5): the worker stops first (worker_client).
    atexit.register(worker_client.shutdown)


def unregister():
    atexit.unregister(worker_client.shutdown)
    worker_client.shutdown()
    for module in reversed(_modules):
        module.unregister()
