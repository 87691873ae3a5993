"""The Blender half: bpy and numpy only, never torch (docs/ARCHITECTURE.md).

Heavy work is sent to the engine in a worker process. The modules sit in one sub-package per
layer, bottom up: data (what is stored on objects and files), worker (the client of the engine
worker and the operators that use it), the pipeline's stages (capture, train, edit, deform,
render, export), ui (panels, preferences); api.py, the scripting API, sits on top. A module imports from
its own layer or lower ones only (tools/check_layering.py). This file registers them all.
"""

import atexit

from . import versioning
from .capture import operators as capture_operators
from .data import properties
from .data.guards import guard_classes
from .deform import handles, live_preview
from .edit import cage, extract, load_nerf, pick, regions
from .export import bake_volume
from .render import composite, preview_render, prewarm, render_engine
from .train import operators as train_operators
from .train import photos, training_preview
from .ui import panel, preferences, scene_panel, stage_panels
from .worker import client as worker_client
from .worker import setup as worker_setup

# Bottom up; the panels last, the main one before its sub-panels (Blender lists them in this order).
_modules = (
    properties,
    versioning,  # early, above its layer: its load_post repairs run before the other modules' (prewarm)
    worker_setup,
    capture_operators,
    train_operators,
    training_preview,
    photos,
    load_nerf,
    regions,
    pick,
    extract,
    cage,
    handles,
    live_preview,
    render_engine,
    prewarm,
    preview_render,
    composite,
    bake_volume,
    preferences,
    panel,
    scene_panel,
    stage_panels,
)


def register():
    for module in _modules:
        guard_classes(getattr(module, "_classes", ()))  # an error nobody foresaw: one report, no traceback
        module.register()
    # The bpy module of Blender 4.2 and 4.5 runs Blender's exit (which disables add-ons, in 4.5)
    # only once Python frees `bpy`, after atexit; a worker reader thread still holding callbacks
    # would keep it alive (exit 139 in 4.2, a hang in 4.5): the worker stops first (worker/client.py).
    atexit.register(worker_client.shutdown)


def unregister():
    atexit.unregister(worker_client.shutdown)
    worker_client.shutdown()
    for module in reversed(_modules):
        module.unregister()
