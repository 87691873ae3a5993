"""Import Photos: a folder of photos → their cameras → a trained NeRF → the NeRF object, as one operator.

Two worker requests in a chain (worker/jobs.py): `prepare` (structure from motion with pycolmap, the
`prepare` command's stage: features, matching, mapping) writes the dataset, then `train` trains on
it and the NeRF object appears as after Train NeRF. The status bar says which stage runs: "1/2
cameras: ..." then "2/2 training: ...". The run folder defaults to `//nerf_runs/<photos folder
name>` (beside a saved .blend, else the extension's user folder, as Train NeRF's) and the dataset
to `<run folder>/dataset`.

Esc cancels whichever stage runs. A cancelled prepare stops pycolmap midway (its cancellation
token) and leaves nothing: the dataset is written into a temporary folder renamed at the end, and
the folders it made are removed again. A cancelled training keeps its checkpoint, which is loaded
as Train NeRF loads it. A prepare that finished before its cancel reached it keeps its (whole)
dataset and the training is not started. From Python (`bpy.ops.nerf_deform.import_photos(...)`,
`api.import_photos`) both stages run blocking.
"""

from __future__ import annotations

import os

import bpy
from bpy.props import EnumProperty, FloatProperty, IntProperty, StringProperty

from ...engine.service.requests import Matcher, PrepareRequest
from ...engine.sfm import photo_names
from ..data.paths import default_run_folder
from ..worker.jobs import WorkerOperator, WorkerRequest
from .operators import show_trained, train_params

MIN_PHOTOS = 3  # what structure from motion needs at the very least


class NERFDEFORM_OT_import_photos(WorkerOperator, bpy.types.Operator):
    """Find the cameras of a folder of photos (structure from motion), train a NeRF on them in the background and load it (Esc cancels)"""  # noqa: E501 (the tooltip: one line)

    bl_idname = "nerf_deform.import_photos"
    bl_label = "Import Photos"
    bl_options = {"REGISTER"}

    photos: StringProperty(name="Photos", subtype="DIR_PATH", description="Folder of photos (.jpg/.png) of one scene")
    run_folder: StringProperty(
        name="Run Folder",
        subtype="DIR_PATH",
        description="Where nerf.ckpt is written (empty: //nerf_runs/<photos folder name>)",
    )
    dataset: StringProperty(
        name="Dataset",
        subtype="DIR_PATH",
        description="Where the cameras and photos are written (empty: <run folder>/dataset)",
    )
    matcher: EnumProperty(
        name="Matching",
        default="exhaustive",
        items=(
            ("exhaustive", "Exhaustive", "Every pair of photos (up to a few hundred photos)"),
            ("sequential", "Sequential", "Neighbours in name order (frames of a video)"),
        ),
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
        name="Downscale", default=1, min=1, max=16, description="Box-filter the photos by this factor"
    )

    def request(self, context):
        photos = os.path.abspath(bpy.path.abspath(self.photos)) if self.photos else ""
        if not photos or not os.path.isdir(photos):
            raise ValueError(f"photos folder {photos or '(none)'} does not exist: pick a folder of photos")
        count = len(photo_names(photos))
        if count < MIN_PHOTOS:
            raise ValueError(
                f"{photos} holds {count} photos (.jpg/.png); finding their cameras needs at least "
                f"{MIN_PHOTOS}, and a few dozen overlapping ones work best"
            )
        if self.seconds <= 0 and self.steps <= 0:
            raise ValueError("give a time budget or a number of steps")
        run = os.path.abspath(bpy.path.abspath(self.run_folder)) if self.run_folder else default_run_folder(photos)
        dataset = os.path.abspath(bpy.path.abspath(self.dataset)) if self.dataset else os.path.join(run, "dataset")
        ckpt = os.path.join(run, "nerf.ckpt")
        if os.path.exists(ckpt):
            raise ValueError(
                f"{ckpt} already holds a NeRF: pick another run folder, or continue it with Train NeRF "
                "(Resume) on its dataset"
            )
        if os.path.exists(dataset) and (not os.path.isdir(dataset) or os.listdir(dataset)):
            raise ValueError(f"{dataset} already holds a dataset: train it with Train NeRF, or pick another run folder")
        self._run, self._dataset, self._checkpoint = run, dataset, ckpt
        request = PrepareRequest(photos, dataset, Matcher(self.matcher))
        return WorkerRequest("prepare", request.to_wire()[0], None, "1/2 cameras")

    def apply(self, context, result, arrays):
        if self.current_request.op == "prepare":
            left_out = result.get("unregistered") or []
            self.report(
                {"INFO"},
                f"Import Photos: cameras of {result.get('registered', 0)} of {result.get('photos', 0)} "
                f"photos found" + (f" ({len(left_out)} left out)" if left_out else "") + f" -> {self._dataset}",
            )
            params = train_params(
                self._dataset, self._run, self.seconds, self.steps, self.device, self.downscale, False
            )
            return WorkerRequest("train", params, None, "2/2 training")
        return show_trained(self, context, result, self._checkpoint)


_classes = (NERFDEFORM_OT_import_photos,)
register, unregister = bpy.utils.register_classes_factory(_classes)
