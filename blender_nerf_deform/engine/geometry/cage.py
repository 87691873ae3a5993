"""The cage: a closed envelope around the filtered object, tetrahedralized ONCE.

Built once per NeRF object and kept fixed for every frame (re-tetrahedralizing
per frame changes the topology and breaks animations). Steps:

1. check the extracted mesh is closed and manifold (trimesh), so inside and
   outside are defined;
2. envelope: signed distance to the mesh on a grid (libigl, fast winding
   number sign) → marching cubes (scikit-image) at level `margin` plus the
   discretisation slack → a closed offset surface at least `margin` from the
   object everywhere, so the soft density around the surface lies inside;
3. tetrahedralize the envelope with fTetWild (pytetwild), size control by
   edge length or an approximate tet count; its envelope tolerance is added to
   the offset level, so the tolerance never eats into the margin;
4. orient every tet positively, drop unreferenced vertices, reject degenerate
   tets, and measure the clearance actually achieved (the distance from the
   object's vertices to the cage boundary), which must be at least `margin`.

`box_cage` makes a structured cage of a box (Kuhn subdivision, 6 tets per
cell), used by the tests and the benchmarks.
"""

from __future__ import annotations

import contextlib
import logging
import os
import tempfile
import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import EngineError
from .barycentric import boundary_faces, signed_volumes  # noqa: F401  (boundary_faces is part of this module's API)

logger = logging.getLogger(__name__)

DEFAULT_MARGIN_FRACTION = 0.03  # of the mesh's bounding-box diagonal, when no margin is given


def box_cage(shape=(4, 4, 4), lo=(0.0, 0.0, 0.0), hi=(1.0, 1.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """Structured tet mesh of a box: (nx, ny, nz) cells, each split into 6 tets along its main diagonal."""
    nx, ny, nz = (int(s) for s in shape)
    axes = [np.linspace(lo[i], hi[i], n + 1) for i, n in enumerate((nx, ny, nz))]
    X, Y, Z = np.meshgrid(*axes, indexing="ij")
    V = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)

    def vid(i, j, k):
        return (i * (ny + 1) + j) * (nz + 1) + k

    ci, cj, ck = np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij")
    ci, cj, ck = ci.ravel(), cj.ravel(), ck.ravel()
    tets = []
    unit = np.eye(3, dtype=int)
    for perm in ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)):
        path = [np.zeros(3, dtype=int)]
        for axis in perm:
            path.append(path[-1] + unit[axis])
        tets.append(np.stack([vid(ci + p[0], cj + p[1], ck + p[2]) for p in path], axis=1))
    T = np.concatenate(tets).astype(np.int64)
    return V, orient_tets(V, T)


def orient_tets(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Tets with negative signed volume get two vertices swapped, so all volumes are positive."""
    tets = np.array(tets, dtype=np.int64, copy=True)
    neg = signed_volumes(vertices, tets) < 0
    tets[neg] = tets[neg][:, [0, 2, 1, 3]]
    return tets


def check_closed_mesh(vertices: np.ndarray, faces: np.ndarray, name: str = "mesh") -> None:
    """EngineError unless the triangle mesh is closed (watertight), manifold and consistently wound.

    Judged on the faces as given first (an extracted mesh may hold distinct vertices at one
    position, and merging them by position can pinch it); a mesh that is closed only once
    coincident vertices are merged (a triangle soup, an STL) passes too."""
    if len(faces) == 0:
        raise EngineError(f"{name} has no faces")
    as_given = _closed_mesh_problem(vertices, faces, merge=False)
    if as_given is None:
        return
    merged = _closed_mesh_problem(vertices, faces, merge=True)
    if merged is None:
        return
    problem = min(as_given, merged)  # the reading with fewer bad edges says more
    raise EngineError(f"{name} {problem[1]}")


def _closed_mesh_problem(vertices, faces, merge: bool) -> tuple[int, str] | None:
    """(number of bad edges, what is wrong), or None when closed, manifold and consistently wound."""
    import trimesh

    m = trimesh.Trimesh(vertices=vertices, faces=faces, process=merge, validate=False)
    edges = np.sort(m.edges, axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    open_edges = int((counts == 1).sum())
    nonmanifold = int((counts > 2).sum())
    if open_edges:
        return open_edges, f"is open: {open_edges} edges belong to a single face (the cage needs a closed mesh)"
    if nonmanifold:
        return nonmanifold, f"is non-manifold: {nonmanifold} edges are shared by more than two faces"
    if not m.is_winding_consistent:
        return 1, "has inconsistent face winding (normals flip between neighbouring faces)"
    return None


def _positive(x) -> bool:
    return (
        isinstance(x, (int, float, np.integer, np.floating))
        and not isinstance(x, bool)
        and bool(np.isfinite(x))
        and x > 0
    )


def check_cage_options(margin=None, edge_length=None, target_tets=None, threshold=None) -> None:
    """EngineError for cage options that cannot build a cage (None means the default), before any work."""
    if margin is not None and not _positive(margin):
        raise EngineError(f"--margin must be a positive finite distance (world units), got {margin!r}")
    if edge_length is not None and not _positive(edge_length):
        raise EngineError(f"--edge-length must be a positive finite length (world units), got {edge_length!r}")
    if target_tets is not None and (
        not isinstance(target_tets, (int, np.integer)) or isinstance(target_tets, bool) or target_tets < 1
    ):
        raise EngineError(f"--target-tets must be a positive number of tets, got {target_tets!r}")
    if threshold is not None and not (_positive(threshold) or threshold == 0):
        raise EngineError(f"--threshold must be a finite density >= 0, got {threshold!r}")


def _check_mesh_arrays(V: np.ndarray, F: np.ndarray, name: str) -> None:
    if V.ndim != 2 or V.shape[1] != 3 or F.ndim != 2 or F.shape[1] != 3:
        raise EngineError(f"{name} must have (N, 3) vertices and (F, 3) triangles, got {V.shape} and {F.shape}")
    bad = np.flatnonzero(~np.isfinite(V).all(axis=1))
    if len(bad):
        raise EngineError(f"{name}: vertex {bad[0]} has non-finite coordinates ({len(bad)} of {len(V)} vertices do)")
    if F.size and (F.min() < 0 or F.max() >= len(V)):
        raise EngineError(f"{name} has faces indexing vertices outside 0..{len(V) - 1}")


@dataclass
class Cage:
    vertices: np.ndarray  # (N, 3) float64
    tets: np.ndarray  # (M, 4) int64, positive volumes
    margin: float
    clearance: float  # smallest distance from the object's vertices to the cage boundary
    timings: dict = field(default_factory=dict)
    warnings: list = field(default_factory=list)  # what the user should know (cages of two regions meeting)


def envelope(
    vertices: np.ndarray, faces: np.ndarray, offset: float, max_cells: int = 160
) -> tuple[np.ndarray, np.ndarray, float]:
    """Closed surface at signed distance ≈ `offset` outside the mesh: (vertices, faces, grid pitch).

    The level is raised by one grid pitch so that, despite the grid's
    discretisation, no point of the envelope is closer than `offset`.
    """
    import igl
    from skimage.measure import marching_cubes

    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(faces, dtype=np.int64)
    lo, hi = V.min(0), V.max(0)
    pitch = max(offset / 2.0, float((hi - lo).max() + 2 * offset) / max_cells)
    level = offset + pitch
    pad = level + 3 * pitch
    axes = [np.arange(lo[i] - pad, hi[i] + pad + pitch, pitch) for i in range(3)]
    G = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    sd = igl.signed_distance(G, V, F, sign_type=igl.SIGNED_DISTANCE_TYPE_FAST_WINDING_NUMBER)[0]
    sd = sd.reshape(len(axes[0]), len(axes[1]), len(axes[2]))
    # Inside values are negative; marching cubes' "descent" puts normals towards lower values, so
    # flip the sign to get outward normals on an inside-positive field.
    ev, ef, _, _ = marching_cubes(-sd, level=-level, spacing=(pitch, pitch, pitch))
    ev = ev + np.array([a[0] for a in axes])
    return ev, ef.astype(np.int64), pitch


@contextlib.contextmanager
def _scratch_directory():
    """fTetWild writes a scratch file (__tracked_surface.stl) into the working directory:
    run it in a temporary one, so nothing lands in the user's folder (or an extension's)."""
    previous = os.getcwd()
    with tempfile.TemporaryDirectory(prefix="nerf_deform_tetwild_") as scratch:
        os.chdir(scratch)
        try:
            yield
        finally:
            os.chdir(previous)


def build_cage(
    vertices: np.ndarray,
    faces: np.ndarray,
    margin: float | None = None,
    *,
    edge_length: float | None = None,
    target_tets: int | None = None,
    epsilon_fraction: float = 0.25,
    optimize: bool = True,
    num_threads: int = 0,
    check_mesh: bool = True,
    attempts: int = 3,
) -> Cage:
    """Tetrahedral cage around a closed mesh, with every mesh vertex at least `margin` inside it.

    `edge_length` (world units) or `target_tets` (approximate) control the
    size; by default fTetWild's 1/20 of the envelope's diagonal.
    `epsilon_fraction` is fTetWild's envelope tolerance as a fraction of the
    margin (looser = faster and more uniform tets; the offset absorbs it).
    A result that fails validation is rebuilt, `attempts` fTetWild runs in all.
    """
    import igl

    check_cage_options(margin, edge_length, target_tets)
    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(faces, dtype=np.int64)
    _check_mesh_arrays(V, F, "mesh")
    if check_mesh:
        check_closed_mesh(V, F)
    diag = float(np.linalg.norm(V.max(0) - V.min(0)))
    if margin is None:
        margin = DEFAULT_MARGIN_FRACTION * diag
    if not margin > 0:
        raise EngineError(f"cage margin must be positive, got {margin}")
    timings = {}
    t0 = time.perf_counter()
    eps_abs = epsilon_fraction * margin
    ev, ef, _pitch = envelope(V, F, margin + eps_abs)
    timings["envelope_s"] = time.perf_counter() - t0
    ediag = float(np.linalg.norm(ev.max(0) - ev.min(0)))
    kw = {}
    if edge_length is None and target_tets is not None:
        vol = abs(float(igl.volume(np.vstack([ev, ev.mean(0)]), np.c_[ef, np.full(len(ef), len(ev))]).sum()))
        # Empirical: fTetWild's tets average about a regular tet's volume
        # (a^3 / (6 sqrt 2)) at its target edge length a (measured on our cages).
        edge_length = (vol * 6 * np.sqrt(2) * 1.0 / max(int(target_tets), 1)) ** (1 / 3)
    if edge_length is not None:
        if not edge_length > 0:
            raise EngineError(f"cage edge length must be positive, got {edge_length}")
        kw["edge_length_abs"] = float(edge_length)
    # fTetWild is not deterministic (not even single-threaded: the same mesh gives a different
    # cage on every run), and a run has been seen to return a cage that left part of the object
    # outside, on a noisy mesh that rebuilds of similar meshes handled. So every result is
    # validated, and a rejected one is rebuilt, up to `attempts` runs in all, before the error is
    # reported.
    timings["tetrahedralize_s"] = timings["clearance_check_s"] = 0.0
    runs = max(1, int(attempts))
    for attempt in range(runs):
        try:
            CV, CT, clearance = _tetrahedralize_checked(
                V, ev, ef, eps_abs / ediag, margin, optimize, num_threads, kw, timings
            )
            break
        except EngineError as error:
            if attempt == runs - 1:
                raise EngineError(f"{error} (after {runs} fTetWild run(s))") from None
            logger.warning("cage: fTetWild result rejected (%s); rebuilding", error)
    timings["attempts"] = attempt + 1
    return Cage(vertices=CV, tets=CT, margin=float(margin), clearance=float(clearance), timings=timings)


def _tetrahedralize_checked(V, ev, ef, epsilon, margin, optimize, threads, kw, timings):
    """fTetWild on the envelope, oriented and validated: (vertices, tets, clearance) or EngineError."""
    import pytetwild

    t0 = time.perf_counter()
    with _scratch_directory():
        CV, CT = pytetwild.tetrahedralize(
            ev, ef.astype(np.int32), epsilon=epsilon, optimize=optimize, num_threads=threads, quiet=True, **kw
        )
    timings["tetrahedralize_s"] += time.perf_counter() - t0
    CT = np.asarray(CT, dtype=np.int64)
    if len(CT) == 0:
        raise EngineError("tetrahedralization produced no tets (is the mesh closed and non-degenerate?)")
    used = np.unique(CT)
    remap = np.full(len(CV), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    CV, CT = np.asarray(CV, dtype=np.float64)[used], remap[CT]
    CT = orient_tets(CV, CT)
    vol = signed_volumes(CV, CT)
    tiny = np.flatnonzero(vol <= 1e-9 * (float(np.median(vol)) if len(vol) else 1.0))
    if len(tiny):
        raise EngineError(f"degenerate cage: {len(tiny)} of {len(CT)} tets have (near) zero volume")
    t0 = time.perf_counter()
    clearance = cage_clearance(CV, CT, V)
    timings["clearance_check_s"] += time.perf_counter() - t0
    if clearance < margin * (1 - 1e-6):
        raise EngineError(
            f"cage clearance {clearance:.4g} is below the margin {margin:.4g} "
            "(some of the object lies outside or too close)"
        )
    return CV, CT, clearance


def cage_clearance(cage_vertices: np.ndarray, tets: np.ndarray, points: np.ndarray) -> float:
    """Smallest signed distance of `points` inside the cage boundary (negative if any lies outside)."""
    import igl

    bf = boundary_faces(tets)
    sd = igl.signed_distance(
        np.asarray(points, dtype=np.float64), cage_vertices, bf, sign_type=igl.SIGNED_DISTANCE_TYPE_FAST_WINDING_NUMBER
    )[0]
    return float((-sd).min())


def build_nerf_cage(
    vertices: np.ndarray,
    faces: np.ndarray,
    nerf,
    margin: float | None = None,
    threshold: float | None = None,
    *,
    edge_length: float | None = None,
    target_tets: int | None = None,
    name: str = "mesh",
    log=print,
    cut: np.ndarray | None = None,
) -> Cage:
    """The cage of a NeRF's extracted mesh (what `cage` writes and the add-on's Build Cage stores).

    The margin (default 3% of the mesh's diagonal) is widened, up to three times by 1.5x,
    while more than 0.5% of the envelope still sees the NeRF's density above a tenth of the
    surface `threshold`: a soft, fuzzy surface needs a wider cage, or its outer shell would
    stay behind when the cage moves. Where an edit region cut the scene (`cut`, per mesh
    vertex), the envelope beyond the cut lies in the rest of the scene (the floor under a
    statue): it is dense there whatever the margin, so it is left out of that check.
    """
    from .extract import DEFAULT_THRESHOLD, density_fn_of

    check_cage_options(margin, edge_length, target_tets, threshold)
    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(faces, dtype=np.int64)
    _check_mesh_arrays(V, F, name)
    check_closed_mesh(V, F, name=name)
    density = density_fn_of(nerf)
    margin = margin if margin is not None else DEFAULT_MARGIN_FRACTION * float(np.linalg.norm(np.ptp(V, axis=0)))
    if not margin > 0:
        raise EngineError(f"cage margin must be positive, got {margin}")
    threshold = threshold if threshold is not None else DEFAULT_THRESHOLD
    beyond_cut = None
    if cut is not None and np.any(cut):
        from scipy.spatial import cKDTree

        to_mesh, to_cut = cKDTree(V), cKDTree(V[np.asarray(cut, dtype=bool)])
    for attempt in range(4):
        ev, _, _ = envelope(V, F, margin)
        if beyond_cut is not None or (cut is not None and np.any(cut)):
            # Beyond the cut and around its rim (the cut about as near as the object, as cut_pins
            # reads it, with a margin's slack): the rest of the scene.
            beyond_cut = to_cut.query(ev)[0] <= to_mesh.query(ev)[0] + margin
            ev = ev[~beyond_cut]
        soft = density(ev) > 0.1 * threshold if len(ev) else np.zeros(1, dtype=bool)
        if soft.mean() <= 0.005 or attempt == 3:
            break
        log(
            f"cage: {soft.mean():.1%} of the envelope at margin {margin:.4g} still has density "
            f"> {0.1 * threshold:g}; widening"
        )
        margin *= 1.5
    return build_cage(V, F, margin, edge_length=edge_length, target_tets=target_tets, check_mesh=False)


def vertices_outside(vertices: np.ndarray, bounds: np.ndarray) -> int:
    """How many cage vertices lie outside a NeRF's (2,3) bounds (reported: the NeRF is empty there)."""
    return int(np.any((vertices < bounds[0]) | (vertices > bounds[1]), axis=1).sum())


PIN_DEPTH = 2.5  # margins: how far from the cut the cage is pinned


def cut_pins(cage_vertices: np.ndarray, mesh_vertices: np.ndarray, cut: np.ndarray | None, margin: float) -> np.ndarray:
    """Cage vertices to pin where an edit region cut the scene (sorted indices; empty without a cut).

    A cage vertex is pinned when the cut is about as near to it as the object is (within half
    the margin), and not farther than PIN_DEPTH margins (the envelope lies about two margins out,
    so its side beyond the cut is inside that): the cage's side beyond the cut and the rim around
    it, and a band of the object's inside above the cut, so the deformation fades to nothing where
    the object meets the rest of the scene and no seam opens there."""
    from scipy.spatial import cKDTree

    if cut is None or not np.any(cut):
        return np.zeros(0, dtype=np.int64)
    M = np.asarray(mesh_vertices, dtype=np.float64)
    C = np.asarray(cage_vertices, dtype=np.float64)
    d_any = cKDTree(M).query(C)[0]
    d_cut = cKDTree(M[np.asarray(cut, dtype=bool)]).query(C)[0]
    return np.flatnonzero((d_cut <= d_any + 0.5 * float(margin)) & (d_cut <= PIN_DEPTH * float(margin))).astype(
        np.int64
    )


def cut_from_region(mesh_vertices: np.ndarray, region) -> np.ndarray:
    """The cut of a mesh that carries no cut flags (made elsewhere): its vertices on or outside
    the region's boundary (extraction closes a cut just outside it)."""
    local = np.abs(region.to_local(mesh_vertices))
    return np.any(local >= region.half * (1 - 1e-6), axis=1)


def submesh(vertices: np.ndarray, faces: np.ndarray, keep: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(vertices, faces, original indices) of the faces whose vertices all lie in `keep` (bool per vertex)."""
    F = np.asarray(faces, dtype=np.int64)
    F = F[keep[F].all(axis=1)]
    used = np.flatnonzero(keep)
    remap = np.full(len(vertices), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return np.asarray(vertices)[used], remap[F], used


def build_part_cages(vertices: np.ndarray, faces: np.ndarray, parts: np.ndarray, build_one) -> tuple[Cage, np.ndarray]:
    """One cage per part of a mesh (the objects of several edit regions), in one cage: (the cages'
    vertices and tets concatenated, the part of each cage vertex). `build_one(vertices, faces, i)`
    builds part i's Cage (build_nerf_cage with its options). Each object gets its own margin and
    no tet joins two objects, so each deforms on its own; the cage's margin and clearance are the
    smallest of the parts'."""
    parts = np.asarray(parts, dtype=np.int64).ravel()
    if len(parts) != len(vertices):
        raise EngineError(f"{len(parts)} part labels for a mesh of {len(vertices)} vertices")
    cages, labels, offset = [], [], 0
    for i in np.unique(parts):
        V, F, _ = submesh(vertices, faces, parts == i)
        if len(F) == 0:
            raise EngineError(f"part {i + 1} of the mesh (edit region {i + 1}) has no faces")
        cage = build_one(V, F, int(i))
        cages.append((cage.vertices, cage.tets + offset, cage))
        labels.append(np.full(len(cage.vertices), i, dtype=np.int64))
        offset += len(cage.vertices)
    timings = {}
    for _v, _t, c in cages:
        for k, v in c.timings.items():
            timings[k] = timings.get(k, 0) + v
    merged = Cage(
        vertices=np.concatenate([c[0] for c in cages]),
        tets=np.concatenate([c[1] for c in cages]),
        margin=min(c[2].margin for c in cages),
        clearance=min(c[2].clearance for c in cages),
        timings=timings,
    )
    labels = np.concatenate(labels)
    merged.warnings = overlapping_pieces(merged.vertices, merged.tets, labels)
    return merged, labels


def overlapping_pieces(vertices: np.ndarray, tets: np.ndarray, part: np.ndarray) -> list[str]:
    """One line per pair of parts whose cages overlap (a vertex of one inside the other's tets):
    there a deformed point could belong to either object, so renders are ambiguous."""
    from .embedding import locate

    tet_part = part[tets[:, 0]]
    lines = []
    ids = np.unique(part)
    for i in ids:
        for j in ids:
            if j <= i:
                continue
            tid, _ = locate(vertices[part == i], vertices, tets[tet_part == j])
            inside = int((tid >= 0).sum())
            tid, _ = locate(vertices[part == j], vertices, tets[tet_part == i])
            inside += int((tid >= 0).sum())
            if inside:
                lines.append(
                    f"the cages of edit regions {i + 1} and {j + 1} overlap ({inside} cage vertices of one "
                    "lie inside the other): renders there are ambiguous; move the regions further apart"
                )
    return lines


def part_cut_pins(
    cage_vertices: np.ndarray,
    cage_part: np.ndarray,
    mesh_vertices: np.ndarray,
    mesh_part: np.ndarray,
    cut: np.ndarray | None,
    margin: float,
) -> np.ndarray:
    """`cut_pins` part by part: a cage vertex is pinned only by its own object's cut."""
    if cut is None or not np.any(cut):
        return np.zeros(0, dtype=np.int64)
    cut = np.asarray(cut, dtype=bool)
    out = []
    for i in np.unique(cage_part):
        own_cage, own_mesh = np.flatnonzero(cage_part == i), np.flatnonzero(mesh_part == i)
        out.append(own_cage[cut_pins(cage_vertices[own_cage], mesh_vertices[own_mesh], cut[own_mesh], margin)])
    return np.sort(np.concatenate(out)).astype(np.int64)
