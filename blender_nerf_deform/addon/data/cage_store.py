"""The cage and the surface embedding, stored in the .blend.

The cage is built once and must render the same frames in a fresh `blender -b`
process or on a farm, so its exact data lives in the file:

- The cage object: a mesh whose vertices are the rest cage's vertices (so
  Armature, Lattice or any modifier on it can deform them) and whose faces are
  the cage's boundary triangles (what an artist needs to see). The exact rest
  positions (float64; mesh vertices are float32) and the tetrahedra are ID
  properties of its mesh datablock.
- The extracted mesh: its embedding in the rest cage, one tet and four
  barycentric weights per vertex, also as ID properties of its mesh.
- The cage vertices pinned where an edit region cut the scene (Build Cage with
  Pin Cut): their indices as an ID property of the cage mesh, which is what ARAP
  keeps at rest, mirrored in the vertex group "NeRF Cut Pin" (weight 1) of the
  cage object for artists (a modifier's mask in Cage Modifiers mode). Editing
  the group does not change the pins: Build Cage does.

ID property arrays are stored compactly and read back through the buffer
protocol, so a 100k-tet cage costs milliseconds to store and load. Reads copy:
a numpy view of an ID property outlives it (undo, Build Cage again, quitting)
and would then read freed memory. Writes delete the old property first: in
bpy 5.0.1 assigning an array of another length over an existing ID-property
array corrupts the heap (and fTetWild's vertex count differs on every build).

What is read back is checked once, where it is read (`load_cage`, `load_embedding`, `cage_pins`):
each property's type (an array of integers or numbers, not text or a list), its length against the
mesh, every index against what it indexes (tets against the cage's vertices, the embedding's tets
against the cage's tets), finite values. Damage (a script, a broken file, another add-on) is one
CageDataError naming the object, what is wrong and the repair (Build Cage again), never a numpy
traceback, and never a render or preview that carries on as if nothing were wrong.

Each stored cage and embedding also carries its content key (the worker
session's name for it, `protocol.content_key` of the arrays as sent), so a
frame or a preview update tells the worker which cage it means without reading,
hashing or sending the arrays again. Data saved before keys existed gets its
key computed once per Blender session.
"""

from __future__ import annotations

import bpy

import numpy as np

from ...engine.errors import EngineError
from ...engine.geometry.barycentric import boundary_faces
from ...engine.geometry.cage_refine import separate_regions as separate_cage_regions
from ...engine.geometry.cage_refine import shared_vertices
from ...engine.geometry.poses import MAX_COORDINATE
from ...engine.service.protocol import content_key
from .mesh_attributes import part_labels, set_part_labels, vertex_group_members, vertex_group_weights
from .properties import PIN_GROUP, CageDataError, handles_of, to_nerf_frame

REST_KEY = "nerf_deform_rest_vertices"
TETS_KEY = "nerf_deform_tets"
EMBED_TET_KEY = "nerf_deform_embed_tet"
EMBED_WEIGHTS_KEY = "nerf_deform_embed_weights"
EMBED_COUNT_KEY = "nerf_deform_embed_vertex_count"
CAGE_CONTENT_KEY = "nerf_deform_cage_key"
EMBED_CONTENT_KEY = "nerf_deform_embed_key"
CUT_PINS_KEY = "nerf_deform_cut_pins"
CUT_PIN_GROUP = "NeRF Cut Pin"
_computed_keys: dict[tuple, str] = {}  # keys of data stored without one, by (datablock, property)
_checked: set[tuple] = set()  # stored data checked whole this session, by datablock, property, key and length
REPAIR = "select its NeRF and run Build Cage again"


def _set_property(idblock, name: str, value) -> None:
    if name in idblock:
        del idblock[name]  # never assign over an array of another length (module docstring)
    idblock[name] = value


def set_triangles(mesh: bpy.types.Mesh, vertices: np.ndarray, faces: np.ndarray) -> None:
    """Replace a mesh's geometry with vertices (N,3) and triangles (F,3), in bulk."""
    mesh.clear_geometry()
    mesh.vertices.add(len(vertices))
    mesh.vertices.foreach_set("co", np.ascontiguousarray(vertices, dtype=np.float32).ravel())
    mesh.loops.add(3 * len(faces))
    mesh.loops.foreach_set("vertex_index", np.ascontiguousarray(faces, dtype=np.int32).ravel())
    mesh.polygons.add(len(faces))
    mesh.polygons.foreach_set("loop_start", np.arange(0, 3 * len(faces), 3, dtype=np.int32))
    mesh.update(calc_edges=True)
    repair_selection_attributes(mesh)


def repair_selection_attributes(mesh: bpy.types.Mesh) -> None:
    """Drop mistyped selection attributes (nothing is selected then; `set_triangles` calls it). In bpy 5.0.1
    `Mesh.update(calc_edges=True)` on a mesh without edges (what `set_triangles` builds) makes
    ".select_edge" an INT32_2D attribute, the type of ".edge_verts"; selecting an edge of the
    mesh then (from Python, and so from any script or add-on) crashes Blender."""
    for name in (".select_vert", ".select_edge", ".select_poly"):
        attribute = mesh.attributes.get(name)
        if attribute is not None and attribute.data_type != "BOOLEAN":
            mesh.attributes.remove(attribute)


def store_cage(cage_mesh: bpy.types.Mesh, vertices: np.ndarray, tets: np.ndarray) -> None:
    """Write the rest cage into `cage_mesh` (replacing its geometry) and its exact data as ID properties."""
    vertices = np.ascontiguousarray(vertices, dtype=np.float64)
    tets = np.asarray(tets)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or tets.ndim != 2 or tets.shape[1] != 4:
        raise CageDataError(f"cage must be vertices (N,3) and tets (M,4), got {vertices.shape} and {tets.shape}")
    if tets.size and (tets.min() < 0 or tets.max() >= len(vertices)):
        raise CageDataError(f"cage tets index vertices outside 0..{len(vertices) - 1}")
    set_triangles(cage_mesh, vertices, boundary_faces(tets, vertices))
    _set_property(cage_mesh, REST_KEY, vertices.ravel())
    _set_property(cage_mesh, TETS_KEY, tets.astype(np.int32).ravel())
    _set_property(cage_mesh, CAGE_CONTENT_KEY, content_key(vertices, tets.astype(np.int64)))


def has_cage(cage_mesh: bpy.types.Mesh | None) -> bool:
    """Whether the mesh holds a NeRF cage, whole or damaged (a damaged one is an error when read, never
    a render at rest)."""
    return cage_mesh is not None and (REST_KEY in cage_mesh or TETS_KEY in cage_mesh)


def _holder(mesh: bpy.types.Mesh) -> str:
    """The object(s) that show `mesh`, and the mesh, as an error names them."""
    users = sorted(o.name for o in bpy.data.objects if o.type == "MESH" and o.data == mesh)
    return f"'{users[0]}' (mesh '{mesh.name}')" if users else f"mesh '{mesh.name}'"


def damaged(mesh: bpy.types.Mesh, what: str) -> CageDataError:
    return CageDataError(f"the NeRF data stored in {_holder(mesh)} is damaged: {what}; {REPAIR}")


def _described(value) -> str:
    if value is None:
        return "missing"
    if isinstance(value, str):
        return f"text {value[:40]!r}"
    if isinstance(value, (int, float)):
        return f"the single number {value!r}"
    return f"a {type(value).__name__}"


def _stored_array(mesh: bpy.types.Mesh, key: str, what: str, integers: bool, row: int) -> np.ndarray:
    """The ID-property array `key` of `mesh` as int64 or float64 rows of `row` values (a copy), or the
    CageDataError that says how it is damaged."""
    value = mesh.get(key)
    typecode = getattr(value, "typecode", None)  # an ID-property array: "i" integers, "d"/"f" floats, "b" bools
    if typecode is None or (integers and typecode != "i") or (not integers and typecode not in "dfi"):
        kind = "integers" if integers else "numbers"
        shown = _described(value) if typecode is None else f"an array of {'floats' if typecode in 'df' else 'booleans'}"
        raise damaged(mesh, f"its {what} ({key}) is {shown}, not an array of {kind}")
    array = np.array(value, dtype=np.int64 if integers else np.float64)  # copies (module docstring)
    if array.ndim != 1 or len(array) % row:
        raise damaged(mesh, f"its {what} ({key}) hold {array.size} values, not whole rows of {row}")
    return array.reshape(-1, row) if row > 1 else array


def load_cage(cage_mesh: bpy.types.Mesh) -> tuple[np.ndarray, np.ndarray]:
    """(rest vertices (N,3) float64, tets (M,4) int64) as stored, checked (module docstring)."""
    if cage_mesh is None or not has_cage(cage_mesh):
        raise CageDataError(f"mesh '{getattr(cage_mesh, 'name', None)}' holds no NeRF cage: run Build Cage")
    rest = _stored_array(cage_mesh, REST_KEY, "rest vertices", integers=False, row=3)
    tets = _stored_array(cage_mesh, TETS_KEY, "tets", integers=True, row=4)
    if len(cage_mesh.vertices) != len(rest):
        raise CageDataError(
            f"cage mesh '{cage_mesh.name}' has {len(cage_mesh.vertices)} vertices but its cage has {len(rest)}: "
            "its vertices were added or deleted in Edit Mode; rebuild the cage (Build Cage)"
        )
    bad = np.flatnonzero(~(np.isfinite(rest) & (np.abs(rest) <= MAX_COORDINATE)).all(axis=1))
    if len(bad):
        raise damaged(
            cage_mesh,
            f"rest vertex {bad[0]} of its cage is {rest[bad[0]].tolist()}, not a finite point "
            f"within {MAX_COORDINATE:g} NeRF units ({len(bad)} of {len(rest)} vertices are not)",
        )
    if not len(tets):
        raise damaged(cage_mesh, "its cage has no tets")
    out = np.flatnonzero(((tets < 0) | (tets >= len(rest))).any(axis=1))
    if len(out):
        raise damaged(
            cage_mesh,
            f"tet {out[0]} of its cage names vertices {tets[out[0]].tolist()}, outside the "
            f"cage's 0..{len(rest) - 1} ({len(out)} of {len(tets)} tets do)",
        )
    ordered = np.sort(tets, axis=1)
    repeated = np.flatnonzero((ordered[:, 1:] == ordered[:, :-1]).any(axis=1))
    if len(repeated):
        raise damaged(
            cage_mesh,
            f"tet {repeated[0]} of its cage names a vertex twice ({tets[repeated[0]].tolist()}; "
            f"{len(repeated)} of {len(tets)} tets do)",
        )
    return rest, tets


def store_cut_pins(cage_object: bpy.types.Object, pins: np.ndarray) -> None:
    """Record the cage vertices pinned at the cut (after `store_cage`): the ID property and the
    vertex group CUT_PIN_GROUP; none pinned: both removed."""
    mesh = cage_object.data
    pins = np.unique(np.asarray(pins, dtype=np.int64).ravel())
    if len(pins) and (pins[0] < 0 or pins[-1] >= len(mesh.vertices)):
        raise CageDataError(f"pinned cage vertices index outside 0..{len(mesh.vertices) - 1}")
    if (group := cage_object.vertex_groups.get(CUT_PIN_GROUP)) is not None:
        cage_object.vertex_groups.remove(group)
    if not len(pins):
        if CUT_PINS_KEY in mesh:
            del mesh[CUT_PINS_KEY]
        return
    _set_property(mesh, CUT_PINS_KEY, pins.astype(np.int32))
    cage_object.vertex_groups.new(name=CUT_PIN_GROUP).add(pins.tolist(), 1.0, "REPLACE")


def cage_vertex_parts(n_vertices: int, tets: np.ndarray, tet_ids: np.ndarray, surface_part: np.ndarray) -> np.ndarray:
    """The part (edit region) of each cage vertex of a cage built per part (no tet joins two parts):
    each connected piece of the tets takes the part of the surface vertices embedded in it (the
    most common one); a piece holding none takes its lower neighbour's in index order (the engine
    concatenates the parts' cages in part order); -1 when no piece holds a surface vertex."""
    tets = np.asarray(tets, dtype=np.int64).reshape(-1, 4)
    labels = np.arange(n_vertices, dtype=np.int64)
    while len(tets):  # connected pieces: hook each tet's roots to its smallest label, then jump
        low = labels[tets].min(axis=1)
        new = labels.copy()
        np.minimum.at(new, labels[tets].ravel(), np.repeat(low, 4))
        np.minimum.at(new, tets.ravel(), np.repeat(low, 4))
        while not np.array_equal(new, new[new]):
            new = new[new]
        if np.array_equal(new, labels):
            break
        labels = new
    part = np.full(n_vertices, -1, dtype=np.int64)
    tet_ids, surface_part = np.asarray(tet_ids, dtype=np.int64), np.asarray(surface_part, dtype=np.int64)
    if not len(tet_ids) or not len(tets):
        return part
    pieces = labels[tets[tet_ids, 0]]
    for piece in np.unique(pieces):
        values, counts = np.unique(surface_part[pieces == piece], return_counts=True)
        part[labels == piece] = values[np.argmax(counts)]
    known = np.flatnonzero(part >= 0)
    if len(known) < n_vertices:
        before = np.searchsorted(known, np.arange(n_vertices), side="right") - 1
        part = np.where(part >= 0, part, part[known[np.maximum(before, 0)]])
    return part


def cage_pins(cage_object: bpy.types.Object) -> np.ndarray:
    """Indices (int64, sorted) of the cage vertices pinned at the cut; empty when none are."""
    mesh = cage_object.data
    if CUT_PINS_KEY not in mesh:
        return np.zeros(0, dtype=np.int64)
    pins = _stored_array(mesh, CUT_PINS_KEY, "cage vertices pinned at the cut", integers=True, row=1)
    if len(pins) and (pins.min() < 0 or pins.max() >= len(mesh.vertices)):
        raise CageDataError(
            f"cage mesh '{mesh.name}' has {len(mesh.vertices)} vertices but its pins at the cut index up to "
            f"{pins.max()}: "
            "rebuild the cage (Build Cage)"
        )
    return np.unique(pins)


def evaluated_cage_vertices(cage_object: bpy.types.Object, depsgraph: bpy.types.Depsgraph) -> np.ndarray:
    """Cage vertices after the cage object's modifiers (Armature, Lattice, ...), in its local frame."""
    evaluated = cage_object.evaluated_get(depsgraph)
    if cage_object.modifiers and depsgraph.objects.get(cage_object.name) is None:
        # Not in this depsgraph (a render's leaves out hide_render objects and excluded collections):
        # its modifiers were not evaluated, and rendering the rest pose instead would be silently wrong.
        raise CageDataError(
            f"cage '{cage_object.name}' is left out of this render or view (disabled in renders, hidden, or its "
            "collection excluded), so its modifiers cannot deform the NeRF: enable it again (Build Cage keeps it "
            "invisible to render engines by its ray visibility; show it as Wire or Bounds to unclutter the view)"
        )
    mesh = evaluated.to_mesh()
    try:
        n = len(mesh.vertices)
        if n != len(cage_object.data.vertices):
            raise CageDataError(
                f"the modifiers of cage '{cage_object.name}' change its vertex count "
                f"({len(cage_object.data.vertices)} → {n}); "
                "use deforming modifiers only (Armature, Lattice, Simple Deform, ...)"
            )
        co = np.empty(3 * n, dtype=np.float32)
        mesh.vertices.foreach_get("co", co)
    finally:
        evaluated.to_mesh_clear()
    return co.reshape(-1, 3).astype(np.float64)


def deformed_cage_in_nerf_frame(
    nerf: bpy.types.Object, cage_object: bpy.types.Object, depsgraph, to_nerf=None
) -> np.ndarray:
    """The cage as its modifiers and its own placement deform it, in the NeRF's frame (`to_nerf`: the
    NeRF's evaluated world -> NeRF frame Matrix, when the caller has it)."""
    local = evaluated_cage_vertices(cage_object, depsgraph)
    if to_nerf is None:
        to_nerf = to_nerf_frame(nerf, nerf.evaluated_get(depsgraph).matrix_world)
    relative = np.array(to_nerf) @ np.array(cage_object.evaluated_get(depsgraph).matrix_world)
    return local @ relative[:3, :3].T + relative[:3, 3]


def store_embedding(mesh: bpy.types.Mesh, tet_ids: np.ndarray, weights: np.ndarray) -> None:
    """Embed `mesh`'s vertices in the rest cage: vertex k = weights[k] · cage[tets[tet_ids[k]]]."""
    tet_ids = np.asarray(tet_ids)
    weights = np.ascontiguousarray(weights, dtype=np.float64)
    if tet_ids.shape != (len(mesh.vertices),) or weights.shape != (len(mesh.vertices), 4):
        raise CageDataError(
            f"embedding of '{mesh.name}' needs one tet and 4 weights per vertex ({len(mesh.vertices)}), "
            f"got {tet_ids.shape} and {weights.shape}"
        )
    _set_property(mesh, EMBED_TET_KEY, tet_ids.astype(np.int32))
    _set_property(mesh, EMBED_WEIGHTS_KEY, weights.ravel())
    _set_property(mesh, EMBED_COUNT_KEY, len(mesh.vertices))
    _set_property(mesh, EMBED_CONTENT_KEY, content_key(tet_ids.astype(np.int64), weights))


def stored_tet_count(cage_mesh: bpy.types.Mesh) -> int | None:
    """How many tets the stored cage has, read without loading it (None when it holds no tets array)."""
    tets = cage_mesh.get(TETS_KEY) if cage_mesh is not None else None
    return len(tets) // 4 if getattr(tets, "typecode", None) == "i" else None


def load_embedding(mesh: bpy.types.Mesh, n_tets: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(tet id per vertex (V,), weights (V,4)) as stored, checked (module docstring); with `n_tets`, the
    tet count of the cage it is embedded in, every tet id against it."""
    if EMBED_TET_KEY not in mesh or EMBED_WEIGHTS_KEY not in mesh:
        raise CageDataError(f"mesh '{mesh.name}' is not embedded in a cage: run Build Cage")
    count = mesh.get(EMBED_COUNT_KEY)
    if not isinstance(count, int) or isinstance(count, bool):
        raise damaged(
            mesh, f"its embedding's vertex count ({EMBED_COUNT_KEY}) is {_described(count)}, not a whole number"
        )
    if count != len(mesh.vertices):
        raise CageDataError(
            f"mesh '{mesh.name}' has {len(mesh.vertices)} vertices but was embedded with {count}: "
            "rebuild the cage (Build Cage)"
        )
    tet_ids = _stored_array(mesh, EMBED_TET_KEY, "embedding's tets", integers=True, row=1)
    weights = _stored_array(mesh, EMBED_WEIGHTS_KEY, "embedding's weights", integers=False, row=4)
    if len(tet_ids) != count or len(weights) != count:
        raise damaged(
            mesh, f"its embedding has {len(tet_ids)} tets and {len(weights)} weight rows for its {count} vertices"
        )
    limit = n_tets if n_tets is not None else np.iinfo(np.int32).max
    out = np.flatnonzero((tet_ids < 0) | (tet_ids >= limit))
    if len(out):
        where = f"its cage's 0..{n_tets - 1}" if n_tets is not None else "any cage"
        raise damaged(
            mesh,
            f"vertex {out[0]} is embedded in tet {tet_ids[out[0]]}, outside {where} "
            f"({len(out)} of {count} vertices are)",
        )
    bad = np.flatnonzero(~np.isfinite(weights).all(axis=1) | (np.abs(weights.sum(axis=1) - 1.0) > 1e-3))
    if len(bad):
        raise damaged(
            mesh,
            f"the embedding weights of vertex {bad[0]} are {weights[bad[0]].tolist()}, not finite "
            f"barycentric weights summing to 1 ({len(bad)} of {count} vertices' are not)",
        )
    return tet_ids, weights


def _stored_key(idblock, name: str, load) -> str:
    key = idblock.get(name)
    if isinstance(key, str) and key:
        return key
    # Saved before content keys: hash once per session (the data cannot change without Build
    # Cage, which stores a key).
    cache_key = (idblock.session_uid, name, len(idblock.vertices))
    if cache_key not in _computed_keys:
        _computed_keys[cache_key] = content_key(*load(idblock))
    return _computed_keys[cache_key]


def _fingerprint(value) -> tuple:
    """What tells one stored value from another cheaply: its type, length and, for an array, the sum of its
    words (read in place: no copy, no hash), which any change of a value alters."""
    typecode = getattr(value, "typecode", None)
    if typecode is None:
        return (type(value).__name__, value if isinstance(value, (str, int, float)) else None)
    words = np.frombuffer(value, dtype=np.uint8)
    if words.size % 4 == 0:
        words = words.view(np.uint32)
    return typecode, words.size, int(words.sum(dtype=np.uint64))


def _checked_once(idblock, name: str, load, against=None) -> None:
    """Run `load` (which checks everything it reads) once for each content of the datablock's stored data:
    what the worker is sent by key alone, without reading it, is checked as if it were read."""
    keys = (name, REST_KEY, TETS_KEY, CUT_PINS_KEY, EMBED_TET_KEY, EMBED_WEIGHTS_KEY, EMBED_COUNT_KEY)
    mark = (idblock.session_uid, name, against, len(idblock.vertices), *(_fingerprint(idblock.get(k)) for k in keys))
    if mark not in _checked:
        load(idblock)
        if len(_checked) > 1000:  # a long session of rebuilds: what was checked before is checked again
            _checked.clear()
        _checked.add(mark)


def shared_cage(cage_mesh: bpy.types.Mesh) -> tuple[str, callable]:
    """The rest cage as worker-session content: (key, loader of its arrays); loaded only when sent."""
    _checked_once(cage_mesh, CAGE_CONTENT_KEY, load_cage)
    key = _stored_key(cage_mesh, CAGE_CONTENT_KEY, load_cage)
    return key, lambda: dict(zip(("vertices", "tets"), load_cage(cage_mesh)))


def shared_embedding(mesh: bpy.types.Mesh, cage_mesh: bpy.types.Mesh | None = None) -> tuple[str, callable]:
    """The surface's embedding as worker-session content: (key, loader of its arrays); with `cage_mesh`,
    checked against that cage's tets."""
    n_tets = stored_tet_count(cage_mesh) if cage_mesh is not None else None
    _checked_once(mesh, EMBED_CONTENT_KEY, lambda m: load_embedding(m, n_tets), against=n_tets)
    key = _stored_key(mesh, EMBED_CONTENT_KEY, load_embedding)
    return key, lambda: dict(zip(("tet_ids", "weights"), load_embedding(mesh, n_tets)))


def separate_regions(nerf: bpy.types.Object) -> list[tuple[str, str]]:
    """Refine `nerf`'s stored cage where two of its regions (handles, the pinned region and the
    cut's pins) lean on the same cage vertices, re-embed its surface and carry the cage's pins,
    part labels and vertex groups over (engine.geometry.cage_refine.separate_regions says why).
    Returns the (level, message) lines to report; nothing happens (and nothing is reported) when no
    cage vertex is shared or the NeRF has no cage yet (Build Cage calls this too). The cage stays as
    built, with a warning that says why, when the regions are too close to part by refining (it
    would multiply the tets for nothing) or its modifiers or shape keys need its vertices."""
    s = nerf.nerf_deform
    surface, cage = s.surface, s.cage
    if surface is None or cage is None or not has_cage(cage.data) or EMBED_TET_KEY not in surface.data:
        return []
    handles = handles_of(nerf)
    if not handles:
        return []
    members = vertex_group_members(surface)
    regions = [members.get(h.nerf_deform.region, np.zeros(0, np.int64)) for h in handles]
    pinned = members.get(PIN_GROUP, np.zeros(0, np.int64))
    rest, tets = load_cage(cage.data)
    tet_ids, weights = load_embedding(surface.data, len(tets))
    pins = cage_pins(cage)
    if not len(shared_vertices(tets, tet_ids, weights, regions, pinned, pins)):
        return []
    if cage.data.shape_keys is not None or cage.modifiers:
        return [
            (
                "WARNING",
                f"{cage.name} is not refined where {nerf.name}'s regions meet: its "
                f"{'shape keys' if cage.data.shape_keys is not None else 'modifiers'} need its vertices as "
                "built, so handles next to each other may stray from their transform by a few percent",
            )
        ]
    try:
        separation = separate_cage_regions(rest, tets, tet_ids, weights, regions, pinned, pins)
    except EngineError as error:  # the cage is kept as it was, and so is the new region
        return [("WARNING", f"{cage.name} is not refined where {nerf.name}'s regions meet: {error}")]
    names = [h.name for h in handles] + ["the pinned region"]
    lines = [
        (
            "WARNING",
            f"{names[a]} and {names[b]} are too close to part on {cage.name}: leave a band of unselected "
            f"vertices about {2 * separation.edge:.2g} wide (NeRF units) between them, so that each follows "
            "its own transform (they stray by a few percent now)",
        )
        for a, b in separation.too_close
    ]  # refining them would multiply the tets and part nothing
    if separation.bisection is None:
        return lines
    groups = {name: w for name, w in vertex_group_weights(cage).items() if name != CUT_PIN_GROUP}
    part = part_labels(cage.data)
    store_cage(cage.data, separation.vertices, separation.tets)
    store_embedding(surface.data, separation.tet_ids, separation.weights)
    store_cut_pins(cage, separation.cage_pins)
    if part is not None and len(part) == len(rest):
        set_part_labels(cage.data, np.rint(separation.bisection.extend_values(part)).astype(np.int32))
    for name, w in groups.items():  # an artist's groups, linear along each split edge (new geometry: new groups)
        group = cage.vertex_groups.get(name) or cage.vertex_groups.new(name=name)
        values = separation.bisection.extend_values(w)
        for weight in np.unique(values[values > 0]):
            group.add(np.flatnonzero(values == weight).tolist(), float(weight), "REPLACE")
    parted = ", ".join(f"{names[a]} and {names[b]}" for a, b in separation.parted)
    return [("INFO", f"{cage.name}: refined where {parted} met: {len(tets)} -> {len(separation.tets)} tets")] + lines
