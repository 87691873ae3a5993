"""When a file with NeRFs opens in Blender's UI, the worker starts and loads them in the background, so
that the artist's first F12 or Rendered viewport waits for neither.

A file's first frame otherwise pays the worker's start (Python, torch and numba imported), the
checkpoints' load and numba's first run of the frame's kernels before it renders anything. The
worker's `warm` op does the last two; the start runs on a thread, so
Blender's main thread never waits for it, and a render asked for meanwhile waits for that same worker
rather than starting a second one.

Not in background mode (`blender -b`): a script may never render, and a batch render starts the worker
at once anyway. Off with the preference Start Worker on Open.
"""

from __future__ import annotations

import os
import sys
import threading

import bpy

from ...engine.service.requests import WarmRequest
from ..data.paths import addon_preferences, checkpoint_path
from ..data.properties import Role, add_app_handlers, remove_app_handlers
from ..worker import jobs
from ..worker.client import WorkerClient, WorkerError


def file_nerfs() -> list[str]:
    """The checkpoints of the NeRF objects in the open file's scene: files that exist, each once."""
    checkpoints = []
    for obj in bpy.context.scene.objects:
        settings = obj.nerf_deform
        if settings.role != Role.NERF or not settings.checkpoint:
            continue
        path = checkpoint_path(obj)
        if os.path.isfile(path) and path not in checkpoints:
            checkpoints.append(path)
    return checkpoints


def _report(error: Exception) -> None:
    # The first render says the same to the artist, in the place they look; here the console only.
    print(f"NeRF Deform: loading the file's NeRFs ahead of rendering failed: {error}", file=sys.stderr)


def start(client: WorkerClient, checkpoints: list[str]) -> threading.Thread:
    """Start `client`'s worker if it is not running and send it `warm` for the checkpoints, on a thread:
    returns at once."""

    def run():
        try:
            client.submit("warm", *WarmRequest(tuple(checkpoints)).to_wire(), on_error=_report)
        except Exception as error:  # whatever it was, a convenience that failed: one line, no traceback
            _report(error)

    thread = threading.Thread(target=run, name="nerf-worker-prewarm", daemon=True)
    thread.start()
    return thread


@bpy.app.handlers.persistent
def _warm_on_open(*_args) -> None:
    if bpy.app.background:
        return
    prefs = addon_preferences()
    if prefs is not None and not prefs.start_worker_on_open:
        return
    checkpoints = file_nerfs()
    if not checkpoints:
        return
    try:
        client = jobs.worker(bpy.context)  # no worker Python yet: the first render asks for one
    except WorkerError:
        return
    if not client.busy:  # a worker still training from the last file is left to it
        start(client, checkpoints)


def _handlers():
    return ((bpy.app.handlers.load_post, _warm_on_open),)


def register():
    add_app_handlers(_handlers())


def unregister():
    remove_app_handlers(_handlers())
