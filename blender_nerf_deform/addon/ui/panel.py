"""The "NeRF Deform" tab of the 3D View's sidebar."""

import bpy

from ..data.properties import handles_of, owning_nerf
from ..edit.regions import regions_of


class NERFDEFORM_PT_main(bpy.types.Panel):
    bl_label = "NeRF Deform"
    bl_idname = "NERFDEFORM_PT_main"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "NeRF Deform"

    def draw(self, context):
        layout = self.layout
        nerf = owning_nerf(context.active_object)
        layout.operator("nerf_deform.load_nerf", icon="FILE_FOLDER")
        if nerf is None:
            layout.label(text="Select a NeRF object, or load one.")
            return
        s = nerf.nerf_deform
        layout.label(text=nerf.name, icon="OUTLINER_OB_EMPTY")
        layout.prop(s, "checkpoint")
        box = layout.box()
        regions = regions_of(nerf)
        box.label(text=f"Edit Regions ({len(regions)})" if regions else "Edit Regions")
        box.operator("nerf_deform.add_edit_region", icon="CUBE")
        if not regions:
            box.label(text="(none: the whole box)")
        for region in regions:
            row = box.row(align=True)
            selected = region.select_get() if context.view_layer.objects.get(region.name) == region else False
            row.label(text=region.name, icon="CUBE")
            row.operator(
                "nerf_deform.select_edit_region",
                text="",
                icon="RESTRICT_SELECT_OFF" if selected else "RESTRICT_SELECT_ON",
                depress=selected,
            ).name = region.name
        col = box.column(align=True)
        col.prop(s, "pick_object")
        col.prop(s, "pin_cut")

        box = layout.box()
        box.label(text="Mesh and Cage")
        col = box.column(align=True)
        col.prop(s, "threshold")
        col.prop(s, "resolution")
        col.prop(s, "min_volume")
        box.operator("nerf_deform.extract_mesh", icon="MESH_DATA")
        box.operator("nerf_deform.build_cage", icon="MESH_ICOSPHERE")
        layout.prop(s, "deformation_mode")
        layout.prop(s, "render_substeps")

        row = layout.row(align=True)
        row.operator("nerf_deform.preview_render", icon="RENDER_STILL")
        row.operator("nerf_deform.cancel_preview", text="", icon="CANCEL")

        box = layout.box()
        box.label(text="Volume (Cycles, EEVEE, OpenVDB)")
        col = box.column(align=True)
        col.prop(s, "volume_folder", text="")
        col.prop(s, "volume_resolution", text="Resolution")
        col.prop(s, "volume_extent", text="Box")
        col.prop(s, "volume_frames", text="Frames")
        col.prop(s, "volume_shading", text="Material")
        bake = box.operator("nerf_deform.bake_volume", icon="VOLUME_DATA")
        bake.directory, bake.resolution, bake.extent = s.volume_folder, s.volume_resolution, s.volume_extent
        bake.frames, bake.shading = s.volume_frames, s.volume_shading
        bake.frame_start, bake.frame_end = context.scene.frame_start, context.scene.frame_end

        box = layout.box()
        box.label(text="Handles")
        col = box.column(align=True)
        col.operator("nerf_deform.add_handle", icon="EMPTY_AXIS")
        col.operator("nerf_deform.pin_selection", icon="PINNED")
        col.operator("nerf_deform.remove_handle", icon="X")
        col.operator("nerf_deform.reset_pose", icon="LOOP_BACK")
        for handle in handles_of(nerf, with_regions=False):
            box.label(text=f"{handle.name}", icon="EMPTY_DATA")


_classes = (NERFDEFORM_PT_main,)
register, unregister = bpy.utils.register_classes_factory(_classes)
