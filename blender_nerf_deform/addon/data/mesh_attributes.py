"""Per-vertex point attributes of the extracted surface and the cage: where an edit region cut the
surface ("NeRF Cut", BOOLEAN) and which edit region each vertex belongs to ("NeRF Part", INT).

Extract Mesh writes them, Build Cage and the handles read them (data layer: docs/ARCHITECTURE.md).
"""

from __future__ import annotations

import bpy

import numpy as np

CUT_ATTRIBUTE = "NeRF Cut"
PART_ATTRIBUTE = "NeRF Part"


def _set_point_values(mesh: bpy.types.Mesh, name: str, data_type: str, dtype, values, what: str) -> None:
    """One value per vertex as the point attribute `name` (replaced; None: removed), checked first,
    so a bad call leaves the old attribute as it was."""
    if values is not None:
        values = np.asarray(values).astype(dtype)
        if values.shape != (len(mesh.vertices),):
            raise ValueError(f"{len(values)} {what} for a mesh of {len(mesh.vertices)} vertices")
    if (old := mesh.attributes.get(name)) is not None:
        mesh.attributes.remove(old)
    if values is not None:
        mesh.attributes.new(name, data_type, "POINT").data.foreach_set("value", values)


def _point_values(mesh: bpy.types.Mesh, name: str, data_type: str, dtype) -> np.ndarray | None:
    """The point attribute `name` (one value per vertex), or None when the mesh has none (made
    elsewhere, or by an older version) or it is not one `data_type` value per vertex."""
    attribute = mesh.attributes.get(name)
    if (
        attribute is None
        or attribute.domain != "POINT"
        or attribute.data_type != data_type
        or len(attribute.data) != len(mesh.vertices)
    ):  # (in Edit Mode the mesh's data is not in sync)
        return None
    values = np.zeros(len(mesh.vertices), dtype=dtype)
    attribute.data.foreach_get("value", values)
    return values


def set_cut_flags(mesh: bpy.types.Mesh, cut: np.ndarray | None) -> None:
    """The cut flags (one per vertex) as the BOOLEAN point attribute CUT_ATTRIBUTE; none: removed."""
    _set_point_values(mesh, CUT_ATTRIBUTE, "BOOLEAN", bool, cut, "cut flags")


def cut_flags(mesh: bpy.types.Mesh) -> np.ndarray | None:
    """The mesh's cut flags (bool per vertex), or None (see `_point_values`)."""
    return _point_values(mesh, CUT_ATTRIBUTE, "BOOLEAN", bool)


def set_part_labels(mesh: bpy.types.Mesh, part: np.ndarray | None) -> None:
    """The part of each vertex (the index of the edit region it was extracted in; also on a cage,
    the part of each cage vertex) as the INT point attribute PART_ATTRIBUTE; none: removed."""
    _set_point_values(mesh, PART_ATTRIBUTE, "INT", np.int32, part, "part labels")


def part_labels(mesh: bpy.types.Mesh) -> np.ndarray | None:
    """The mesh's part labels (int per vertex), or None (see `_point_values`)."""
    return _point_values(mesh, PART_ATTRIBUTE, "INT", np.int32)


def vertex_group_members(obj: bpy.types.Object) -> dict[str, np.ndarray]:
    """The vertices (indices, weight > 0) of each of `obj`'s vertex groups, by group name, in one
    pass over the mesh (there is no bulk reader of vertex-group weights in bpy)."""
    members: list[list[int]] = [[] for _ in obj.vertex_groups]
    for v in obj.data.vertices:
        for g in v.groups:
            if g.weight > 0 and g.group < len(members):
                members[g.group].append(v.index)
    return {group.name: np.array(members[group.index], dtype=np.int64) for group in obj.vertex_groups}


def vertex_group_weights(obj: bpy.types.Object) -> dict[str, np.ndarray]:
    """Each vertex group of `obj` as one weight per vertex (0 where a vertex is not in it)."""
    weights = np.zeros((len(obj.vertex_groups), len(obj.data.vertices)))
    for v in obj.data.vertices:
        for g in v.groups:
            if g.group < len(weights):
                weights[g.group, v.index] = g.weight
    return {group.name: weights[group.index] for group in obj.vertex_groups}
