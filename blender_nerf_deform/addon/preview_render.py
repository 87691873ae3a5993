"""Background preview: the active camera's view, rendered in the worker, streamed into an image.

Frames come coarse first and then finer (1/8, 1/4, 1/2, full resolution), each
written into the image "NeRF Preview" as it arrives, so an Image Editor shows
something at once and sharpens while the artist keeps working: nothing here
blocks Blender. The worker's answers reach the main thread through the
client's timer; each answer sends the next, finer request. Cancel stops the
request in flight and keeps the last frame shown.
"""

from __future__ import annotations

import bpy
import numpy as np

from . import jobs
from .camera import CameraError
from .frame_render import frame_request, nerfs_to_render, srgb_to_linear
from .worker_client import WorkerError

IMAGE_NAME = "NeRF Preview"
DOWNSCALES = (8, 4, 2, 1)


def show_in_image_editors(image: bpy.types.Image) -> None:
    """Show `image` in every open Image Editor that shows nothing or a previous preview, and redraw."""
    wm = bpy.context.window_manager
    for window in wm.windows if wm else ():
        for area in window.screen.areas:
            if area.type != "IMAGE_EDITOR":
                continue
            space = area.spaces.active
            if space.image is None or space.image == image:
                space.image = image
            area.tag_redraw()


def write_image(rgba: np.ndarray) -> bpy.types.Image:
    """Put a straight-alpha sRGB frame (rows top-down) into "NeRF Preview" (linear float, rows bottom-up)."""
    height, width = rgba.shape[:2]
    image = bpy.data.images.get(IMAGE_NAME)
    if image is None:
        image = bpy.data.images.new(IMAGE_NAME, width, height, alpha=True, float_buffer=True)
    elif tuple(image.size) != (width, height):
        image.scale(width, height)
    linear = np.concatenate([srgb_to_linear(rgba[..., :3]), rgba[..., 3:]], axis=-1)
    image.pixels.foreach_set(np.ascontiguousarray(linear[::-1], dtype=np.float32).ravel())
    image.update()
    return image


class PreviewJob:
    """One progressive preview: a chain of worker requests, coarse to fine."""

    def __init__(self, context):
        scene = context.scene
        nerfs = nerfs_to_render(scene)
        if not nerfs:
            raise ValueError("no NeRF object in the scene to preview: use Load NeRF first")
        depsgraph = context.evaluated_depsgraph_get()
        self.requests = [frame_request(depsgraph, nerfs[0], k) for k in DOWNSCALES]
        self.client = jobs.worker(context)
        self.delivered: list[tuple[int, int]] = []  # sizes shown so far
        self.state = "running"  # running, finished, cancelled, failed
        self.error = ""
        self._request_id: int | None = None

    def start(self) -> None:
        self._send(0)

    def _send(self, step: int) -> None:
        request = self.requests[step]
        self._request_id = self.client.submit(
            "render", request.params, request.arrays, shared=request.shared,
            on_done=lambda result, out: self._arrived(step, out),
            on_error=self._failed,
        )

    def _arrived(self, step: int, out: dict) -> None:
        if self.state != "running":
            return
        image = write_image(out["rgba"])
        self.delivered.append(tuple(image.size))
        show_in_image_editors(image)
        if step + 1 < len(self.requests):
            self._send(step + 1)
        else:
            self.state = "finished"

    def _failed(self, error: WorkerError) -> None:
        if self.state == "running":
            self.state, self.error = ("cancelled", "") if error.kind == "cancelled" else ("failed", str(error))

    def cancel(self) -> None:
        if self.state == "running":
            self.state = "cancelled"
            self.client.cancel(self._request_id)


_job: PreviewJob | None = None


def current_job() -> PreviewJob | None:
    return _job


class NERFDEFORM_OT_preview_render(bpy.types.Operator):
    """Render the active camera's view of the NeRF in the background into the image "NeRF Preview", coarse to fine"""

    bl_idname = "nerf_deform.preview_render"
    bl_label = "Preview Render"

    def execute(self, context):
        global _job
        if _job is not None:
            _job.cancel()
        try:
            _job = PreviewJob(context)
            _job.start()
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
