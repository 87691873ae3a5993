"""Load NeRF: a checkpoint becomes a NeRF object placed in the scene."""

from __future__ import annotations

import os

import bpy
from bpy.props import StringProperty
from bpy_extras.io_utils import ImportHelper

from .jobs import WorkerOperator
from .properties import select_only

NERFDEFORM_ENGINE = "NERF_DEFORM"


def checkpoint_path(nerf: bpy.types.Object) -> str:
    """The NeRF's checkpoint as an absolute path (stored relative to the .blend when it is saved)."""
    return os.path.normpath(bpy.path.abspath(nerf.nerf_deform.checkpoint))


def relative_if_possible(path: str) -> str:
    """`//`-relative to the .blend when the .blend is saved (and on the same drive), else absolute."""
    if not bpy.data.filepath:
        return path
    try:
        return bpy.path.relpath(path)
    except ValueError:  # another drive on Windows
        return path


@bpy.app.handlers.persistent
def make_checkpoint_paths_relative(*_args) -> None:
    """On save: a NeRF loaded before the .blend had a path gets its checkpoint path made relative."""
    for obj in bpy.data.objects:
        s = obj.nerf_deform
        if s.role == "NERF" and s.checkpoint and not s.checkpoint.startswith("//"):
            s.checkpoint = relative_if_possible(s.checkpoint)


class NERFDEFORM_OT_load_nerf(WorkerOperator, bpy.types.Operator, ImportHelper):
    """Load a trained NeRF checkpoint as a NeRF object (an Empty drawn as its scene box)"""

    bl_idname = "nerf_deform.load_nerf"
    bl_label = "Load NeRF"
    bl_options = {"REGISTER", "UNDO"}

    filename_ext = ".ckpt"
    filter_glob: StringProperty(default="*.ckpt", options={"HIDDEN"})

    def request(self, context):
        path = os.path.abspath(bpy.path.abspath(self.filepath))
        if not os.path.isfile(path):
            raise ValueError(f"checkpoint {path} does not exist")
        self._path = path
        return "load", {"path": path}, None

    def invoke(self, context, event):
        # The file browser first; its confirmation calls execute().
        return ImportHelper.invoke(self, context, event)

    @staticmethod
    def _prepare_scene(scene) -> None:
        """Render with NeRF Deform, and show the NeRF's colours as it learnt them: the Standard
        view transform undoes exactly the sRGB decoding of the render, and dithering would add noise."""
        scene.render.engine = NERFDEFORM_ENGINE
        scene.view_settings.view_transform = "Standard"
        scene.view_settings.look = "None"
        scene.view_settings.exposure, scene.view_settings.gamma = 0.0, 1.0
        scene.render.dither_intensity = 0.0
        scene.render.film_transparent = True

    def apply(self, context, result, arrays):
        lo, hi = result["aabb"][:3], result["aabb"][3:]
        name = os.path.splitext(os.path.basename(os.path.dirname(self._path)) or "NeRF")[0] or "NeRF"
        nerf = bpy.data.objects.new(f"NeRF {name}", None)
        # An Empty's cube is centred on its origin: draw the smallest one that holds the box.
        nerf.empty_display_type = "CUBE"
        nerf.empty_display_size = max(max(abs(v) for v in lo), max(abs(v) for v in hi))
        s = nerf.nerf_deform
        s.role = "NERF"
        s.checkpoint = relative_if_possible(self._path)
        s.aabb = [*lo, *hi]
        context.collection.objects.link(nerf)
        nerf.location = context.scene.cursor.location
        self._prepare_scene(context.scene)
        select_only(context, nerf)
        self.report({"INFO"}, f"Loaded {nerf.name} from {self._path} (bounds {lo} .. {hi})")
        return {"FINISHED"}


_classes = (NERFDEFORM_OT_load_nerf,)
_register_classes, _unregister_classes = bpy.utils.register_classes_factory(_classes)


def register():
    _register_classes()
    bpy.app.handlers.save_pre.append(make_checkpoint_paths_relative)


def unregister():
    if make_checkpoint_paths_relative in bpy.app.handlers.save_pre:
        bpy.app.handlers.save_pre.remove(make_checkpoint_paths_relative)
    _unregister_classes()
