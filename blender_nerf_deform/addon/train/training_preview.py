"""Preview Training: a small frame of a training run, of the model as it is now, while it trains.

The worker serves one request at a time, but a training answers the `training_preview`
requests of its own run between two steps (engine/service/registry.py: side requests): the
preview comes back within a step and a render, and the training goes on as if it had not been
asked (the same weights). When no training of the run runs, the worker renders the run's
checkpoint file instead. The frame goes into the image "NeRF Training Preview", shown in the
open Image Editors.

Which run: the operator's `run_folder`, else the training this Blender runs now (Train NeRF,
Import Photos, the last one started), else the Train panel's run folder (its own, or its
dataset's or photos' default) when it holds a checkpoint.
Which view: the scene camera, placed as the NeRF object that shows the checkpoint places it (or,
before there is one, as Load NeRF will place it: at the 3D cursor), at a reduced resolution (the
longest side `max_size` pixels); without a scene camera, a view of the NeRF's box from the front
right, above (where Blender's default camera stands), Z up, the box filling the view, at the
render resolution's aspect (the engine's `Camera.looking_at_box`).
From the UI the button returns at once and the image fills when the answer comes (a Train NeRF
running in the background keeps running); from Python (`bpy.ops.nerf_deform.preview_training()`)
it blocks.
"""

from __future__ import annotations

import math
import os

import bpy
from bpy.props import IntProperty, StringProperty

import numpy as np

from ...engine.service.requests import TrainingPreviewRequest, WireCamera
from ..data.camera import CameraError, pinhole_from_blender, render_size
from ..data.images import show_in_image_editors, srgb_to_linear, write_image
from ..data.paths import default_run_folder, same_file
from ..data.properties import PlacementError, Role, to_nerf_frame
from ..worker import jobs
from ..worker.client import WorkerError, active_client

IMAGE_NAME = "NeRF Training Preview"
OP = "training_preview"
_last = {"message": "", "error": ""}  # what the Train panel shows of the last preview


def running_checkpoints() -> list[str]:
    """The checkpoints of the trainings this Blender's worker runs now, oldest first."""
    client = active_client()
    if client is None:
        return []
    return [os.path.join(p["out"], "nerf.ckpt") for p in client.in_flight("train") if isinstance(p.get("out"), str)]


def panel_checkpoints(context) -> list[str]:
    """Where the Train panel's runs write their checkpoints: its run folder (or its dataset's default),
    and its photos' default (Import Photos)."""
    t = context.scene.nerf_deform_training
    found = []
    if t.run_folder:
        found.append(os.path.join(os.path.abspath(bpy.path.abspath(t.run_folder)), "nerf.ckpt"))
    elif t.data:
        found.append(
            os.path.join(default_run_folder(os.path.abspath(bpy.path.abspath(t.data)), create=False), "nerf.ckpt")
        )
    if t.photos:
        found.append(
            os.path.join(default_run_folder(os.path.abspath(bpy.path.abspath(t.photos)), create=False), "nerf.ckpt")
        )
    return found


def can_preview(context) -> bool:
    return bool(running_checkpoints()) or any(os.path.isfile(c) for c in panel_checkpoints(context))


def world_to_nerf(context, checkpoint: str) -> np.ndarray:
    """World → the NeRF's frame: the NeRF object's showing `checkpoint`, else where Load NeRF will put it
    (its origin at the 3D cursor)."""
    for nerf in bpy.data.objects:
        s = nerf.nerf_deform
        if (
            s.role == Role.NERF
            and s.checkpoint
            and nerf.users_collection
            and same_file(bpy.path.abspath(s.checkpoint), checkpoint)
        ):
            return np.array(to_nerf_frame(nerf), dtype=np.float64)
    to_nerf = np.eye(4)
    to_nerf[:3, 3] = -np.array(context.scene.cursor.location, dtype=np.float64)
    return to_nerf


def preview_params(context, checkpoint: str, max_size: int) -> dict:
    """The request: the scene camera at a reduced resolution, or a view of the NeRF's box."""
    scene = context.scene
    if scene.camera is None:
        width, height = render_size(scene.render)
        scale = max_size / max(width, height, 1)
        size = [max(1, round(width * scale)), max(1, round(height * scale))]
        return TrainingPreviewRequest(checkpoint, None, tuple(size)).to_wire()[0]
    pinhole = pinhole_from_blender(scene, scene.camera.evaluated_get(context.evaluated_depsgraph_get()))
    pinhole = pinhole.downscaled(max(1, math.ceil(max(pinhole.width, pinhole.height) / max_size)))
    c2w = world_to_nerf(context, checkpoint) @ np.array(pinhole.camera_to_world, dtype=np.float64)
    return TrainingPreviewRequest(checkpoint, WireCamera.from_pinhole(pinhole, c2w)).to_wire()[0]


def show_preview(result: dict, arrays: dict) -> str:
    """Write the frame into the preview image and show it; returns what to tell the user."""
    rgba = arrays["rgba"]
    alpha = rgba[..., 3:]
    linear = np.concatenate(
        [srgb_to_linear(rgba[..., :3]) * alpha, alpha], axis=-1
    )  # premultiplied, as write_image takes
    show_in_image_editors(write_image(linear, IMAGE_NAME))
    size = f"{rgba.shape[1]}x{rgba.shape[0]}"
    if result.get("source") == "training":
        psnr = result.get("psnr")
        at = f"step {result.get('step', 0)}" + (f", batch PSNR {psnr:.1f} dB" if psnr is not None else "")
        message = f"training at {at}"
    else:
        message = f"the checkpoint {result.get('checkpoint', '')}"
    _last.update(message=f"{size} preview of {message}", error="")
    return f"Preview Training: {_last['message']}, in the image '{IMAGE_NAME}'"


def _redraw_panels() -> None:
    wm = bpy.context.window_manager
    for window in wm.windows if wm else ():
        for area in window.screen.areas:
            if area.type == "VIEW_3D":
                area.tag_redraw()


class NERFDEFORM_OT_preview_training(bpy.types.Operator):
    """Render a small preview of the NeRF being trained (or of the run's checkpoint) into the image "NeRF Training Preview\""""  # noqa: E501 (the tooltip: one line)

    bl_idname = "nerf_deform.preview_training"
    bl_label = "Preview"

    run_folder: StringProperty(
        name="Run Folder",
        subtype="DIR_PATH",
        description="The run to preview (empty: the training running now, else the Train panel's)",
    )
    max_size: IntProperty(
        name="Size",
        default=160,
        min=16,
        max=1024,
        description="Longest side of the preview in pixels (the training waits while it renders)",
    )

    @classmethod
    def poll(cls, context):
        if context.scene is None or not can_preview(context):
            cls.poll_message_set("No training runs, and the Train panel's run folder holds no checkpoint yet")
            return False
        return True

    def _params(self, context) -> dict:
        if self.run_folder:
            checkpoint = os.path.join(os.path.abspath(bpy.path.abspath(self.run_folder)), "nerf.ckpt")
        else:
            running = running_checkpoints()
            found = [c for c in panel_checkpoints(context) if os.path.isfile(c)]
            if not running and not found:
                raise ValueError(
                    "no training runs and the Train panel's run folder holds no checkpoint: "
                    "start Train NeRF or Import Photos first"
                )
            checkpoint = running[-1] if running else found[0]
        return preview_params(context, checkpoint, int(self.max_size))

    def _fail(self, error) -> set[str]:
        _last.update(error=str(error))
        self.report({"ERROR"}, f"Preview Training: {error}")
        return {"CANCELLED"}

    def execute(self, context):
        try:
            params = self._params(context)
            result, arrays = jobs.worker(context).call(OP, params)
        except (CameraError, PlacementError, ValueError, WorkerError) as error:
            return self._fail(error)
        self.report({"INFO"}, show_preview(result, arrays))
        return {"FINISHED"}

    def invoke(self, context, event):
        """Ask and return: the image fills when the answer comes (a running training answers between steps)."""
        try:
            params = self._params(context)
            client = jobs.worker(context)
            if client.in_flight(OP):
                self.report({"INFO"}, "Preview Training: a preview is on its way")
                return {"CANCELLED"}

            def done(result, arrays):
                print(show_preview(result, arrays))
                _redraw_panels()

            def failed(error):
                _last.update(error=str(error))
                print(f"Preview Training: {error}")
                _redraw_panels()

            client.submit(OP, params, on_done=done, on_error=failed)
        except (CameraError, PlacementError, ValueError, WorkerError) as error:
            return self._fail(error)
        _last.update(error="")
        return {"FINISHED"}


def draw_in_panel(layout, context) -> None:
    """The Train panel's Preview row and what the last preview said."""
    row = layout.row(align=True)
    row.operator(NERFDEFORM_OT_preview_training.bl_idname, icon="IMAGE_DATA")
    if _last["error"]:
        layout.label(text=_last["error"], icon="ERROR")
    elif _last["message"]:
        layout.label(text=_last["message"], icon="INFO")


_classes = (NERFDEFORM_OT_preview_training,)
register, unregister = bpy.utils.register_classes_factory(_classes)
