"""What the add-on stores on objects: `Object.nerf_deform`.

One NeRF object (an Empty drawn as the NeRF's box) owns everything: its
extracted surface mesh and its cage are children with identity local
transforms, so their local coordinates are the NeRF's world frame (the frame
of its transforms.json and of every engine array). Handles are Empties whose
region is a vertex group of the surface mesh; a handle's pose is its matrix in
the NeRF's frame, compared with the rest matrix recorded when it was made, so
parenting a handle to a bone, constraints and drivers all just work.
"""

import bpy
from bpy.props import EnumProperty, FloatProperty, FloatVectorProperty, IntProperty, PointerProperty, StringProperty

ROLES = (
    ("NONE", "None", "Not part of a NeRF"),
    ("NERF", "NeRF", "A NeRF placed in the scene (an Empty drawn as its bounding box)"),
    ("SURFACE", "Surface", "Mesh extracted from the NeRF; the proxy for selections and the live preview"),
    ("CAGE", "Cage", "Tetrahedral cage of the NeRF, built once; modifiers on it can drive the deformation"),
    ("HANDLE", "Handle", "An Empty that moves a region of the surface"),
)

DEFORMATION_MODES = (
    ("ARAP", "ARAP from Handles", "Handles move their regions; pinned regions stay; everything else follows as rigidly as possible"),
    ("AFFINE", "Affine Regions", "Each handle's region moves exactly by its handle's transform; the rest stays"),
    ("MODIFIERS", "Cage Modifiers", "The cage object's modifiers (Armature, Lattice, ...) deform the NeRF"),
)

PIN_GROUP = "NeRF Pin"
# Blender 5.0 warns when a "//" path is stored in a property not declared blend-relative;
# older versions (4.2-4.4) do not know the option.
_BLEND_RELATIVE_PATH = (
    {"PATH_SUPPORTS_BLEND_RELATIVE"} if "is_path_supports_blend_relative" in bpy.types.Property.bl_rna.properties else set()
)
IDENTITY = (1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0)


class NERFDEFORM_ObjectSettings(bpy.types.PropertyGroup):
    role: EnumProperty(name="Role", items=ROLES, default="NONE")

    # On the NeRF object.
    checkpoint: StringProperty(
        name="Checkpoint", subtype="FILE_PATH", description="NeRF checkpoint (nerf.ckpt), relative to the .blend when saved",
        options=_BLEND_RELATIVE_PATH,
    )
    aabb: FloatVectorProperty(name="Bounds", size=6, description="NeRF's scene box in its own frame: min x y z, max x y z")
    deformation_mode: EnumProperty(name="Deformation", items=DEFORMATION_MODES, default="ARAP")
    surface: PointerProperty(name="Surface", type=bpy.types.Object, description="Extracted mesh of this NeRF")
    cage: PointerProperty(name="Cage", type=bpy.types.Object, description="Tetrahedral cage of this NeRF")
    threshold: FloatProperty(name="Density Threshold", default=10.0, min=0.0, description="Density at the extracted surface")
    resolution: IntProperty(name="Resolution", default=256, min=16, max=1024, description="Grid cells per axis for extraction")
    min_volume: FloatProperty(
        name="Min Component Volume",
        default=0.0,
        min=0.0,
        description="Connected pieces smaller than this are dropped as floaters (0: automatic)",
    )

    # On handles.
    nerf: PointerProperty(name="NeRF", type=bpy.types.Object, description="The NeRF this handle deforms")
    region: StringProperty(name="Region", description="Vertex group of the surface mesh this handle moves")
    rest_matrix: FloatVectorProperty(name="Rest Matrix", size=16, default=IDENTITY, description="Handle's matrix in the NeRF's frame when made (row-major)")


def settings(obj: bpy.types.Object) -> NERFDEFORM_ObjectSettings:
    return obj.nerf_deform


def owning_nerf(obj: bpy.types.Object | None) -> bpy.types.Object | None:
    """The NeRF object `obj` belongs to (itself, its parent for surface/cage, its owner for handles)."""
    if obj is None:
        return None
    s = obj.nerf_deform
    if s.role == "NERF":
        return obj
    if s.role == "HANDLE":
        return s.nerf
    if s.role in ("SURFACE", "CAGE"):
        parent = obj.parent
        return parent if parent is not None and parent.nerf_deform.role == "NERF" else None
    return None


def select_only(context, obj: bpy.types.Object) -> None:
    """Make `obj` the one selected and active object (ready for its gizmos)."""
    for other in context.selected_objects:
        other.select_set(False)
    obj.select_set(True)
    context.view_layer.objects.active = obj


def handles_of(nerf: bpy.types.Object) -> list[bpy.types.Object]:
    """The handles of a NeRF, in a stable order (by name), so solves are deterministic."""
    return sorted(
        (o for o in bpy.data.objects if o.nerf_deform.role == "HANDLE" and o.nerf_deform.nerf == nerf),
        key=lambda o: o.name,
    )


def register():
    bpy.utils.register_class(NERFDEFORM_ObjectSettings)
    bpy.types.Object.nerf_deform = PointerProperty(type=NERFDEFORM_ObjectSettings)


def unregister():
    del bpy.types.Object.nerf_deform
    bpy.utils.unregister_class(NERFDEFORM_ObjectSettings)
