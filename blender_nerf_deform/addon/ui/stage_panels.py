"""The stages' sub-panels of the "NeRF Deform" tab: Composite, Train (with Preview Training and Import
Photos), Capture Dataset. Each draws the settings its stage keeps on the scene and hands them to the
stage's operator when its button is pressed."""

from __future__ import annotations

import bpy

from ..capture.dataset import renderable
from ..capture.operators import CAPTURE_OPTIONS, NERFDEFORM_OT_capture_dataset
from ..render.composite import NERFDEFORM_OT_composite_with_scene, mesh_scene_of
from ..train import training_preview
from ..train.operators import NERFDEFORM_OT_train_nerf


class _StagePanel:
    """Where the stages' sub-panels sit: closed, under the sidebar's NeRF Deform tab."""

    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "NeRF Deform"
    bl_parent_id = "NERFDEFORM_PT_main"
    bl_options = {"DEFAULT_CLOSED"}


class NERFDEFORM_PT_composite(_StagePanel, bpy.types.Panel):
    bl_label = "Composite"
    bl_idname = "NERFDEFORM_PT_composite"

    def draw(self, context):
        layout = self.layout
        layout.operator(NERFDEFORM_OT_composite_with_scene.bl_idname, icon="NODE_COMPOSITING")
        mesh_scene = mesh_scene_of(context.scene)
        if mesh_scene is not None:
            layout.label(text=f"Meshes: {mesh_scene.name} ({mesh_scene.render.engine.title()})", icon="SCENE_DATA")


class NERFDEFORM_PT_train(_StagePanel, bpy.types.Panel):
    bl_label = "Train"
    bl_idname = "NERFDEFORM_PT_train"

    def draw(self, context):
        t = context.scene.nerf_deform_training
        col = self.layout.column()
        for name in ("data", "run_folder", "seconds", "steps", "device", "downscale", "masks", "resume"):
            col.prop(t, name)
        op = col.operator(NERFDEFORM_OT_train_nerf.bl_idname, icon="PLAY")
        for name in ("data", "run_folder", "seconds", "steps", "device", "downscale", "masks", "resume"):
            setattr(op, name, getattr(t, name))
        training_preview.draw_in_panel(col, context)
        box = self.layout.box()
        box.label(text="Import Photos (time budget, steps and device above)")
        box.prop(t, "photos")
        op = box.operator("nerf_deform.import_photos", icon="IMAGE_DATA")
        for name in ("photos", "seconds", "steps", "device", "downscale"):
            setattr(op, name, getattr(t, name))


class NERFDEFORM_PT_capture(_StagePanel, bpy.types.Panel):
    bl_label = "Capture Dataset"
    bl_idname = "NERFDEFORM_PT_capture"

    def draw(self, context):
        s = context.scene.nerf_deform_capture
        col = self.layout.column()
        col.prop(s, "output")
        col.prop(s, "count")
        col.prop(s, "test_count")
        col.prop(s, "resolution")
        col.prop(s, "radius")
        col.prop(s, "lens")
        col.prop(s, "seed")
        row = col.row()
        row.active = not s.use_min_elevation
        row.prop(s, "hemisphere")
        row = col.row(align=True)
        row.prop(s, "use_min_elevation", text="")
        sub = row.row()
        sub.active = s.use_min_elevation
        sub.prop(s, "min_elevation")
        col.prop(s, "engine")
        sub = col.row()
        sub.active = s.engine == "CYCLES"
        sub.prop(s, "samples")
        col.prop(s, "transparent")
        col.prop(s, "selected_only")
        selected = len(renderable(context.selected_objects))
        col.label(
            text=f"{selected} selected object{'s' if selected != 1 else ''} to capture"
            if selected
            else "Select the objects to capture",
            icon="RESTRICT_SELECT_OFF",
        )
        op = col.operator(NERFDEFORM_OT_capture_dataset.bl_idname, icon="RENDER_STILL")
        for name in CAPTURE_OPTIONS:
            setattr(op, name, getattr(s, name))


# Registered after the main panel (their parent); Blender lists sub-panels in registration order.
_classes = (NERFDEFORM_PT_composite, NERFDEFORM_PT_train, NERFDEFORM_PT_capture)
register, unregister = bpy.utils.register_classes_factory(_classes)
