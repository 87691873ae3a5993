"""Mesh extraction from a NeRF's density, with automatic filtering of floaters.

1. Sample the density on a grid over the NeRF's bounds (`resolution` points
   per axis, chunked by z-slabs, with progress), or over an edit region (an
   oriented box, region.py: `resolution` points along its longest side, its
   other sides at the same spacing, samples outside the NeRF's bounds empty).
   With a pick point, keep only the part of {density > threshold} connected to
   it (NeRFshop's region growing over the density grid, scipy's labelling,
   6-connected), limited by the region.
2. Pad the grid with one layer of empty samples, so every surface closes even
   where the object touches the bounds or the region cuts it (the cut), and
   flag the vertices that close a cut (those on a grid edge to a padding or
   outside-the-bounds sample): the cage pins them. Run marching cubes
   (scikit-image) at the density threshold, in world coordinates. Samples
   within a hair of the threshold are first moved off it, and coincident
   triangles are dropped afterwards: scikit-image's Lewiner tables leave holes
   and doubled faces where samples or face tests tie at the level
   (scikit-image issues 8116 and 8109), which the cage builder would refuse.
3. Connected components (scipy's graph components) and their enclosed volume
   (divergence theorem, per face, summed per component); components below
   the volume threshold are dropped, and reported. By default the threshold is
   1% of the largest component's volume, so the floaters that training leaves
   in empty space go without anyone picking them by hand.
4. Optional decimation (libigl's edge collapse), then vertex colours from the
   NeRF, looking at each vertex along its inward normal.

Everything is written against a density callable (numpy (N,3) → (N,)) and a
colour callable, so it runs on analytic fields as well as on a NeRF.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from ..errors import EngineError
from ..memory import check_memory

DEFAULT_THRESHOLD = 10.0  # volume density of the surface (the NeRF's density is trunc_exp-activated)
DEFAULT_RESOLUTION = 256
DEFAULT_MIN_VOLUME_FRACTION = 0.01  # of the largest component, when no --min-volume is given
MAX_DESCRIBED = 50  # dropped components described one by one in the result

DensityFn = Callable[[np.ndarray], np.ndarray]
ColourFn = Callable[[np.ndarray, np.ndarray], np.ndarray]


@dataclass
class Component:
    volume: float
    faces: int
    centroid: tuple


@dataclass
class ExtractResult:
    vertices: np.ndarray  # (N, 3) float64, world
    faces: np.ndarray  # (F, 3) int64, outward normals
    colors: np.ndarray | None  # (N, 3) float in [0, 1]
    kept: list[Component]
    dropped: list[Component]  # the largest dropped components, at most MAX_DESCRIBED
    dropped_count: int  # all dropped components
    dropped_volume: float  # their total volume
    threshold: float
    min_volume: float
    timings: dict = field(default_factory=dict)
    cut: np.ndarray | None = None  # (N,) bool: vertices that close a cut by the region or the bounds
    notes: list = field(default_factory=list)  # what the region and the pick did, for the report
    part: np.ndarray | None = None  # (N,) int: which edit region each vertex was extracted in (several regions)

    def report(self) -> str:
        lines = list(self.notes) + [
            f"kept {len(self.kept)} component(s): {len(self.vertices)} vertices, {len(self.faces)} faces, "
            f"volume {sum(c.volume for c in self.kept):.4g}",
        ]
        if self.cut is not None and self.cut.any():
            lines.append(
                f"closed along the cut: {int(self.cut.sum())} vertices where the region or the box cuts "
                "the scene (the cage pins them)"
            )
        if self.dropped:
            big = max(self.dropped, key=lambda c: c.volume)
            lines.append(
                f"dropped {self.dropped_count} component(s) below volume {self.min_volume:.4g} "
                f"(total volume {self.dropped_volume:.4g}, largest {big.volume:.4g} at "
                f"({big.centroid[0]:.3f}, {big.centroid[1]:.3f}, {big.centroid[2]:.3f}))"
            )
        else:
            lines.append(f"dropped no component (volume threshold {self.min_volume:.4g})")
        return "\n".join(lines)


MAX_RESOLUTION = 2048
# Peak bytes per grid sample while extracting: the float32 grid, its padded copy, and the
# temporaries of moving samples off the level (marching cubes reads the padded copy in place).
BYTES_PER_SAMPLE = 16


def _is_number(x) -> bool:
    return isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, bool)


def check_extract_options(resolution=None, threshold=None, min_volume=None, decimate=None) -> None:
    """EngineError for options extraction cannot use (None means the default), before any sampling."""
    if resolution is not None and (
        not isinstance(resolution, (int, np.integer))
        or isinstance(resolution, bool)
        or not 2 <= resolution <= MAX_RESOLUTION
    ):
        raise EngineError(f"--resolution must be an integer from 2 to {MAX_RESOLUTION}, got {resolution!r}")
    if threshold is not None and not (_is_number(threshold) and np.isfinite(threshold) and threshold >= 0):
        raise EngineError(f"--threshold must be a finite density >= 0, got {threshold!r}")
    if min_volume is not None and not (_is_number(min_volume) and np.isfinite(min_volume) and min_volume >= 0):
        raise EngineError(f"--min-volume must be a finite volume >= 0, got {min_volume!r}")
    if decimate is not None and (
        not isinstance(decimate, (int, np.integer)) or isinstance(decimate, bool) or decimate < 4
    ):
        raise EngineError(f"--decimate must be a face count of at least 4, got {decimate!r}")


def check_grid_memory(resolution: int, shape=None) -> None:
    """EngineError, before sampling, when the grid (`resolution`^3 samples, or `shape`) cannot fit in memory."""
    count = float(np.prod(shape)) if shape is not None else float(resolution) ** 3
    check_memory(
        BYTES_PER_SAMPLE * count,
        f"extraction at resolution {resolution} ({int(count)} density samples)",
        "lower the resolution",
    )


def _bounds(bounds) -> np.ndarray:
    b = np.asarray(bounds, dtype=np.float64).reshape(2, 3)
    if not np.all(b[1] > b[0]):
        raise EngineError(f"extraction bounds must have max > min on every axis, got {b.tolist()}")
    return b


@dataclass(frozen=True)
class Lattice:
    """The sample points of an extraction: world = origin + steps @ (i, j, k)."""

    origin: np.ndarray  # (3,) world position of sample (0, 0, 0)
    steps: np.ndarray  # (3, 3): column a is the world step along index axis a
    shape: tuple  # samples per axis

    def to_world(self, index: np.ndarray) -> np.ndarray:
        return self.origin + np.asarray(index, dtype=np.float64) @ self.steps.T

    def to_index(self, points: np.ndarray) -> np.ndarray:
        return np.linalg.solve(self.steps, (np.asarray(points, dtype=np.float64) - self.origin).T).T

    @property
    def spacing(self) -> np.ndarray:
        return np.linalg.norm(self.steps, axis=0)


def box_lattice(bounds, resolution: int) -> Lattice:
    """`resolution` samples per axis from the box's min corner to its max corner."""
    b = _bounds(bounds)
    return Lattice(b[0], np.diag((b[1] - b[0]) / (resolution - 1)), (resolution,) * 3)


def region_lattice(region, resolution: int) -> Lattice:
    """Samples spanning an edit region exactly, `resolution` along its longest side and the same
    spacing (to within rounding) along the others, so a small object gets the whole resolution."""
    pitch = float(region.size.max()) / (resolution - 1)
    shape = tuple(int(max(2, round(float(s) / pitch) + 1)) for s in region.size)
    h = region.size / (np.array(shape) - 1)
    return Lattice(region.to_world(-region.half), region.rotation * h, shape)


def sample_lattice(
    density_fn: DensityFn, lattice: Lattice, chunk: int = 1 << 18, progress: bool = False, clip_bounds=None
) -> tuple[np.ndarray, np.ndarray | None]:
    """(grid (n0, n1, n2) float32 densities at the lattice's points, mask of the samples outside
    `clip_bounds` (their density is not asked: they count as empty), or None without clipping)."""
    nx, ny, nz = lattice.shape
    check_grid_memory(max(lattice.shape), lattice.shape)
    grid = np.zeros(lattice.shape, dtype=np.float32)
    outside = np.zeros(lattice.shape, dtype=bool) if clip_bounds is not None else None
    I, J = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")  # noqa: E741 (grid indices i, j)
    slab = max(1, chunk // (nx * ny))
    starts = range(0, nz, slab)
    if progress:
        from tqdm import tqdm

        starts = tqdm(starts, desc="density grid", unit="slab", file=sys.stderr)
    for k0 in starts:
        ks = np.arange(k0, min(nz, k0 + slab))
        idx = np.empty((nx, ny, len(ks), 3))
        idx[..., 0], idx[..., 1], idx[..., 2] = I[..., None], J[..., None], ks
        P = lattice.to_world(idx.reshape(-1, 3))
        if clip_bounds is None:
            d = np.asarray(density_fn(P), dtype=np.float32)
        else:
            lo, hi = clip_bounds
            out = np.any((P < lo) | (P > hi), axis=1)
            d = np.zeros(len(P), dtype=np.float32)
            if not out.all():
                d[~out] = np.asarray(density_fn(P[~out]), dtype=np.float32)
            outside[:, :, ks] = out.reshape(nx, ny, len(ks))
        grid[:, :, ks] = d.reshape(nx, ny, len(ks))
    if not np.isfinite(grid).all():
        raise EngineError("the density field returned non-finite values")
    return grid, outside


def sample_grid(
    density_fn: DensityFn, bounds, resolution: int = DEFAULT_RESOLUTION, chunk: int = 1 << 18, progress: bool = False
) -> np.ndarray:
    """(R, R, R) float32 densities at the grid's corner points, x fastest-varying last (index [i, j, k] =
    x_i, y_j, z_k)."""
    if resolution < 2 or resolution > MAX_RESOLUTION:
        raise EngineError(f"grid resolution must be between 2 and {MAX_RESOLUTION}, got {resolution}")
    return sample_lattice(density_fn, box_lattice(bounds, resolution), chunk, progress)[0]


PICK_SEARCH_FRACTION = 0.03  # of the lattice's longest side: how far from the pick point a dense sample is looked for


def pick_component(grid: np.ndarray, threshold: float, lattice: Lattice, point) -> tuple[np.ndarray, str]:
    """(mask of the samples above `threshold` 6-connected to the one nearest `point`, report line).

    The pick point is where the artist clicked (or the 3D cursor): on the surface rather than
    inside it, so the nearest dense sample within a few percent of the grid counts."""
    from scipy import ndimage

    q = lattice.to_index(np.asarray(point, dtype=np.float64).reshape(1, 3))[0]
    shape = np.array(grid.shape)
    r = max(2, int(np.ceil(PICK_SEARCH_FRACTION * shape.max())))
    p = np.asarray(point, dtype=np.float64).ravel()
    where = f"({p[0]:.3g}, {p[1]:.3g}, {p[2]:.3g})"
    if np.any(q < -r) or np.any(q > shape - 1 + r):
        raise EngineError(
            f"the pick point {where} lies outside the sampled region: put it on the object, inside "
            "the edit region and the NeRF's box"
        )
    lo = np.clip(np.floor(q).astype(int) - r, 0, shape - 1)
    hi = np.clip(np.ceil(q).astype(int) + r, 0, shape - 1) + 1
    window = grid[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]]
    dense = np.argwhere(window > threshold)
    if len(dense) == 0:
        radius = float(r * lattice.spacing.max())
        raise EngineError(
            f"the pick point {where} is in empty space: the largest density within {radius:.3g} of it "
            f"is {float(window.max()):.4g}, not above the threshold {threshold:g}; put it on the object"
        )
    seed = lo + dense[np.argmin(np.linalg.norm((dense + lo) - q, axis=1))]
    labels, count = ndimage.label(grid > threshold)
    mask = labels == labels[tuple(seed)]
    line = (
        f"picked the part connected to {where}: {int(mask.sum())} of {int((labels > 0).sum())} dense samples "
        f"({count - 1} other part(s) left out)"
    )
    return mask, line


def _cut_vertices(verts_index: np.ndarray, forced_empty: np.ndarray) -> np.ndarray:
    """Marching cubes vertices lying on a grid edge to a forced-empty sample (padding, outside the
    bounds): where the region or the box cut the scene and the surface was closed."""
    lo = np.floor(verts_index + 1e-6).astype(np.int64)
    hi = np.ceil(verts_index - 1e-6).astype(np.int64)
    upper = np.array(forced_empty.shape) - 1
    lo, hi = np.clip(lo, 0, upper), np.clip(hi, 0, upper)
    return forced_empty[lo[:, 0], lo[:, 1], lo[:, 2]] | forced_empty[hi[:, 0], hi[:, 1], hi[:, 2]]


def component_volumes(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(labels per face, signed enclosed volume per component) of a triangle mesh.

    Components are those of the vertex graph (scipy's connected components on
    the faces' edges: linear time, where trimesh's face adjacency sorts all
    edges first); marching cubes' vertices are shared, so this is the surface's
    connectivity.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = len(vertices)
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]]])
    graph = coo_matrix((np.ones(len(e), dtype=np.int8), (e[:, 0], e[:, 1])), shape=(n, n))
    _, vlabels = connected_components(graph, directed=False)
    _, labels = np.unique(vlabels[faces[:, 0]], return_inverse=True)
    labels = labels.ravel()
    tri = vertices[faces]
    vol_face = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])) / 6.0
    return labels, np.bincount(labels, weights=vol_face)


def _off_the_level(grid: np.ndarray, level: float) -> np.ndarray:
    """The grid (float32, as marching cubes reads it) with samples closer to `level` than a
    relative 1e-5 moved to level +- that much, on their own side: where a sample equals the
    level, scikit-image's cubes disagree on the faces they share and leave holes (scikit-image issue 8116).
    The surface moves by at most that tolerance over the local density slope."""
    grid = np.asarray(grid, dtype=np.float32)
    eps = np.float32(1e-5 * max(abs(level), 1.0))
    lvl = np.float32(level)
    near = np.abs(grid - lvl) < eps
    if not near.any():
        return grid
    return np.where(near, np.where(grid >= lvl, lvl + eps, lvl - eps), grid)


def _drop_coincident_faces(faces: np.ndarray) -> np.ndarray:
    """Faces with the vertices of another face: a pair wound oppositely encloses nothing and both
    go; of same-wound copies one stays. Marching cubes makes such pairs where a face's ambiguity
    test ties at zero (scikit-image issue 8109), leaving edges shared by four faces."""
    key = np.sort(faces, axis=1)
    _, group, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    group = group.ravel()
    repeated = np.flatnonzero(counts[group] > 1)
    if len(repeated) == 0:
        return faces
    # +1 where the face is an even permutation (a rotation) of its sorted vertices.
    f, k = faces[repeated], key[repeated]
    even = (f == k).all(1) | (f == k[:, [1, 2, 0]]).all(1) | (f == k[:, [2, 0, 1]]).all(1)
    sign = np.where(even, 1, -1)
    net = np.zeros(len(counts), dtype=np.int64)
    np.add.at(net, group[repeated], sign)
    keep = np.ones(len(faces), dtype=bool)
    keep[repeated] = False
    # One face per group, wound as the group's majority (a cancelling group, net 0, keeps none).
    majority = repeated[sign == np.sign(net[group[repeated]])]
    _, first = np.unique(group[majority], return_index=True)
    keep[majority[first]] = True
    return faces[keep]


def extract_mesh(
    density_fn: DensityFn,
    bounds,
    resolution: int = DEFAULT_RESOLUTION,
    threshold: float = DEFAULT_THRESHOLD,
    min_volume: float | None = None,
    colour_fn: ColourFn | None = None,
    decimate: int | None = None,
    progress: bool = False,
    grid: np.ndarray | None = None,
    region=None,
    pick=None,
) -> ExtractResult:
    """Surface of {density > threshold} over `bounds` (or over the edit `region` within them),
    floaters removed; with `pick` (a world point) only the part connected to it. See the module
    docstring. `grid` is a density grid sampled over `bounds` already (tests)."""
    from skimage.measure import marching_cubes

    check_extract_options(resolution if grid is None else None, threshold, min_volume, decimate)
    b = _bounds(bounds)
    timings, notes = {}, []
    t0 = time.perf_counter()
    outside = None
    if region is not None:
        from .region import check_region_in_box

        check_region_in_box(region, b)
        lattice = region_lattice(region, resolution)
        grid, outside = sample_lattice(density_fn, lattice, progress=progress, clip_bounds=b)
        where = f"the {region.describe()}"
        notes.append(
            f"{region.describe()}: {'x'.join(str(n) for n in lattice.shape)} samples, spacing "
            f"{float(lattice.spacing.max()):.3g}"
            + (f"; {outside.mean():.0%} of it outside the NeRF's box" if outside.any() else "")
        )
    else:
        if grid is None:
            grid = sample_grid(density_fn, b, resolution, progress=progress)
        lattice = box_lattice(b, grid.shape[0])
        where = f"bounds {b.tolist()}"
    timings["grid_s"] = time.perf_counter() - t0
    dmax = float(grid.max())
    if dmax <= threshold:
        raise EngineError(
            f"the density grid is empty: the largest density over the {grid.size} samples in {where} "
            f"is {dmax:.4g}, not above the threshold {threshold:g}"
        )
    empty = min(float(grid.min()), threshold) - 1.0
    if pick is not None:
        t0 = time.perf_counter()
        mask, line = pick_component(grid, threshold, lattice, pick)
        grid = np.where((grid > threshold) & ~mask, np.float32(empty), grid)
        notes.append(line)
        timings["pick_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    if outside is not None and outside.any():
        grid = np.where(outside, np.float32(empty), grid)
    padded = _off_the_level(np.pad(grid, 1, mode="constant", constant_values=empty), threshold)
    verts_index, faces, _, _ = marching_cubes(padded, level=threshold)
    forced_empty = np.pad(
        outside if outside is not None else np.zeros(grid.shape, dtype=bool), 1, mode="constant", constant_values=True
    )
    cut = _cut_vertices(verts_index, forced_empty)
    # Vertices stay as marching cubes shares them (one per grid edge), none merged by position:
    # near a sample at the level several lie within float precision of each other, and merging
    # some of them but not others is what pinches the surface into non-manifold edges.
    verts = lattice.to_world(verts_index.astype(np.float64) - 1.0)
    faces = _drop_coincident_faces(faces.astype(np.int64))
    timings["marching_cubes_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    labels, vols = component_volumes(verts, faces)
    if np.sum(vols) < 0:  # marching cubes' orientation: make normals point out of the dense region
        faces = faces[:, [0, 2, 1]]
        vols = -vols
    avol = np.abs(vols)
    if min_volume is None:
        min_volume = DEFAULT_MIN_VOLUME_FRACTION * float(avol.max())
    keep_comp = avol >= min_volume
    if not keep_comp.any():
        raise EngineError(
            f"no component left above the volume threshold {min_volume:.4g}: the largest component's volume is "
            f"{avol.max():.4g}"
        )

    def describe(c):
        fm = labels == c
        return Component(
            volume=float(avol[c]),
            faces=int(fm.sum()),
            centroid=tuple(float(x) for x in verts[faces[fm]].reshape(-1, 3).mean(0)),
        )

    kept = [describe(c) for c in np.flatnonzero(keep_comp)]
    dropped_ids = np.flatnonzero(~keep_comp)
    # Describe only the largest dropped components individually (there can be thousands).
    dropped = [describe(c) for c in dropped_ids[np.argsort(-avol[dropped_ids])][:MAX_DESCRIBED]]
    faces = faces[keep_comp[labels]]
    used = np.unique(faces)
    remap = np.full(len(verts), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    verts, faces, cut = verts[used], remap[faces], cut[used]
    timings["filter_s"] = time.perf_counter() - t0

    if decimate is not None and decimate < len(faces):
        import igl
        from scipy.spatial import cKDTree

        t0 = time.perf_counter()
        out = igl.decimate(np.asfortranarray(verts), np.asfortranarray(faces.astype(np.int32)), int(decimate))
        decimated = np.ascontiguousarray(out[0])
        if cut.any():  # a decimated vertex is on the cut where its nearest original vertex was
            cut = cut[cKDTree(verts).query(decimated)[1]]
        else:
            cut = np.zeros(len(decimated), dtype=bool)
        verts, faces = decimated, np.ascontiguousarray(out[1], dtype=np.int64)
        timings["decimate_s"] = time.perf_counter() - t0

    colors = None
    if colour_fn is not None:
        import trimesh

        t0 = time.perf_counter()
        normals = trimesh.Trimesh(vertices=verts, faces=faces, process=False).vertex_normals
        colors = np.clip(np.asarray(colour_fn(verts, -normals), dtype=np.float64), 0.0, 1.0)
        timings["colour_s"] = time.perf_counter() - t0
    return ExtractResult(
        verts,
        faces,
        colors,
        kept,
        dropped,
        len(dropped_ids),
        float(avol[dropped_ids].sum()),
        float(threshold),
        float(min_volume),
        timings,
        cut=cut,
        notes=notes,
    )


# ------------------------------------------------------------------ NeRF glue


def density_fn_of(nerf, chunk: int = 1 << 18) -> DensityFn:
    """numpy (N,3) → numpy (N,) density of a NerfModel (checkpoint.load_nerf), chunked, without gradients."""
    import torch

    def fn(points: np.ndarray) -> np.ndarray:
        out = np.empty(len(points), dtype=np.float32)
        with torch.no_grad():
            for s in range(0, len(points), chunk):
                p = torch.as_tensor(points[s : s + chunk], dtype=torch.float32, device=nerf.device)
                out[s : s + chunk] = nerf.density(p).float().cpu().numpy()
        return out

    return fn


def colour_fn_of(nerf, chunk: int = 1 << 16) -> ColourFn:
    import torch

    def fn(points: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        out = np.empty((len(points), 3), dtype=np.float32)
        with torch.no_grad():
            for s in range(0, len(points), chunk):
                p = torch.as_tensor(points[s : s + chunk], dtype=torch.float32, device=nerf.device)
                d = torch.as_tensor(dirs[s : s + chunk], dtype=torch.float32, device=nerf.device)
                out[s : s + chunk] = nerf.query(p, d)[1].float().cpu().numpy()
        return out

    return fn


def extract_nerf_mesh(
    nerf,
    resolution: int | None = None,
    threshold: float | None = None,
    min_volume: float | None = None,
    decimate: int | None = None,
    progress: bool = False,
    region=None,
    pick=None,
) -> ExtractResult:
    """The surface of a loaded NeRF over its bounds (its inner box when unbounded) or over an edit
    region within them, floaters dropped, only the part connected to `pick` when given, vertex
    colours from the NeRF (what `extract` writes and the add-on's Extract Mesh imports). None means
    the default (a min_volume of 0 too: "automatic" in the add-on); a resolution of 0 is an error."""
    check_extract_options(resolution, threshold, min_volume, decimate)
    return extract_mesh(
        density_fn_of(nerf),
        nerf.aabb.detach().cpu().numpy().reshape(2, 3),
        resolution=int(resolution if resolution is not None else DEFAULT_RESOLUTION),
        threshold=float(threshold) if threshold is not None else DEFAULT_THRESHOLD,
        min_volume=float(min_volume) if min_volume else None,
        colour_fn=colour_fn_of(nerf),
        decimate=decimate,
        progress=progress,
        region=region,
        pick=pick,
    )


def extract_nerf_regions(
    nerf,
    regions: list,
    pick=None,
    resolution: int | None = None,
    threshold: float | None = None,
    min_volume: float | None = None,
    decimate: int | None = None,
    progress: bool = False,
) -> ExtractResult:
    """One surface per edit region of a loaded NeRF, in one mesh (`extract_regions`)."""
    return extract_regions(
        lambda region, point: extract_nerf_mesh(
            nerf, resolution, threshold, min_volume, decimate, progress, region=region, pick=point
        ),
        regions,
        pick,
    )


def extract_regions(extract_one, regions: list, pick=None) -> ExtractResult:
    """One surface per edit region (several objects of one capture, each edited on its own), in
    one mesh: `part` says which region each vertex came from. `extract_one(region, pick)` extracts
    one (extract_mesh with its options). The pick applies to the region that holds the pick
    point. Regions must not overlap (their cages would claim the same space)."""
    from .region import check_regions_apart

    check_regions_apart(regions)
    if len(regions) == 1:
        res = extract_one(regions[0], pick)
        res.part = np.zeros(len(res.vertices), dtype=np.int64)
        return res
    point = None if pick is None else np.asarray(pick, dtype=np.float64).reshape(1, 3)
    holder = next((i for i, r in enumerate(regions) if point is not None and r.contains(point)[0]), None)
    if point is not None and holder is None:
        raise EngineError(
            f"the pick point ({', '.join(f'{x:.3g}' for x in point[0])}) lies in none of the "
            f"{len(regions)} edit regions: put it on the object to keep, inside its region"
        )
    results = []
    for i, region in enumerate(regions):
        try:
            results.append(extract_one(region, pick if i == holder else None))
        except EngineError as error:
            raise EngineError(f"edit region {i + 1}: {error}") from None
    offsets = np.cumsum([0] + [len(r.vertices) for r in results])
    return ExtractResult(
        vertices=np.concatenate([r.vertices for r in results]),
        faces=np.concatenate([r.faces + o for r, o in zip(results, offsets)]),
        colors=None if any(r.colors is None for r in results) else np.concatenate([r.colors for r in results]),
        kept=[c for r in results for c in r.kept],
        dropped=[c for r in results for c in r.dropped],
        dropped_count=sum(r.dropped_count for r in results),
        dropped_volume=sum(r.dropped_volume for r in results),
        threshold=results[0].threshold,
        min_volume=min(r.min_volume for r in results),
        timings={k: sum(r.timings.get(k, 0.0) for r in results) for k in results[0].timings},
        cut=np.concatenate([r.cut for r in results]),
        notes=[f"edit region {i + 1}: {line}" for i, r in enumerate(results) for line in r.notes],
        part=np.repeat(np.arange(len(results)), np.diff(offsets)),
    )


def first_dense_point(
    density_fn: DensityFn, origin, direction, bounds, threshold: float = DEFAULT_THRESHOLD, samples: int = 2048
) -> tuple[np.ndarray | None, float, float]:
    """Where a ray first meets {density > threshold} inside `bounds`: (point or None, distance
    along the unit ray, largest density seen). What a click on the NeRF in the viewport picks.

    The ray is sampled at `samples` points across the box (slab test), then the crossing is
    refined by bisection between the last sample below and the first above the threshold."""
    o = np.asarray(origin, dtype=np.float64).ravel()
    d = np.asarray(direction, dtype=np.float64).ravel()
    if o.shape != (3,) or d.shape != (3,) or not (np.isfinite(o).all() and np.isfinite(d).all()):
        raise EngineError(f"a pick ray needs a finite origin and direction, got {o.tolist()} and {d.tolist()}")
    n = np.linalg.norm(d)
    if n < 1e-12:
        raise EngineError("a pick ray needs a non-zero direction")
    d = d / n
    b = _bounds(bounds)
    with np.errstate(divide="ignore", invalid="ignore"):
        t0, t1 = (b[0] - o) / d, (b[1] - o) / d
    near = np.nanmax(np.where(np.isfinite(np.minimum(t0, t1)), np.minimum(t0, t1), -np.inf))
    far = np.nanmin(np.where(np.isfinite(np.maximum(t0, t1)), np.maximum(t0, t1), np.inf))
    near = max(near, 0.0)
    if not far > near:
        return None, float("nan"), 0.0
    t = np.linspace(near, far, samples)
    dens = np.asarray(density_fn(o + t[:, None] * d), dtype=np.float64)
    above = np.flatnonzero(dens > threshold)
    if len(above) == 0:
        return None, float("nan"), float(dens.max())
    k = int(above[0])
    if k == 0:
        return o + t[0] * d, float(t[0]), float(dens.max())
    lo, hi = t[k - 1], t[k]
    for _ in range(20):
        mid = 0.5 * (lo + hi)
        if float(np.asarray(density_fn((o + mid * d)[None]))[0]) > threshold:
            hi = mid
        else:
            lo = mid
    return o + hi * d, float(hi), float(dens.max())
