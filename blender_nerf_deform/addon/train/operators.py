"""Train NeRF: train a NeRF on a dataset folder in the worker, in the background, then load it.

Any dataset form the engine reads (NeRF-synthetic / instant-ngp / nerfstudio transforms.json,
LLFF, a COLMAP model with its images). The run folder (its `nerf.ckpt`) defaults to
`//nerf_runs/<dataset name>` beside a saved .blend, else the extension's user folder. From the UI
it runs in the worker while Blender stays usable: progress (steps, batch PSNR, elapsed, an
estimate of what is left) in the status bar; Esc cancels, and the checkpoint written so far is
kept and loaded. Resume continues the run folder's checkpoint. When done the NeRF object appears,
or, if one already shows this checkpoint, it renders the new weights (the worker reloads a
checkpoint whose file changed). From Python (`bpy.ops.nerf_deform.train_nerf(...)`) it blocks.
The worker serves one request at a time: renders and previews of the scene wait while it trains.

Preview (the Train panel's button, `nerf_deform.preview_training`, train/training_preview.py): while a
training runs, a small frame of the model as it is now, from the scene camera (or, without one,
a view of the NeRF's box), into the image "NeRF Training Preview" shown in open Image Editors.
The training answers it between two steps and goes on undisturbed; with no training running it
renders the run folder's checkpoint. The button is enabled while a training runs or when the
panel's run folder holds a checkpoint.

Import Photos (train/photos.py) is the same training after a first stage that finds the photos'
cameras by structure from motion: one operator, photos folder to NeRF object.
"""

from __future__ import annotations

import os

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, StringProperty

from ...engine.service.requests import MaskMeaning, TrainRequest
from ..data.paths import default_run_folder, same_file
from ..data.properties import Role
from ..worker.jobs import WorkerOperator

# What a dataset's masks mean (the engine's `train --masks`, silhouettes.py), as Blender enum items.
MASK_ITEMS = (
    (
        "auto",
        "Auto",
        "Decided by their shape: Object when the masks keep a shape inside the photo, Ignore "
        "when they keep most of it (the report says which)",
    ),
    (
        "object",
        "Object",
        "The object alone is real: outside the mask is empty space, and the NeRF renders "
        "transparent around the object (turntable and product captures)",
    ),
    ("ignore", "Ignore", "The masked-out pixels are not trained (passers-by); the rest of the photo is"),
)
MASK_REPORTS = {
    "object": "masks read as the object alone (transparent around it)",
    "ignore": "masks read as pixels to skip",
}


def train_params(
    data: str, out: str, seconds: float, steps: int, device: str, downscale: int, resume: bool, masks: str = "auto"
) -> dict:
    """The worker's `train` request (a budget of seconds and/or steps; 0 is no limit)."""
    request = TrainRequest(
        data,
        out,
        steps=int(steps) if steps > 0 else None,
        max_seconds=float(seconds) if seconds > 0 else None,
        device=device,
        downscale=int(downscale),
        resume=bool(resume),
        masks=MaskMeaning(masks),
    )
    return request.to_wire()[0]


def show_trained(op, context, result: dict, ckpt: str) -> set[str]:
    """After a training (done or cancelled): report it, then load its checkpoint as a NeRF object, or
    refresh the objects that already show it."""
    ckpt = result.get("checkpoint", ckpt)
    how = "cancelled, the checkpoint so far kept" if result.get("cancelled") else "done"
    masks = (
        f"; {MASK_REPORTS[result['masks']]}: {result.get('masks_reason')}"
        if result.get("masks") in MASK_REPORTS
        else ""
    )
    op.report(
        {"INFO"},
        f"{op.bl_label} {how}: {result.get('steps', 0)} steps in {result.get('seconds', 0):.0f} s, "
        f"batch PSNR {result.get('psnr', float('nan')):.1f} dB -> {ckpt}{masks}",
    )
    existing = [
        o
        for o in bpy.data.objects
        if o.nerf_deform.role == Role.NERF
        and o.users_collection
        and o.nerf_deform.checkpoint
        and same_file(bpy.path.abspath(o.nerf_deform.checkpoint), ckpt)
    ]
    if existing:
        for nerf in existing:
            nerf.update_tag()  # renders and the viewport take the new weights (the worker reloads the file)
        op.report({"INFO"}, f"{', '.join(o.name for o in existing)} now shows the new checkpoint")
        return {"FINISHED"}
    if bpy.ops.nerf_deform.load_nerf(filepath=ckpt) != {"FINISHED"}:
        op.report({"ERROR"}, f"{op.bl_label}: the checkpoint {ckpt} could not be loaded")
        return {"CANCELLED"}
    return {"FINISHED"}


class NERFDEFORM_OT_train_nerf(WorkerOperator, bpy.types.Operator):
    """Train a NeRF on a dataset folder in the background (Esc cancels and keeps the checkpoint), then load it"""

    bl_idname = "nerf_deform.train_nerf"
    bl_label = "Train NeRF"
    bl_options = {"REGISTER"}

    data: StringProperty(
        name="Dataset",
        subtype="DIR_PATH",
        description="Folder of a dataset: transforms.json (+ images), LLFF or a COLMAP model",
    )
    run_folder: StringProperty(
        name="Run Folder",
        subtype="DIR_PATH",
        description="Where nerf.ckpt is written (empty: //nerf_runs/<dataset name>)",
    )
    seconds: FloatProperty(
        name="Time Budget",
        default=300.0,
        min=0.0,
        subtype="TIME_ABSOLUTE",
        unit="TIME_ABSOLUTE",
        description="Seconds of training (0: no time limit, use Steps)",
    )
    steps: IntProperty(name="Steps", default=0, min=0, description="Training steps (0: no step limit, use the time)")
    device: EnumProperty(
        name="Device",
        items=(("auto", "Auto", "CUDA when the worker has it, else the CPU"), ("cpu", "CPU", ""), ("cuda", "CUDA", "")),
        default="auto",
    )
    downscale: IntProperty(
        name="Downscale", default=1, min=1, max=16, description="Box-filter the images by this factor"
    )
    resume: BoolProperty(name="Resume", default=False, description="Continue the run folder's checkpoint")
    masks: EnumProperty(
        name="Masks", items=MASK_ITEMS, default="auto", description="What the dataset's masks (mask_path) mean"
    )

    def request(self, context):
        data = os.path.abspath(bpy.path.abspath(self.data)) if self.data else ""
        if not data or not os.path.isdir(data):
            raise ValueError(f"dataset folder {data or '(none)'} does not exist: pick the folder of a dataset")
        if self.seconds <= 0 and self.steps <= 0:
            raise ValueError("give a time budget or a number of steps")
        out = os.path.abspath(bpy.path.abspath(self.run_folder)) if self.run_folder else default_run_folder(data)
        ckpt = os.path.join(out, "nerf.ckpt")
        if os.path.exists(ckpt) and not self.resume:
            raise ValueError(f"{ckpt} already holds a NeRF: tick Resume to continue it, or pick another run folder")
        self._checkpoint = ckpt
        return (
            "train",
            train_params(
                data,
                out,
                self.seconds,
                self.steps,
                self.device,
                self.downscale,
                self.resume and os.path.exists(ckpt),
                self.masks,
            ),
            None,
        )

    def apply(self, context, result, arrays):
        return show_trained(self, context, result, self._checkpoint)


class NERFDEFORM_TrainingSettings(bpy.types.PropertyGroup):
    """The Train panel's fields (the scene's), handed to Train NeRF when its button is pressed."""

    data: StringProperty(
        name="Dataset",
        subtype="DIR_PATH",
        description="Folder of a dataset: transforms.json (+ images), LLFF or a COLMAP model",
    )
    run_folder: StringProperty(
        name="Run Folder",
        subtype="DIR_PATH",
        description="Where nerf.ckpt is written (empty: //nerf_runs/<dataset name>)",
    )
    seconds: FloatProperty(
        name="Time Budget (s)", default=300.0, min=0.0, description="Seconds of training (0: use Steps)"
    )
    steps: IntProperty(name="Steps", default=0, min=0, description="Training steps (0: use the time budget)")
    device: EnumProperty(
        name="Device",
        items=(("auto", "Auto", "CUDA when the worker has it, else the CPU"), ("cpu", "CPU", ""), ("cuda", "CUDA", "")),
        default="auto",
    )
    downscale: IntProperty(
        name="Downscale", default=1, min=1, max=16, description="Box-filter the images by this factor"
    )
    resume: BoolProperty(name="Resume", default=False, description="Continue the run folder's checkpoint")
    masks: EnumProperty(
        name="Masks", items=MASK_ITEMS, default="auto", description="What the dataset's masks (mask_path) mean"
    )
    photos: StringProperty(
        name="Photos",
        subtype="DIR_PATH",
        description="Folder of photos (.jpg/.png) for Import Photos: cameras by structure from "
        "motion, then training (run folder //nerf_runs/<folder name>)",
    )


_classes = (NERFDEFORM_OT_train_nerf, NERFDEFORM_TrainingSettings)
_register_classes, _unregister_classes = bpy.utils.register_classes_factory(_classes)


def register():
    _register_classes()
    bpy.types.Scene.nerf_deform_training = bpy.props.PointerProperty(type=NERFDEFORM_TrainingSettings)


def unregister():
    del bpy.types.Scene.nerf_deform_training
    _unregister_classes()
