"""What the add-on stores on objects: `Object.nerf_deform`.

One NeRF object (an Empty drawn as the NeRF's box) owns everything: its
extracted surface mesh and its cage are children with identity local
transforms, so their local coordinates are the NeRF's world frame (the frame
of its transforms.json and of every engine array). Handles are Empties whose
region is a vertex group of the surface mesh; a handle's pose is its matrix in
the NeRF's frame, compared with the rest matrix recorded when it was made, so
parenting a handle to a bone, constraints and drivers all just work. Edit
regions are cube Empties parented to the NeRF (edit/regions.py): boxes that
limit extraction and the cage, one object (and one cage piece) each; a NeRF
owns every REGION Empty whose `nerf` is it, and `edit_region` is the one
added last.

A deleted part is gone. Deleting an object in the viewport or the outliner
only unlinks it from its collections; our pointers (the NeRF's `surface`,
`cage` and `edit_region`, a handle's or region's `nerf`) would keep it alive in the file, rendering and
blocking Extract Mesh while no one sees it. An object in no collection counts
as deleted: every reader here skips it, and `forget_deleted` (run after
every change of collections, on load, undo, redo and save) clears the pointers
to it, so it is not saved either.
"""

from enum import StrEnum

import bpy
from bpy.app.handlers import persistent
from bpy.props import (
    BoolProperty,
    EnumProperty,
    FloatProperty,
    FloatVectorProperty,
    IntProperty,
    PointerProperty,
    StringProperty,
)

import numpy as np

from ...engine.nerf.substeps import FINAL_SUBSTEPS, MAX_SUBSTEPS
from .guards import guarded


class CageDataError(ValueError):
    """Stored cage or embedding data is missing or no longer matches its mesh (data/cage_store.py reads it)."""


# The surface mesh's shape key that the live preview (deform/live_preview.py) writes the deformation into.
PREVIEW_KEY = "NeRF Deform"
# The NeRF Deform render engine's id (render/render_engine.py); Load NeRF makes it the scene's engine,
# and saved .blend files name it in scene.render.engine.
RENDER_ENGINE_ID = "NERF_DEFORM"


class Role(StrEnum):
    """What an object is to the add-on: `Object.nerf_deform.role`, which reads as the role's string (a
    role compares equal to it). A .blend file stores a role as its position in this order (ROLES, the
    EnumProperty's items), and scripts use the strings: add roles at the end, never reorder, rename or
    remove one."""

    NONE = "NONE"
    NERF = "NERF"
    SURFACE = "SURFACE"
    CAGE = "CAGE"
    HANDLE = "HANDLE"
    REGION = "REGION"


_ROLE_LABELS = {
    Role.NONE: ("None", "Not part of a NeRF"),
    Role.NERF: ("NeRF", "A NeRF placed in the scene (an Empty drawn as its bounding box)"),
    Role.SURFACE: ("Surface", "Mesh extracted from the NeRF; the proxy for selections and the live preview"),
    Role.CAGE: ("Cage", "Tetrahedral cage of the NeRF, built once; modifiers on it can drive the deformation"),
    Role.HANDLE: ("Handle", "An Empty that moves a region of the surface"),
    Role.REGION: ("Edit Region", "A box Empty that limits extraction and the cage to the object being edited"),
}
ROLES = tuple((role.value, *_ROLE_LABELS[role]) for role in Role)  # the EnumProperty's items

DEFORMATION_MODES = (
    (
        "ARAP",
        "ARAP from Handles",
        "Handles move their regions; pinned regions stay; everything else follows as rigidly as possible",
    ),
    ("AFFINE", "Affine Regions", "Each handle's region moves exactly by its handle's transform; the rest stays"),
    ("MODIFIERS", "Cage Modifiers", "The cage object's modifiers (Armature, Lattice, ...) deform the NeRF"),
)

# Bake Volume (export/bake_volume.py): the NeRF's settings, which the panel hands to the operator.
VOLUME_EXTENTS = (
    ("NERF", "NeRF Box", "The NeRF's whole box (an unbounded NeRF's inner box)"),
    ("CAGE", "Posed Cage", "The box of the cage as posed at each frame: the edited object"),
    ("REGION", "Edit Region", "An edit region's box (the one named, or the NeRF's only one)"),
)
VOLUME_FRAMES = (
    ("CURRENT", "Current Frame", "Bake the frame shown"),
    ("RANGE", "Frame Range", "Bake each frame of the scene's range into a sequence the Volume object plays"),
)
VOLUME_SHADINGS = (
    (
        "EMISSION",
        "Emission-Absorption",
        "As the NeRF renders: it emits its colour and hides what is behind it; scene lights do not light it",
    ),
    (
        "LIT",
        "Lit",
        "It scatters the scene's light (its colour as albedo) and casts shadows: integration over faithfulness",
    ),
)

PIN_GROUP = "NeRF Pin"
# Blender 5.0 warns when a "//" path is stored in a property not declared blend-relative;
# older versions (4.2-4.4) do not know the option.
_BLEND_RELATIVE_PATH = (
    {"PATH_SUPPORTS_BLEND_RELATIVE"}
    if "is_path_supports_blend_relative" in bpy.types.Property.bl_rna.properties
    else set()
)
IDENTITY = (1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0)


class NERFDEFORM_ObjectSettings(bpy.types.PropertyGroup):
    role: EnumProperty(name="Role", items=ROLES, default=Role.NONE.value)

    # On the NeRF object.
    checkpoint: StringProperty(
        name="Checkpoint",
        subtype="FILE_PATH",
        description="NeRF checkpoint (nerf.ckpt), relative to the .blend when saved",
        options=_BLEND_RELATIVE_PATH,
    )
    aabb: FloatVectorProperty(
        name="Bounds", size=6, description="NeRF's scene box in its own frame: min x y z, max x y z"
    )
    deformation_mode: EnumProperty(name="Deformation", items=DEFORMATION_MODES, default="ARAP")
    render_substeps: IntProperty(
        name="Render Substeps",
        default=FINAL_SUBSTEPS,
        min=1,
        max=MAX_SUBSTEPS,
        description="Samples per step of this NeRF's march in renders (F12, Render Animation, blender -b, and "
        "the last image of the viewport and the preview render): more is sharper and slower",
    )
    surface: PointerProperty(name="Surface", type=bpy.types.Object, description="Extracted mesh of this NeRF")
    cage: PointerProperty(name="Cage", type=bpy.types.Object, description="Tetrahedral cage of this NeRF")
    threshold: FloatProperty(
        name="Density Threshold", default=10.0, min=0.0, description="Density at the extracted surface"
    )
    resolution: IntProperty(
        name="Resolution", default=256, min=16, max=1024, description="Grid cells per axis for extraction"
    )
    min_volume: FloatProperty(
        name="Min Component Volume",
        default=0.0,
        min=0.0,
        description="Connected pieces smaller than this are dropped as floaters (0: automatic)",
    )
    # No `poll=` here (nor on any property of the add-on): a PointerProperty with a Python poll
    # callback makes the bpy module of Blender 4.2 LTS segfault when its process exits (even after
    # unregister) and that of 4.5 LTS hang there while it is registered (test_extension). Only the
    # add-on sets this pointer (Add Edit Region: a cube Empty); no panel offers it as a picker.
    edit_region: PointerProperty(
        name="Edit Region",
        type=bpy.types.Object,
        description="The edit region added last (a NeRF's regions are all the REGION Empties of it; "
        "none: the whole box)",
    )
    pick_object: BoolProperty(
        name="Pick at 3D Cursor",
        default=False,
        description="Extract only the part of the NeRF connected to the 3D cursor (put the cursor on the object)",
    )
    pin_cut: BoolProperty(
        name="Pin Cut",
        default=True,
        description="The cage is pinned where the edit region cut the scene, so the object stays attached; "
        "off lets the cut move with the rest",
    )

    volume_folder: StringProperty(
        name="Volume Folder",
        subtype="DIR_PATH",
        default="//nerf_volume/",
        options=_BLEND_RELATIVE_PATH,
        description="Where Bake Volume writes its .vdb files (// is the .blend's folder)",
    )
    volume_resolution: IntProperty(
        name="Volume Resolution",
        default=256,
        min=1,
        max=2048,
        soft_min=16,
        soft_max=512,
        description="Voxels along the longest side of the baked box",
    )
    volume_extent: EnumProperty(name="Volume Box", items=VOLUME_EXTENTS, default="NERF")
    volume_frames: EnumProperty(name="Volume Frames", items=VOLUME_FRAMES, default="CURRENT")
    volume_shading: EnumProperty(name="Volume Material", items=VOLUME_SHADINGS, default="EMISSION")

    # On handles and edit regions.
    nerf: PointerProperty(
        name="NeRF", type=bpy.types.Object, description="The NeRF this handle deforms or this region limits"
    )
    region: StringProperty(name="Region", description="Vertex group of the surface mesh this handle moves")
    rest_matrix: FloatVectorProperty(
        name="Rest Matrix",
        size=16,
        default=IDENTITY,
        description="Handle's matrix in the NeRF's frame when made (row-major)",
    )


def settings(obj: bpy.types.Object) -> NERFDEFORM_ObjectSettings:
    return obj.nerf_deform


class PlacementError(CageDataError):
    """The NeRF object's transform cannot place the NeRF (a zero scale). A CageDataError, so that
    whatever reports a cage that cannot be used (the live preview, renders) reports this too."""


def is_deleted(obj: bpy.types.Object | None) -> bool:
    """Whether `obj` was deleted by the artist (unlinked from every collection) though a pointer still holds it."""
    return obj is not None and not obj.users_collection


def alive(obj: bpy.types.Object | None) -> bpy.types.Object | None:
    """`obj`, or None when it is missing or deleted (a pointer of ours to a deleted part)."""
    return None if obj is None or is_deleted(obj) else obj


def alive_object(obj: bpy.types.Object) -> bool:
    """Whether a Python reference still names an object in the file, not deleted (an operator's
    NeRF may be removed while its worker job runs)."""
    try:
        return not is_deleted(obj)
    except ReferenceError:  # removed from bpy.data
        return False


def to_nerf_frame(nerf: bpy.types.Object, matrix_world=None):
    """The inverse of the NeRF object's world matrix (or of `matrix_world`, its evaluated one),
    which takes world coordinates into the NeRF's frame; a clear error naming the object when its
    scale is zero (a Matrix)."""
    matrix = nerf.matrix_world if matrix_world is None else matrix_world
    try:
        return matrix.inverted()
    except ValueError:
        # In float64: Matrix.to_scale squares float32 values, which shows a scale of 1e-20 as 0.
        scale = ", ".join(f"{x:.3g}" for x in np.linalg.norm(np.array(matrix, dtype=np.float64)[:3, :3], axis=0))
        raise PlacementError(
            f"NeRF object '{nerf.name}' has a zero scale ({scale}): the NeRF cannot be placed; "
            "give it a non-zero scale (Object Properties > Transform > Scale)"
        ) from None


RAY_VISIBILITY = (
    "visible_camera",
    "visible_diffuse",
    "visible_glossy",
    "visible_transmission",
    "visible_volume_scatter",
    "visible_shadow",
)


def keep_out_of_renders(obj: bpy.types.Object) -> None:
    """Hide a NeRF part (the cage) from every render engine's image while keeping it in render
    depsgraphs: F12 reads the cage's modifiers from the render's own depsgraph, which leaves out
    `hide_render` objects (their modifiers would silently not apply). Ray visibility off instead."""
    obj.hide_render = False
    for flag in RAY_VISIBILITY:
        setattr(obj, flag, False)


def owning_nerf(obj: bpy.types.Object | None) -> bpy.types.Object | None:
    """The NeRF object `obj` belongs to (itself, its parent for surface/cage, its owner for handles and regions);
    None for a deleted object or one whose NeRF was deleted."""
    if obj is None or is_deleted(obj):
        return None
    s = obj.nerf_deform
    if s.role == Role.NERF:
        return obj
    if s.role in (Role.HANDLE, Role.REGION):
        return alive(s.nerf)
    if s.role in (Role.SURFACE, Role.CAGE):
        parent = obj.parent
        return alive(parent) if parent is not None and parent.nerf_deform.role == Role.NERF else None
    return None


class OnNeRF:
    """Operator mixin: runs on the active object's NeRF (the NeRF object itself, its mesh, cage,
    handles or regions); the poll says so otherwise."""

    @classmethod
    def poll(cls, context):
        if owning_nerf(context.active_object) is None:
            cls.poll_message_set("Select a NeRF object, or its mesh, cage or handles")
            return False
        return True


def select_only(context, obj: bpy.types.Object) -> None:
    """Make `obj` the one selected and active object (ready for its gizmos)."""
    for other in context.selected_objects:
        other.select_set(False)
    if context.view_layer.objects.get(obj.name) == obj:  # not in an excluded or unlinked collection
        obj.select_set(True)
        context.view_layer.objects.active = obj


def handles_of(nerf: bpy.types.Object, *, with_regions: bool = True) -> list[bpy.types.Object]:
    """The handles of a NeRF, in a stable order (by name), so solves are deterministic; deleted
    ones left out. A handle's region is a vertex group of the NeRF's extracted mesh: once that
    mesh is deleted the handles move nothing, and only `with_regions=False` lists them."""
    if with_regions and alive(nerf.nerf_deform.surface) is None:
        return []
    return sorted(
        (
            o
            for o in bpy.data.objects
            if o.nerf_deform.role == Role.HANDLE and o.nerf_deform.nerf == nerf and not is_deleted(o)
        ),
        key=lambda o: o.name,
    )


def forget_deleted() -> int:
    """Clear our pointers to deleted objects (module docstring); returns how many were cleared.
    A NeRF whose cage is gone renders at rest, and so its mesh's preview goes back to rest."""
    cleared = 0
    for obj in bpy.data.objects:
        s = obj.nerf_deform
        if obj.library is not None or s.role not in (Role.NERF, Role.HANDLE, Role.REGION):
            continue
        for name in ("surface", "cage", "edit_region") if s.role == Role.NERF else ("nerf",):
            if is_deleted(getattr(s, name)):
                setattr(s, name, None)
                cleared += 1
                surface = alive(s.surface) if name == "cage" else None
                keys = surface.data.shape_keys if surface is not None else None
                if keys is not None and (key := keys.key_blocks.get(PREVIEW_KEY)) is not None:
                    surface.shape_key_remove(key)
    return cleared


@persistent
def _forget_deleted_on_depsgraph_update(scene, depsgraph):
    # Objects are deleted by unlinking them: the collections (or the scene) change.
    if depsgraph.id_type_updated("COLLECTION") or depsgraph.id_type_updated("SCENE"):
        forget_deleted()


@persistent
def _forget_deleted(*_args):
    forget_deleted()


def _handlers():
    h = bpy.app.handlers
    return (
        (h.depsgraph_update_post, _forget_deleted_on_depsgraph_update),
        (h.load_post, _forget_deleted),
        (h.undo_post, _forget_deleted),
        (h.redo_post, _forget_deleted),
        (h.save_pre, _forget_deleted),
    )


def add_app_handlers(pairs) -> None:
    """Append each (bpy.app.handlers list, function) of `pairs`, once (a module's register), guarded: an
    error nobody foresaw is one console line naming its log file (data/guards.py)."""
    for handlers, fn in pairs:
        if guarded(fn) not in handlers:
            handlers.append(guarded(fn))


def remove_app_handlers(pairs) -> None:
    """Remove what `add_app_handlers` appended (a module's unregister; absent ones are fine)."""
    for handlers, fn in pairs:
        if guarded(fn) in handlers:
            handlers.remove(guarded(fn))


def register():
    bpy.utils.register_class(NERFDEFORM_ObjectSettings)
    bpy.types.Object.nerf_deform = PointerProperty(type=NERFDEFORM_ObjectSettings)
    add_app_handlers(_handlers())


def unregister():
    remove_app_handlers(_handlers())
    del bpy.types.Object.nerf_deform
    bpy.utils.unregister_class(NERFDEFORM_ObjectSettings)
