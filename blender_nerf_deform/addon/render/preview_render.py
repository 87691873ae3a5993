"""Background preview: the active camera's view, rendered in the worker, streamed into an image.

Frames come coarse first and then finer (1/8, 1/4, 1/2, full resolution), each
written into the image "NeRF Preview" as it arrives, so an Image Editor shows
something at once and sharpens while the artist keeps working: nothing here
blocks Blender. It is the viewport's `ProgressiveRender` through the scene
camera: every visible NeRF, merged by depth as F12 merges them. The worker's
answers reach the main thread through the client's timer; each step's answers
send the next, finer step. Cancel stops the requests in flight and keeps the
last frame shown.
"""

from __future__ import annotations

import bpy

import numpy as np

from ..data.camera import CameraError
from ..data.images import show_in_image_editors, write_image
from ..worker import jobs
from ..worker.client import WorkerError
from .frame import nerf_pose, nerfs_to_render, scene_pinhole
from .viewport import DOWNSCALES, ProgressiveRender

IMAGE_NAME = "NeRF Preview"


class PreviewJob:
    """One progressive preview of the scene camera's view: coarse to fine, every visible NeRF."""

    def __init__(self, context):
        depsgraph = context.evaluated_depsgraph_get()
        nerfs = nerfs_to_render(depsgraph)
        if not nerfs:
            raise ValueError("no NeRF object in the scene to preview: use Load NeRF first")
        poses = [nerf_pose(depsgraph, nerf) for nerf in nerfs]
        self.client = jobs.worker(context)
        self._render = ProgressiveRender(
            self.client, poses, scene_pinhole(depsgraph), self._arrived, downscales=DOWNSCALES
        )

    @property
    def state(self) -> str:  # running, finished, cancelled, failed
        return self._render.state

    @property
    def error(self) -> str:
        return self._render.error

    @property
    def delivered(self) -> list[tuple[int, int]]:  # sizes shown so far
        return self._render.delivered

    def start(self) -> None:
        self._render.start()

    def _arrived(self, _render, rgba: np.ndarray, _depth, _downscale) -> None:
        show_in_image_editors(write_image(rgba, IMAGE_NAME))

    def cancel(self) -> None:
        self._render.cancel()


_job: PreviewJob | None = None


def current_job() -> PreviewJob | None:
    return _job


class NERFDEFORM_OT_preview_render(bpy.types.Operator):
    """Render the active camera's view of the NeRFs in the background into the image "NeRF Preview", coarse to fine"""

    bl_idname = "nerf_deform.preview_render"
    bl_label = "Preview Render"

    def execute(self, context):
        global _job
        if _job is not None:
            _job.cancel()
        try:
            _job = PreviewJob(context)
            _job.start()
            if _job.state == "failed":  # the worker could not take the requests
                raise WorkerError(_job.error)
        except (CameraError, ValueError, WorkerError) as error:
            self.report({"ERROR"}, f"Preview Render: {error}")
            return {"CANCELLED"}
        self.report({"INFO"}, f"Preview rendering into the image '{IMAGE_NAME}' (open it in an Image Editor)")
        return {"FINISHED"}


class NERFDEFORM_OT_cancel_preview(bpy.types.Operator):
    """Stop the background preview render, keeping the last frame shown"""

    bl_idname = "nerf_deform.cancel_preview"
    bl_label = "Cancel Preview"

    @classmethod
    def poll(cls, context):
        if _job is None or _job.state != "running":
            cls.poll_message_set("No preview render is running")
            return False
        return True

    def execute(self, context):
        _job.cancel()
        return {"FINISHED"}


_classes = (NERFDEFORM_OT_preview_render, NERFDEFORM_OT_cancel_preview)
register, unregister = bpy.utils.register_classes_factory(_classes)
