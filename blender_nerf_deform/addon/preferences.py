"""Add-on preferences: which Python (one that has torch) runs the engine worker."""

import bpy
from bpy.props import StringProperty

# The extension's top-level package: `bl_ext.<repo>.blender_nerf_deform` when
# enabled as an extension, `blender_nerf_deform` when imported directly.
ADDON_PACKAGE = __package__.rpartition(".")[0]


class NERFDEFORM_AddonPreferences(bpy.types.AddonPreferences):
    bl_idname = ADDON_PACKAGE

    worker_python: StringProperty(
        name="Worker Python",
        description="Python interpreter with torch installed that runs the NeRF engine "
        "(extraction, cage building, ARAP solves and rendering) in a separate process",
        subtype="FILE_PATH",
        default="",
    )

    def draw(self, context):
        layout = self.layout
        layout.prop(self, "worker_python")
        layout.label(text="A Python 3.11 with torch (CPU or CUDA); see the README.")


def worker_python(context=None) -> str:
    """The Worker Python preference ("" when unset, or when the add-on was imported
    directly rather than enabled, so it has no preferences)."""
    context = context or bpy.context
    addon = context.preferences.addons.get(ADDON_PACKAGE)
    return addon.preferences.worker_python if addon is not None else ""


_classes = (NERFDEFORM_AddonPreferences,)
register, unregister = bpy.utils.register_classes_factory(_classes)
