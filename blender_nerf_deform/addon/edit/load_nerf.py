"""Load NeRF: a checkpoint becomes a NeRF object placed in the scene."""

from __future__ import annotations

import os

import bpy
from bpy.props import StringProperty

from bpy_extras.io_utils import ImportHelper

from ...engine.service.requests import LoadRequest
from ..data.properties import RENDER_ENGINE_ID, Role, add_app_handlers, remove_app_handlers, select_only
from ..worker.jobs import WorkerOperator


def relative_if_possible(path: str, start: str | None = None) -> str:
    """`//`-relative to the folder `start` (default: the .blend's, when it is saved) where the
    path is on the same drive, else absolute."""
    if start is None:
        if not bpy.data.filepath:
            return path
        start = os.path.dirname(bpy.data.filepath)
    try:
        return bpy.path.relpath(path, start=start)
    except ValueError:  # another drive on Windows
        return path


def rebased_path(path: str, old_blend: str, new_blend: str, make_relative: bool = True) -> str:
    """`path` as stored in the .blend `old_blend` ("": never saved), rewritten for the .blend
    `new_blend`: a `//` path is resolved against the old file's folder and made relative to the
    new one's (absolute where it cannot be: another drive); an absolute one is made relative
    when `make_relative`."""
    if path.startswith("//"):
        if not old_blend:
            return path  # relative to no file: nothing to resolve it against
        absolute = os.path.normpath(bpy.path.abspath(path, start=os.path.dirname(old_blend)))
    elif not make_relative:
        return path
    else:
        absolute = os.path.abspath(path)
    return relative_if_possible(absolute, start=os.path.dirname(os.path.abspath(new_blend)))


# (object, checkpoint path before the save) of the save under way: a save that did not make the
# saved file the open one (Save Copy) or failed gives the open file its paths back.
_before_save: list[tuple[bpy.types.Object, str]] = []


def _saved_path(args) -> str:
    """The file being saved, as Blender passes it to save handlers (bpy.data.filepath before 4.x)."""
    return next((a for a in args if isinstance(a, str)), bpy.data.filepath)


@bpy.app.handlers.persistent
def make_checkpoint_paths_relative(*args) -> None:
    """On save: every NeRF's checkpoint path, relative to the file being saved. Blender's own
    relative remap does not rewrite add-on properties, so Save As into another folder would break
    `//` paths; a NeRF loaded before the .blend had a path gets its path made relative."""
    _before_save.clear()
    new_blend = _saved_path(args)
    if not new_blend:  # the startup file
        return
    make_relative = bpy.context.preferences.filepaths.use_relative_paths
    for obj in bpy.data.objects:
        s = obj.nerf_deform
        if s.role != Role.NERF or not s.checkpoint or obj.library is not None:
            continue
        path = rebased_path(s.checkpoint, bpy.data.filepath, new_blend, make_relative)
        if path != s.checkpoint:
            _before_save.append((obj, s.checkpoint))
            s.checkpoint = path


@bpy.app.handlers.persistent
def _after_save(*args) -> None:
    saved = _saved_path(args)
    if not bpy.data.filepath or os.path.normpath(bpy.data.filepath) != os.path.normpath(saved):
        _restore_paths()  # a copy: the open file keeps paths relative to itself
    _before_save.clear()


@bpy.app.handlers.persistent
def _restore_paths(*_args) -> None:
    for obj, path in _before_save:
        try:
            obj.nerf_deform.checkpoint = path
        except ReferenceError:
            pass
    _before_save.clear()


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
        return "load", *LoadRequest(path).to_wire()

    def invoke(self, context, event):
        # The file browser first; its confirmation calls execute().
        return ImportHelper.invoke(self, context, event)

    @staticmethod
    def _prepare_scene(scene) -> None:
        """Render with NeRF Deform, and show the NeRF's colours as it learnt them: the Standard
        view transform undoes exactly the sRGB decoding of the render, and dithering would add noise."""
        scene.render.engine = RENDER_ENGINE_ID
        scene.view_settings.view_transform = "Standard"
        scene.view_settings.look = "None"
        scene.view_settings.exposure, scene.view_settings.gamma = 0.0, 1.0
        scene.render.dither_intensity = 0.0
        scene.render.film_transparent = True

    def apply(self, context, result, arrays):
        lo, hi = result["aabb"][:3], result["aabb"][3:]
        unbounded = result.get("config", {}).get("contraction", "none") != "none"
        name = os.path.splitext(os.path.basename(os.path.dirname(self._path)) or "NeRF")[0] or "NeRF"
        nerf = bpy.data.objects.new(f"NeRF {name}", None)
        # An Empty's cube is centred on its origin: draw the smallest one that holds the box. For an
        # unbounded NeRF the box is its inner region (what extraction and cages use); the background
        # beyond it renders but is not drawn.
        nerf.empty_display_type = "CUBE"
        nerf.empty_display_size = max(max(abs(v) for v in lo), max(abs(v) for v in hi))
        s = nerf.nerf_deform
        s.role = Role.NERF
        s.checkpoint = relative_if_possible(self._path)
        s.aabb = [*lo, *hi]
        context.collection.objects.link(nerf)
        nerf.location = context.scene.cursor.location
        # The datasets' frames are Z up already (instant-ngp, nerfstudio, and the engine's LLFF, COLMAP
        # and prepare readers orient them). A capture in arbitrary units (a COLMAP scale of 0.001 or
        # 1000) is shown at a workable size: its box's largest side becomes SENSIBLE_SIZE.
        extent = max(b - a for a, b in zip(lo, hi))
        note = ""
        if not SIZE_RANGE[0] <= extent <= SIZE_RANGE[1]:
            factor = SENSIBLE_SIZE / extent
            nerf.scale = (factor, factor, factor)
            note = f"; scaled by {factor:.3g} to {SENSIBLE_SIZE:g} units across"
        self._prepare_scene(context.scene)
        select_only(context, nerf)
        kind = "unbounded: a background surrounds the box" if unbounded else "bounded"
        masks = result.get("config", {}).get("masks", "none")
        if masks == "object":
            kind += ", an object cut out by its masks: transparent around it"
        elif masks == "ignore":
            kind += ", trained with the masked-out pixels skipped"
        self.report({"INFO"}, f"Loaded {nerf.name} from {self._path} (box {_fmt(lo)} .. {_fmt(hi)}, {kind}{note})")
        return {"FINISHED"}


SIZE_RANGE = (0.05, 100.0)  # a box side outside this is no size to edit at
SENSIBLE_SIZE = 3.0


def _fmt(v) -> str:
    return "(" + ", ".join(f"{x:.3g}" for x in v) + ")"


_classes = (NERFDEFORM_OT_load_nerf,)
_register_classes, _unregister_classes = bpy.utils.register_classes_factory(_classes)


def _handlers():
    h = bpy.app.handlers
    handlers = [(h.save_pre, make_checkpoint_paths_relative), (h.save_post, _after_save)]
    if hasattr(h, "save_post_fail"):  # Blender 4.x+
        handlers.append((h.save_post_fail, _restore_paths))
    return handlers


def register():
    _register_classes()
    add_app_handlers(_handlers())


def unregister():
    remove_app_handlers(_handlers())
    _unregister_classes()
