"""Composite With Scene: the NeRFs and the scene's meshes in one picture, merged by depth.

The NeRF Deform engine renders only the NeRFs; meshes, lights and the world
are Cycles' or EEVEE's. The operator sets up what a compositor artist would
wire by hand, so that F12, Render Animation and `blender -b -a` give the
composite:

- a second scene, "<scene> Meshes", rendered by Cycles (or EEVEE), with the
  NeRF scene as its background set: it renders exactly that scene's objects
  (a set scene's objects render with it), always in step with it, from the
  same camera, with the NeRF scene's world. Nothing of the NeRFs shows there:
  NeRF objects and handles are Empties, the extracted meshes and cages are
  hidden from renders;
- the Depth pass in both scenes: the NeRF Deform engine writes Cycles'
  convention (distance from the camera plane, 1e10 where empty);
- the NeRF scene's compositor (Blender 5's `scene.compositing_node_group`, a
  node group whose Group Output is the picture): its own Render Layers and the
  meshes scene's Render Layers, merged by Z Combine with alpha, so a mesh in
  front of a NeRF hides it, one behind is hidden by it, and the NeRF's soft
  edges and haze blend over what lies behind. Blender renders the meshes scene
  at the NeRF scene's resolution and frame whenever the NeRF scene renders.

A compositor the scene already had is kept (with a fake user) and replaced by
the new one; running the operator again rebuilds its own tree and brings the
meshes scene back in step (camera, resolution, world). Where a NeRF and a mesh
interpenetrate, one depth per pixel decides for the whole NeRF pixel (the
NeRF's expected depth, data/depth_compositing.py), as any depth composite does.
"""

from __future__ import annotations

import bpy
from bpy.props import EnumProperty

from ..data.properties import Role

TREE_NAME = "NeRF Deform Composite"
MESH_SCENE_KEY = "nerf_deform_mesh_scene"  # ID property of the NeRF scene: its meshes scene
TREE_KEY = "nerf_deform_composite"  # ID property marking the node group as ours
ENGINES = (
    ("CYCLES", "Cycles", "Render the scene's meshes with Cycles"),
    ("BLENDER_EEVEE", "EEVEE", "Render the scene's meshes with EEVEE"),
)


def mesh_scene_of(scene: bpy.types.Scene) -> bpy.types.Scene | None:
    """The meshes scene that Composite With Scene made for `scene`, if it still exists."""
    mesh_scene = scene.get(MESH_SCENE_KEY)
    return mesh_scene if isinstance(mesh_scene, bpy.types.Scene) and mesh_scene.background_set == scene else None


def _sync_mesh_scene(scene: bpy.types.Scene, mesh_scene: bpy.types.Scene, engine: str) -> None:
    mesh_scene.background_set = scene
    mesh_scene.camera = scene.camera
    mesh_scene.world = scene.world
    mesh_scene.render.engine = engine
    for name in (
        "resolution_x",
        "resolution_y",
        "resolution_percentage",
        "pixel_aspect_x",
        "pixel_aspect_y",
        "film_transparent",
        "fps",
        "fps_base",
    ):
        setattr(mesh_scene.render, name, getattr(scene.render, name))
    mesh_scene.frame_start, mesh_scene.frame_end = scene.frame_start, scene.frame_end
    mesh_scene.view_layers[0].use_pass_z = True


def _build_tree(
    scene: bpy.types.Scene, view_layer: bpy.types.ViewLayer, mesh_scene: bpy.types.Scene
) -> bpy.types.NodeTree:
    tree = bpy.data.node_groups.new(TREE_NAME, "CompositorNodeTree")
    tree[TREE_KEY] = True
    tree.interface.new_socket(name="Image", in_out="OUTPUT", socket_type="NodeSocketColor")
    nerfs = tree.nodes.new("CompositorNodeRLayers")
    nerfs.label, nerfs.location = "NeRFs", (-400, 200)
    nerfs.scene, nerfs.layer = scene, view_layer.name
    meshes = tree.nodes.new("CompositorNodeRLayers")
    meshes.label, meshes.location = "Meshes", (-400, -200)
    meshes.scene, meshes.layer = mesh_scene, mesh_scene.view_layers[0].name
    combine = tree.nodes.new("CompositorNodeZcombine")
    combine.location = (0, 0)
    combine.inputs["Use Alpha"].default_value = True  # the nearer image over the farther, by its alpha
    output = tree.nodes.new("NodeGroupOutput")
    output.location = (300, 0)
    links = tree.links
    links.new(nerfs.outputs["Image"], combine.inputs["A"])
    links.new(nerfs.outputs["Depth"], combine.inputs["Depth A"])
    links.new(meshes.outputs["Image"], combine.inputs["B"])
    links.new(meshes.outputs["Depth"], combine.inputs["Depth B"])
    links.new(combine.outputs["Result"], output.inputs["Image"])
    return tree


def composite_with_scene(
    scene: bpy.types.Scene, view_layer: bpy.types.ViewLayer | None = None, engine: str = "CYCLES"
) -> tuple[bpy.types.Scene, bpy.types.NodeTree, str]:
    """Set up (or bring back in step) the composite of `scene`'s NeRFs (rendered in `view_layer`,
    default the first) with its meshes.
    Returns (meshes scene, compositor node group, what was done, for the report)."""
    if scene.camera is None:
        raise ValueError(f"scene '{scene.name}' has no active camera: the meshes are rendered from it")
    if scene.background_set is not None and scene.get(MESH_SCENE_KEY) is None and mesh_scene_of(scene.background_set):
        raise ValueError(
            f"scene '{scene.name}' is the meshes scene of '{scene.background_set.name}': "
            f"run Composite With Scene in '{scene.background_set.name}'"
        )
    mesh_scene = mesh_scene_of(scene)
    notes = []
    if mesh_scene is None:
        mesh_scene = bpy.data.scenes.new(f"{scene.name} Meshes")
        scene[MESH_SCENE_KEY] = mesh_scene
    _sync_mesh_scene(scene, mesh_scene, engine)
    for layer in scene.view_layers:
        layer.use_pass_z = True

    old = scene.compositing_node_group
    if old is not None and old.get(TREE_KEY):
        bpy.data.node_groups.remove(old)
    elif old is not None:
        old.use_fake_user = True  # the artist's compositor, kept in the file
        notes.append(f"the compositor '{old.name}' was kept (fake user) and replaced")
    tree = _build_tree(scene, view_layer or scene.view_layers[0], mesh_scene)
    scene.compositing_node_group = tree
    scene.render.use_compositing = True
    return mesh_scene, tree, "; ".join(notes)


class NERFDEFORM_OT_composite_with_scene(bpy.types.Operator):
    """Render the scene's meshes with Cycles or EEVEE from the same camera and merge them with the NeRFs by depth in the compositor"""  # noqa: E501 (the tooltip: one line)

    bl_idname = "nerf_deform.composite_with_scene"
    bl_label = "Composite With Scene"
    bl_options = {"REGISTER", "UNDO"}

    engine: EnumProperty(
        name="Meshes Engine", items=ENGINES, default="CYCLES", description="Render engine of the scene's meshes"
    )

    @classmethod
    def poll(cls, context):
        return context.scene is not None

    def execute(self, context):
        scene = context.scene
        try:
            if not any(o.nerf_deform.role == Role.NERF for o in scene.objects):
                raise ValueError("no NeRF object in the scene: use Load NeRF first")
            mesh_scene, tree, notes = composite_with_scene(scene, context.view_layer, self.engine)
        except (ValueError, TypeError) as error:
            self.report({"ERROR"}, f"Composite With Scene: {error}")
            return {"CANCELLED"}
        engine = dict((key, label) for key, label, _ in ENGINES)[self.engine]
        self.report(
            {"INFO"},
            f"Composite With Scene: the meshes render in scene '{mesh_scene.name}' ({engine}) and "
            f"merge with the NeRFs by depth in the compositor '{tree.name}'" + (f"; {notes}" if notes else ""),
        )
        return {"FINISHED"}


_classes = (NERFDEFORM_OT_composite_with_scene,)
register, unregister = bpy.utils.register_classes_factory(_classes)
