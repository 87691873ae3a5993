"""Build Cage: the NeRF's tetrahedral cage, built once from its extracted mesh and kept in the .blend.

A mesh extracted in several edit regions has one part per region (its "NeRF Part" attribute):
the worker builds one cage per part, in the one cage object (no tet joins two parts, so a handle
on one object moves that object alone), and pins each part at its own cut. The cage's vertices
get the "NeRF Part" attribute too (which region's object each cage vertex wraps)."""

from __future__ import annotations

import bpy

import numpy as np

from ...engine.service.requests import CageRequest
from ..data.cage_store import cage_vertex_parts, separate_regions, store_cage, store_cut_pins, store_embedding
from ..data.mesh_attributes import cut_flags, part_labels, set_part_labels
from ..data.paths import checkpoint_path
from ..data.properties import (
    PREVIEW_KEY,
    OnNeRF,
    Role,
    alive,
    alive_object,
    forget_deleted,
    keep_out_of_renders,
    owning_nerf,
)
from ..worker.jobs import WorkerOperator
from .regions import edit_regions_of, extracted_regions, same_regions


def surface_arrays(surface: bpy.types.Object) -> dict[str, np.ndarray]:
    """Rest vertices and triangles of a mesh (its own vertices: the preview shape key aside)."""
    mesh = surface.data
    co = np.empty(3 * len(mesh.vertices), dtype=np.float32)
    mesh.vertices.foreach_get("co", co)
    mesh.calc_loop_triangles()
    tris = np.empty(3 * len(mesh.loop_triangles), dtype=np.int32)
    mesh.loop_triangles.foreach_get("vertices", tris)
    return {"vertices": co.reshape(-1, 3).astype(np.float64), "faces": tris.reshape(-1, 3)}


class NERFDEFORM_OT_build_cage(WorkerOperator, OnNeRF, bpy.types.Operator):
    """Build the NeRF's tetrahedral cage around its extracted mesh (once; every frame deforms this cage)"""

    bl_idname = "nerf_deform.build_cage"
    bl_label = "Build Cage"
    bl_options = {"REGISTER", "UNDO"}

    refine_selected: bpy.props.BoolProperty(
        name="Refine Selected",
        description="Make the cage finer around the extracted mesh's selected vertices (select the part that "
        "will stretch in Edit Mode first): a coarse cage bends a strong smooth stretch piecewise and smears it",
        default=False,
    )
    refine_edge: bpy.props.FloatProperty(
        name="Refine Edge",
        description="Longest tet edge around the selection (0: half the cage's typical edge)",
        default=0.0,
        min=0.0,
        subtype="DISTANCE",
    )

    def request(self, context):
        forget_deleted()  # a cage or mesh deleted since the last update is gone
        nerf = owning_nerf(context.active_object)
        surface = alive(nerf.nerf_deform.surface)
        if surface is None:
            raise ValueError(f"{nerf.name} has no extracted mesh yet: run Extract Mesh first")
        if surface.mode == "EDIT":
            raise ValueError(f"leave Edit Mode on {surface.name} first")
        arrays = surface_arrays(surface)
        if len(arrays["faces"]) == 0:
            raise ValueError(f"{surface.name} has no faces to build a cage around")
        self._nerf = nerf
        # The cut is where extraction closed the surface at the region (or the NeRF's box).
        cut = cut_flags(surface.data)
        if cut is not None and cut.any():
            arrays["cut"] = cut.astype(np.uint8)
        # One cage per edit region's object (the part each vertex was extracted in).
        part = part_labels(surface.data)
        self._part = part
        if part is not None and len(np.unique(part)) > 1:
            arrays["part"] = part
        if self.refine_selected:
            selected = np.zeros(len(surface.data.vertices), dtype=bool)
            surface.data.vertices.foreach_get("select", selected)
            if not selected.any():
                raise ValueError(
                    f"Refine Selected: no vertex of {surface.name} is selected; select the part that "
                    "will stretch in Edit Mode, or turn Refine Selected off"
                )
            arrays["refine"] = selected.astype(np.uint8)
        self._note = ""
        context.view_layer.update()
        extracted = extracted_regions(surface)
        try:
            changed = not same_regions(edit_regions_of(nerf), extracted)
        except ValueError:  # a region has no box now
            changed = True
        if changed:
            self._note = (
                f"the edit regions changed since {surface.name} was extracted (it was extracted in "
                f"{len(extracted) or 'no'} region{'' if len(extracted) == 1 else 's'}): the cage wraps the mesh "
                "as extracted (delete the cage and handles, and Extract Mesh again, to use the regions now)"
            )
        # With the checkpoint and the extraction threshold the worker widens the margin where the
        # NeRF's density is still soft, as the `cage` command does (one stage function for both).
        # (A NeRF object without a checkpoint, made by a script, gets the cage at the plain margin.)
        request = CageRequest(
            arrays["vertices"],
            arrays["faces"],
            arrays.get("cut"),
            arrays.get("part"),
            arrays.get("refine"),
            checkpoint=checkpoint_path(nerf) if nerf.nerf_deform.checkpoint else None,
            threshold=nerf.nerf_deform.threshold,
            pin_cut=nerf.nerf_deform.pin_cut,
            refine_edge=float(self.refine_edge) if self.refine_selected and self.refine_edge > 0 else None,
        )
        return "cage", *request.to_wire()

    def apply(self, context, result, arrays):
        nerf = self._nerf
        # From the UI the worker builds while the artist works on: the NeRF or its mesh may have
        # been deleted or edited since the request.
        surface = alive(nerf.nerf_deform.surface) if alive_object(nerf) else None
        if surface is None or len(surface.data.vertices) != len(arrays["tet_ids"]):
            return self._fail(
                ValueError(
                    "the NeRF or its extracted mesh was deleted or edited while the cage was built: "
                    "run Build Cage again"
                )
            )
        s = nerf.nerf_deform
        cage = alive(s.cage)
        if cage is None:
            cage = bpy.data.objects.new(f"{nerf.name} Cage", bpy.data.meshes.new(f"{nerf.name} Cage"))
            for collection in nerf.users_collection:
                collection.objects.link(cage)
            cage.parent = nerf
            cage.nerf_deform.role = Role.CAGE
            cage.display_type = "WIRE"
            keep_out_of_renders(cage)
            s.cage = cage
        store_cage(cage.data, arrays["vertices"], arrays["tets"])
        store_embedding(surface.data, arrays["tet_ids"], arrays["weights"])
        pins = np.asarray(arrays.get("pinned_vertices", np.zeros(0, np.int64)), dtype=np.int64)
        store_cut_pins(cage, pins)
        cage_part = None
        if self._part is not None and len(self._part) == len(surface.data.vertices):
            cage_part = cage_vertex_parts(len(arrays["vertices"]), arrays["tets"], arrays["tet_ids"], self._part)
        set_part_labels(cage.data, cage_part)
        # A rebuilt cage starts undeformed: drop the previous preview.
        keys = surface.data.shape_keys
        if keys is not None and (key := keys.key_blocks.get(PREVIEW_KEY)) is not None:
            surface.shape_key_remove(key)
        self.report(
            {"INFO"},
            f"{cage.name}: {result['n_tets']} tets, {result['n_vertices']} vertices, margin {result['margin']:.3g} "
            f"(clearance {result['clearance']:.3g})",
        )
        if result.get("refined"):
            r = result["refined"]
            self.report(
                {"INFO"},
                f"{cage.name}: refined around the selection to edges of {r['edge']:.3g} "
                f"({r['tets_before']} -> {result['n_tets']} tets)",
            )
        n_cut, n_pinned = result.get("n_cut", 0), result.get("n_pinned", 0)
        if n_pinned and cage_part is not None and len(np.unique(cage_part)) > 1:
            per_part = ", ".join(
                f"{int(np.count_nonzero(cage_part[pins] == i))} in part {i + 1}" for i in np.unique(cage_part)
            )
            self.report(
                {"INFO"},
                f"{cage.name}: one cage per edit region ({len(np.unique(cage_part))}); {n_pinned} cage "
                f"vertices pinned at the cuts ({per_part}; {n_cut} cut mesh vertices)",
            )
        elif n_pinned:
            self.report(
                {"INFO"}, f"{cage.name}: {n_pinned} cage vertices pinned at the cut ({n_cut} cut mesh vertices)"
            )
        elif n_cut and not s.pin_cut:
            self.report({"INFO"}, f"{cage.name}: Pin Cut is off: the cut ({n_cut} mesh vertices) moves with the cage")
        if self._note:
            self.report({"WARNING"}, f"{cage.name}: {self._note}")
        for line in result.get("warnings", []):
            self.report({"WARNING"}, f"{cage.name}: {line}")
        for level, line in separate_regions(nerf):  # handles made before this cage
            self.report({level}, line)
        return {"FINISHED"}


_classes = (NERFDEFORM_OT_build_cage,)
register, unregister = bpy.utils.register_classes_factory(_classes)
