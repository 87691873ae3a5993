"""The "NeRF Deform" tab of the 3D View's sidebar."""

import bpy


class NERFDEFORM_PT_main(bpy.types.Panel):
    bl_label = "NeRF Deform"
    bl_idname = "NERFDEFORM_PT_main"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "NeRF Deform"

    def draw(self, context):
        # Placeholder until the add-on issue lands its operators.
        self.layout.label(text="Load a NeRF to begin (coming soon).")


_classes = (NERFDEFORM_PT_main,)
register, unregister = bpy.utils.register_classes_factory(_classes)
