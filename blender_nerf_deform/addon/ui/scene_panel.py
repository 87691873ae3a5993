"""The "NeRF Objects" sub-panel: every NeRF of the scene at a glance.

Per NeRF object: whether the viewport and F12 show it (the same tests the viewport's and the
render's depsgraphs apply: the object's eye in the view layer, its monitor, its camera, and its
collections), its edit regions, its mesh and its cage (tetrahedra, one piece per region), and
what is out of date (regions moved since the mesh was extracted, a cage older than its mesh).
`nerf_status` computes it without drawing, so scripts and tests read the same facts the panel
shows.
"""

from __future__ import annotations

import bpy

from ..data.cage_store import EMBED_COUNT_KEY, EMBED_TET_KEY, has_cage, stored_tet_count
from ..data.properties import Role
from ..edit.regions import edit_regions_of, extracted_regions, regions_of, same_regions


def scene_nerfs(scene: bpy.types.Scene) -> list[bpy.types.Object]:
    """The scene's NeRF objects (in a collection of this scene), by name."""
    return sorted((o for o in scene.objects if o.nerf_deform.role == Role.NERF), key=lambda o: o.name)


def _in_render(obj: bpy.types.Object, view_layer: bpy.types.ViewLayer) -> bool:
    """Whether F12 renders `obj`: not hide_render, and in a collection that renders in this view layer."""
    if obj.hide_render:
        return False

    def renders(layer_collection) -> bool:
        return any(
            not child.exclude
            and not child.collection.hide_render
            and (obj.name in child.collection.objects or renders(child))
            for child in layer_collection.children
        )

    root = view_layer.layer_collection
    return obj.name in root.collection.objects or renders(root)


def nerf_status(nerf: bpy.types.Object, view_layer: bpy.types.ViewLayer) -> dict:
    """What the panel shows for one NeRF object (plain values)."""
    s = nerf.nerf_deform
    surface = s.surface if s.surface is not None and s.surface.users_collection else None
    cage = s.cage if s.cage is not None and s.cage.users_collection else None
    regions = regions_of(nerf)
    status = {
        "name": nerf.name,
        "in_viewport": bool(nerf.visible_get(view_layer=view_layer)),
        "in_render": _in_render(nerf, view_layer),
        "regions": [r.name for r in regions],
        "surface_vertices": len(surface.data.vertices) if surface is not None and surface.type == "MESH" else 0,
        "cage_tets": 0,
        "cage_pieces": 0,
        "stale": [],
    }
    if cage is not None and cage.type == "MESH" and has_cage(cage.data):
        status["cage_tets"] = stored_tet_count(cage.data) or 0
        status["cage_pieces"] = max(1, len(extracted_regions(surface))) if surface is not None else 1
        if not status["cage_tets"]:
            status["stale"].append("the stored cage is damaged: Build Cage again")
    if surface is not None and not same_regions(extracted_regions(surface), edit_regions_of(nerf)):
        status["stale"].append("regions changed since the mesh was extracted: Extract Mesh again")
    if (
        surface is not None
        and status["cage_tets"]
        and (EMBED_TET_KEY not in surface.data or surface.data.get(EMBED_COUNT_KEY) != len(surface.data.vertices))
    ):
        status["stale"].append("the mesh changed since the cage was built: Build Cage again")
    if surface is None and cage is None:
        status["stale"].append("no mesh yet: Extract Mesh, then Build Cage")
    elif status["cage_tets"] == 0 and not status["stale"]:
        status["stale"].append("no cage yet: Build Cage")
    return status


class NERFDEFORM_OT_activate_nerf(bpy.types.Operator):
    """Make this NeRF object the active one (select it)"""

    bl_idname = "nerf_deform.activate_nerf"
    bl_label = "Activate NeRF"
    bl_options = {"REGISTER", "UNDO"}

    name: bpy.props.StringProperty()

    def execute(self, context):
        obj = context.scene.objects.get(self.name)
        if obj is None or obj.nerf_deform.role != Role.NERF:
            self.report({"ERROR"}, f"Activate NeRF: no NeRF object {self.name!r} in this scene")
            return {"CANCELLED"}
        if not obj.visible_get():
            self.report({"WARNING"}, f"{obj.name} is hidden in the viewport: made active, but not selected")
        else:
            for other in context.selected_objects:
                other.select_set(False)
            obj.select_set(True)
        context.view_layer.objects.active = obj
        return {"FINISHED"}


class NERFDEFORM_PT_scene_nerfs(bpy.types.Panel):
    bl_label = "NeRF Objects"
    bl_idname = "NERFDEFORM_PT_scene_nerfs"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "NeRF Deform"
    bl_parent_id = "NERFDEFORM_PT_main"

    @classmethod
    def poll(cls, context):
        return bool(scene_nerfs(context.scene))

    def draw(self, context):
        active = context.active_object
        for nerf in scene_nerfs(context.scene):
            st = nerf_status(nerf, context.view_layer)
            box = self.layout.box()
            row = box.row(align=True)
            op = row.operator(
                NERFDEFORM_OT_activate_nerf.bl_idname,
                text=nerf.name,
                icon="OUTLINER_OB_EMPTY",
                depress=nerf == active,
                emboss=True,
            )
            op.name = nerf.name
            row.label(text="", icon="HIDE_OFF" if st["in_viewport"] else "HIDE_ON")
            row.prop(nerf, "hide_viewport", text="", emboss=False)
            row.prop(nerf, "hide_render", text="", emboss=False)
            col = box.column(align=True)
            col.label(
                text=f"Viewport: {'shown' if st['in_viewport'] else 'hidden'}   "
                f"Render: {'shown' if st['in_render'] else 'hidden'}"
            )
            col.label(text=f"Regions: {', '.join(st['regions'])}" if st["regions"] else "Regions: none (the whole box)")
            mesh = f"{st['surface_vertices']:,} vertices" if st["surface_vertices"] else "none"
            cage = (
                f"{st['cage_tets']:,} tets, {st['cage_pieces']} piece{'s' if st['cage_pieces'] != 1 else ''}"
                if st["cage_tets"]
                else "none"
            )
            col.label(text=f"Mesh: {mesh}   Cage: {cage}")
            for line in st["stale"]:
                col.label(text=line, icon="ERROR" if "changed" in line else "INFO")


_classes = (NERFDEFORM_OT_activate_nerf, NERFDEFORM_PT_scene_nerfs)
register, unregister = bpy.utils.register_classes_factory(_classes)
