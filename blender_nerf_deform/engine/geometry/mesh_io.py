"""File formats of the geometry stages, pure numpy (the add-on may use them).

- PLY: binary little-endian triangle meshes with optional 8-bit vertex colours
  and an optional `nerf_cut` uchar vertex property (1 on the vertices that
  close a cut by an edit region, which the cage pins; other tools ignore it)
  (what `extract` writes); reading accepts binary little/big-endian and ASCII
  PLY with float/double/int/uchar vertex properties and triangle faces.
- Cage `.npz`: `vertices` (N,3 float64), `tets` (M,4 int64) and optional
  extras (margin, bounds, `pinned_vertices` (K,) int64 at an edit region's
  cut, the region's `region_center/size/rotation_euler`, ...). Loaded with `allow_pickle=False`: no code runs.

Writes go to a temporary file in the same folder, then `os.replace`: a crash
never leaves a half-written file under the target name.
"""

from __future__ import annotations

import zipfile
import zlib
from pathlib import Path

import numpy as np

from ..errors import EngineError
from ..files import atomic_write
from .poses import check_coordinates


def write_ply(
    path,
    vertices: np.ndarray,
    faces: np.ndarray,
    colors: np.ndarray | None = None,
    cut: np.ndarray | None = None,
    part: np.ndarray | None = None,
) -> None:
    """Binary little-endian PLY; `colors` (N,3) uint8 or float in [0,1] become red/green/blue uchar;
    `cut` (N,) bool becomes the `nerf_cut` uchar property (written only when some vertex is cut),
    `part` (N,) int the `nerf_part` uchar property (the edit region; written when there are several)."""
    vertices = np.asarray(vertices, dtype=np.float32)
    faces = np.asarray(faces, dtype=np.int32)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
        raise EngineError(f"write_ply needs (N,3) vertices and (F,3) faces, got {vertices.shape} and {faces.shape}")
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if colors is not None:
        colors = np.asarray(colors)
        if colors.dtype != np.uint8:
            colors = np.clip(np.round(np.asarray(colors, dtype=np.float64) * 255.0), 0, 255).astype(np.uint8)
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    if cut is not None:
        cut = np.asarray(cut, dtype=bool).ravel()
        if len(cut) != len(vertices):
            raise EngineError(f"write_ply: {len(cut)} cut flags for {len(vertices)} vertices")
        cut = cut if cut.any() else None
    if cut is not None:
        fields += [("nerf_cut", "u1")]
    if part is not None:
        part = np.asarray(part, dtype=np.int64).ravel()
        if len(part) != len(vertices) or (len(part) and (part.min() < 0 or part.max() > 255)):
            raise EngineError("write_ply: part labels must be 0..255, one per vertex")
        part = part if len(part) and part.max() > 0 else None
    if part is not None:
        fields += [("nerf_part", "u1")]
    vrec = np.empty(len(vertices), dtype=fields)
    vrec["x"], vrec["y"], vrec["z"] = vertices.T
    if colors is not None:
        vrec["red"], vrec["green"], vrec["blue"] = colors[:, :3].T
    if cut is not None:
        vrec["nerf_cut"] = cut
    if part is not None:
        vrec["nerf_part"] = part
    frec = np.empty(len(faces), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    frec["n"] = 3
    frec["i"] = faces
    header = [
        "ply",
        "format binary_little_endian 1.0",
        "comment blender_nerf_deform",
        f"element vertex {len(vertices)}",
    ]
    header += ["property float x", "property float y", "property float z"]
    if colors is not None:
        header += ["property uchar red", "property uchar green", "property uchar blue"]
    if cut is not None:
        header += ["property uchar nerf_cut"]
    if part is not None:
        header += ["property uchar nerf_part"]
    header += [f"element face {len(faces)}", "property list uchar int vertex_indices", "end_header"]

    def write(f):
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(vrec.tobytes())
        f.write(frec.tobytes())

    atomic_write(path, write)


_PLY_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}


def _ply_header(path: Path, data: bytes) -> tuple[str, list, int]:
    """(format, [[element name, count, properties]], offset of the body) of a PLY's header."""
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise EngineError(f"{path} is not a PLY file (no 'ply' magic or no end_header)")
    newline = data.find(b"\n", end)
    if newline < 0 or data[end + len(b"end_header") : newline].strip():
        raise EngineError(f"{path}: the PLY header's end_header line has no newline after it (truncated file?)")
    fmt, elements = None, []
    for number, line in enumerate(data[:end].decode("ascii", "replace").splitlines(), start=1):
        tok = line.split()
        if not tok:
            continue
        if tok[0] == "format" and len(tok) > 1:
            fmt = tok[1]
        elif tok[0] == "element":
            if len(tok) != 3 or not tok[2].isdigit():
                raise EngineError(
                    f"{path}: header line {number} {line.strip()!r} must be 'element <name> <count>' "
                    "with a whole-number count"
                )
            elements.append([tok[1], int(tok[2]), []])
        elif tok[0] == "property" and elements:
            props = tok[1:]
            types = props[1:3] if props and props[0] == "list" else props[:1]
            if len(props) != (4 if props and props[0] == "list" else 2) or any(t not in _PLY_TYPES for t in types):
                raise EngineError(f"{path}: header line {number} {line.strip()!r} is not a property of a known type")
            elements[-1][2].append(props)
    if fmt not in ("binary_little_endian", "binary_big_endian", "ascii"):
        raise EngineError(f"{path}: unsupported PLY format {fmt!r}")
    return fmt, elements, newline + 1


def _binary_element(path, data, offset, name, count, dtype) -> np.ndarray:
    need = dtype.itemsize * count
    if offset + need > len(data):
        raise EngineError(
            f"{path} is truncated: element {name!r} needs {need} bytes at byte {offset}, "
            f"the file has {len(data) - offset} left"
        )
    return np.frombuffer(data, dtype, count, offset)


def _ascii_rows(path, rows, pos, name, count) -> list[list[str]]:
    if pos + count > len(rows):
        raise EngineError(
            f"{path} is truncated: element {name!r} needs {count} rows, the file has {max(len(rows) - pos, 0)} left"
        )
    return [r.split() for r in rows[pos : pos + count]]


def read_ply(path, with_cut: bool = False, with_part: bool = False) -> tuple:
    """(vertices (N,3) float64, faces (F,3) int64, colours (N,3) uint8 or None), with `with_cut`
    the `nerf_cut` flags (N,) bool or None, with `with_part` the `nerf_part` labels (N,) int64
    or None (after the cut flags). Triangles only.

    Every count, row and byte is checked against the header (a truncated or malformed file is an
    EngineError naming it), and vertices must be finite."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise EngineError(f"cannot read mesh {path}: {exc.strerror}") from None
    fmt, elements, body_start = _ply_header(path, data)
    order = "<" if fmt == "binary_little_endian" else ">"
    verts = colors = faces = cut = part = None
    if fmt == "ascii":
        rows = [r for r in data[body_start:].decode("ascii", "replace").splitlines() if r.strip()]
        pos = 0
    offset = body_start
    for name, count, props in elements:
        is_list = any(p[0] == "list" for p in props)
        if is_list and (name != "face" or len(props) != 1):
            raise EngineError(f"{path}: unsupported list element {name!r}")
        if fmt == "ascii":
            chunk = _ascii_rows(path, rows, pos, name, count)
            pos += count
            if is_list:
                if any(len(r) != 4 or r[0] != "3" for r in chunk):
                    bad = next(i for i, r in enumerate(chunk) if len(r) != 4 or r[0] != "3")
                    raise EngineError(
                        f"{path}: face {bad} is {' '.join(chunk[bad])!r}: only triangle faces ('3 i j k') are supported"
                    )
                try:
                    faces = np.array([r[1:] for r in chunk], dtype=np.int64).reshape(-1, 3)
                except ValueError:
                    raise EngineError(f"{path}: face indices must be whole numbers") from None
                continue
            short = [i for i, r in enumerate(chunk) if len(r) != len(props)]
            if short:
                raise EngineError(
                    f"{path}: {name} row {short[0]} has {len(chunk[short[0]])} values, the header "
                    f"declares {len(props)} properties"
                )
            try:
                table = np.array(chunk, dtype=np.float64).reshape(count, len(props))
            except ValueError:
                raise EngineError(f"{path}: {name} rows hold values that are not numbers") from None
            cols = {p[1]: table[:, i] for i, p in enumerate(props)}
        else:
            if is_list:
                _, ctype, itype, _pname = props[0]
                ct, it = np.dtype(order + _PLY_TYPES[ctype]), np.dtype(order + _PLY_TYPES[itype])
                rec = np.dtype([("n", ct), ("i", it, (3,))])
                if count and _binary_element(path, data, offset, name, 1, ct)[0] != 3:
                    raise EngineError(f"{path}: only triangle faces are supported")
                arr = _binary_element(path, data, offset, name, count, rec)
                if count and np.any(arr["n"] != 3):
                    raise EngineError(f"{path}: only triangle faces are supported")
                faces = arr["i"].astype(np.int64)
                offset += rec.itemsize * count
                continue
            rec = np.dtype([(p[1], order + _PLY_TYPES[p[0]]) for p in props])
            arr = _binary_element(path, data, offset, name, count, rec)
            offset += rec.itemsize * count
            cols = {p[1]: arr[p[1]] for p in props}
        if name == "vertex":
            try:
                verts = np.stack([cols["x"], cols["y"], cols["z"]], axis=1).astype(np.float64)
            except KeyError:
                raise EngineError(f"{path}: vertex element lacks x/y/z") from None
            if all(c in cols for c in ("red", "green", "blue")):
                colors = np.stack([cols["red"], cols["green"], cols["blue"]], axis=1).astype(np.uint8)
            if "nerf_cut" in cols:
                cut = np.asarray(cols["nerf_cut"]) != 0
            if "nerf_part" in cols:
                part = np.asarray(cols["nerf_part"]).astype(np.int64)
    if verts is None or faces is None:
        raise EngineError(f"{path}: a mesh needs vertex and face elements")
    bad = np.flatnonzero(~np.isfinite(verts).all(axis=1))
    if len(bad):
        raise EngineError(
            f"{path}: vertex {bad[0]} has non-finite coordinates {verts[bad[0]].tolist()} "
            f"({len(bad)} of {len(verts)} vertices do)"
        )
    if faces.size and (faces.min() < 0 or faces.max() >= len(verts)):
        raise EngineError(f"{path}: faces index vertices outside 0..{len(verts) - 1}")
    return (verts, faces, colors) + ((cut,) if with_cut else ()) + ((part,) if with_part else ())


def save_cage(path, vertices: np.ndarray, tets: np.ndarray, **extra) -> None:
    """Write a cage `.npz` atomically: `vertices` float64, `tets` int64, plus plain-array extras."""
    arrays = {"vertices": np.asarray(vertices, dtype=np.float64), "tets": np.asarray(tets, dtype=np.int64)}
    arrays.update({k: np.asarray(v) for k, v in extra.items()})

    def write(f):
        np.savez(f, **arrays)

    atomic_write(path, write)


def load_cage(path, validate: bool = True) -> dict[str, np.ndarray]:
    """Read a cage `.npz` (no pickles, so no code runs). Always checked: the file is an archive,
    `vertices` are finite numbers (N,3), `tets` are (M,4) integers indexing them (the point-location
    kernels read what they index unchecked). With `validate`, every tet must have positive volume."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            magic = f.read(6)
    except FileNotFoundError:
        raise EngineError(f"cage file {path} does not exist") from None
    except OSError as exc:
        raise EngineError(f"cannot read cage {path}: {exc.strerror or exc}") from None
    if magic.startswith(b"\x93NUMPY"):
        raise EngineError(
            f"cannot read cage {path}: it is a single .npy array, not a cage .npz (an archive of `vertices` and `tets`)"
        )
    if not magic.startswith(b"PK"):
        raise EngineError(f"cannot read cage {path}: it is not a cage file (not an .npz archive)")
    try:
        with np.load(path, allow_pickle=False) as z:
            out = {}
            for k in z.files:
                try:
                    out[k] = z[k]
                except ValueError as exc:
                    if "pickle" in str(exc):
                        raise EngineError(
                            f"cannot read cage {path}: array `{k}` holds Python objects (pickled "
                            "data), which a cage file never does"
                        ) from None
                    raise
    except (ValueError, OSError, EOFError, zipfile.BadZipFile, zlib.error, KeyError) as exc:
        raise EngineError(
            f"cannot read cage {path}: it is not a cage file ({str(exc).splitlines()[0][:160] or type(exc).__name__})"
        ) from None
    for key in ("vertices", "tets"):
        if key not in out:
            raise EngineError(f"cage {path} has no `{key}` array")
    V, T = out["vertices"], out["tets"]
    if V.ndim != 2 or V.shape[1] != 3 or T.ndim != 2 or T.shape[1] != 4 or not np.issubdtype(T.dtype, np.integer):
        raise EngineError(
            f"cage {path}: `vertices` must be (N,3) and `tets` (M,4) int, got {V.shape} and {T.shape} {T.dtype}"
        )
    if not (np.issubdtype(V.dtype, np.floating) or np.issubdtype(V.dtype, np.integer)):
        raise EngineError(f"cage {path}: `vertices` must be numbers, got an array of {V.dtype}")
    bad = np.flatnonzero(~np.isfinite(V).all(axis=1))
    if len(bad):
        raise EngineError(
            f"cage {path}: vertex {bad[0]} has non-finite coordinates {V[bad[0]].tolist()} "
            f"({len(bad)} of {len(V)} vertices do)"
        )
    check_coordinates(V, f"cage {path}")
    if len(T) == 0:
        raise EngineError(f"cage {path} has no tets")
    if T.min() < 0 or T.max() >= len(V):
        raise EngineError(f"cage {path}: tets index vertices outside 0..{len(V) - 1}")
    out["vertices"], out["tets"] = V.astype(np.float64), T.astype(np.int64)
    if "pinned_vertices" in out:  # cage vertices pinned at an edit region's cut (cage.cut_pins)
        P = out["pinned_vertices"]
        if P.ndim != 1 or not np.issubdtype(P.dtype, np.integer) or (len(P) and (P.min() < 0 or P.max() >= len(V))):
            raise EngineError(f"cage {path}: `pinned_vertices` must be a list of vertex indices in 0..{len(V) - 1}")
        out["pinned_vertices"] = P.astype(np.int64)
    if validate:
        from .barycentric import signed_volumes  # pure numpy

        vol = signed_volumes(out["vertices"], out["tets"])
        scale = float(np.ptp(V, axis=0).max()) ** 3
        bad = np.flatnonzero(vol <= 1e-12 * scale)
        if len(bad):
            raise EngineError(
                f"degenerate cage {path}: {len(bad)} of {len(T)} tets have zero or negative volume "
                f"(first: tet {bad[0]})"
            )
    return out
