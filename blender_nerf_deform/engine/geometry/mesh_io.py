"""File formats of the geometry stages, pure numpy (the add-on may use them).

- PLY: binary little-endian triangle meshes with optional 8-bit vertex colours
  (what `extract` writes); reading accepts binary little/big-endian and ASCII
  PLY with float/double/int/uchar vertex properties and triangle faces.
- Cage `.npz`: `vertices` (N,3 float64), `tets` (M,4 int64) and optional
  extras (margin, bounds, ...). Loaded with `allow_pickle=False`: no code runs.

Writes go to a temporary file in the same folder, then `os.replace`: a crash
never leaves a half-written file under the target name.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import EngineError
from ..files import atomic_write


def write_ply(path, vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray | None = None) -> None:
    """Binary little-endian PLY; `colors` (N,3) uint8 or float in [0,1] become red/green/blue uchar."""
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
    vrec = np.empty(len(vertices), dtype=fields)
    vrec["x"], vrec["y"], vrec["z"] = vertices.T
    if colors is not None:
        vrec["red"], vrec["green"], vrec["blue"] = colors[:, :3].T
    frec = np.empty(len(faces), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    frec["n"] = 3
    frec["i"] = faces
    header = ["ply", "format binary_little_endian 1.0", "comment blender_nerf_deform", f"element vertex {len(vertices)}"]
    header += ["property float x", "property float y", "property float z"]
    if colors is not None:
        header += ["property uchar red", "property uchar green", "property uchar blue"]
    header += [f"element face {len(faces)}", "property list uchar int vertex_indices", "end_header"]

    def write(f):
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(vrec.tobytes())
        f.write(frec.tobytes())

    atomic_write(path, write)


_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


def read_ply(path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(vertices (N,3) float64, faces (F,3) int64, colours (N,3) uint8 or None). Triangles only."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise EngineError(f"cannot read mesh {path}: {exc.strerror}") from None
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise EngineError(f"{path} is not a PLY file (no 'ply' magic or no end_header)")
    body_start = data.index(b"\n", end) + 1
    lines = data[:end].decode("ascii", "replace").splitlines()
    fmt, elements = None, []
    for line in lines:
        tok = line.split()
        if not tok:
            continue
        if tok[0] == "format":
            fmt = tok[1]
        elif tok[0] == "element":
            elements.append([tok[1], int(tok[2]), []])
        elif tok[0] == "property" and elements:
            elements[-1][2].append(tok[1:])
    if fmt not in ("binary_little_endian", "binary_big_endian", "ascii"):
        raise EngineError(f"{path}: unsupported PLY format {fmt!r}")
    order = "<" if fmt == "binary_little_endian" else ">"
    verts = colors = faces = None
    if fmt == "ascii":
        rows = data[body_start:].decode("ascii", "replace").split("\n")
        pos = 0
    offset = body_start
    for name, count, props in elements:
        is_list = any(p[0] == "list" for p in props)
        if fmt == "ascii":
            chunk = rows[pos : pos + count]
            pos += count
            if is_list:
                if name == "face":
                    lists = [np.array(r.split(), dtype=np.int64) for r in chunk]
                    if any(len(l) == 0 or l[0] != 3 for l in lists):
                        raise EngineError(f"{path}: only triangle faces are supported")
                    faces = np.array([l[1:4] for l in lists], dtype=np.int64).reshape(-1, 3)
                continue
            table = np.array([r.split() for r in chunk], dtype=np.float64).reshape(count, len(props))
            cols = {p[1]: table[:, i] for i, p in enumerate(props)}
        else:
            if is_list:
                if name != "face" or len(props) != 1:
                    raise EngineError(f"{path}: unsupported list element {name!r}")
                _, ctype, itype, _pname = props[0]
                ct, it = np.dtype(order + _PLY_TYPES[ctype]), np.dtype(order + _PLY_TYPES[itype])
                rec = np.dtype([("n", ct), ("i", it, (3,))])
                if count and np.frombuffer(data, ct, 1, offset)[0] != 3:
                    raise EngineError(f"{path}: only triangle faces are supported")
                arr = np.frombuffer(data, rec, count, offset)
                if count and np.any(arr["n"] != 3):
                    raise EngineError(f"{path}: only triangle faces are supported")
                faces = arr["i"].astype(np.int64)
                offset += rec.itemsize * count
                continue
            rec = np.dtype([(p[1], order + _PLY_TYPES[p[0]]) for p in props])
            arr = np.frombuffer(data, rec, count, offset)
            offset += rec.itemsize * count
            cols = {p[1]: arr[p[1]] for p in props}
        if name == "vertex":
            try:
                verts = np.stack([cols["x"], cols["y"], cols["z"]], axis=1).astype(np.float64)
            except KeyError:
                raise EngineError(f"{path}: vertex element lacks x/y/z") from None
            if all(c in cols for c in ("red", "green", "blue")):
                colors = np.stack([cols["red"], cols["green"], cols["blue"]], axis=1).astype(np.uint8)
    if verts is None or faces is None:
        raise EngineError(f"{path}: a mesh needs vertex and face elements")
    if faces.size and (faces.min() < 0 or faces.max() >= len(verts)):
        raise EngineError(f"{path}: faces index vertices outside 0..{len(verts) - 1}")
    return verts, faces, colors


def save_cage(path, vertices: np.ndarray, tets: np.ndarray, **extra) -> None:
    """Write a cage `.npz` atomically: `vertices` float64, `tets` int64, plus plain-array extras."""
    arrays = {"vertices": np.asarray(vertices, dtype=np.float64), "tets": np.asarray(tets, dtype=np.int64)}
    arrays.update({k: np.asarray(v) for k, v in extra.items()})

    def write(f):
        np.savez(f, **arrays)

    atomic_write(path, write)


def load_cage(path, validate: bool = True) -> dict[str, np.ndarray]:
    """Read a cage `.npz` (no pickles, so no code runs); checks shapes, indices and orientation."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            out = {k: z[k] for k in z.files}
    except FileNotFoundError:
        raise EngineError(f"cage file {path} does not exist") from None
    except (ValueError, OSError) as exc:
        raise EngineError(f"cannot read cage {path}: {exc}") from None
    for key in ("vertices", "tets"):
        if key not in out:
            raise EngineError(f"cage {path} has no `{key}` array")
    V, T = out["vertices"], out["tets"]
    if V.ndim != 2 or V.shape[1] != 3 or T.ndim != 2 or T.shape[1] != 4 or not np.issubdtype(T.dtype, np.integer):
        raise EngineError(f"cage {path}: `vertices` must be (N,3) and `tets` (M,4) int, got {V.shape} and {T.shape} {T.dtype}")
    out["vertices"], out["tets"] = V.astype(np.float64), T.astype(np.int64)
    if validate:
        from .barycentric import signed_volumes  # pure numpy

        if len(T) == 0:
            raise EngineError(f"cage {path} has no tets")
        if T.min() < 0 or T.max() >= len(V):
            raise EngineError(f"cage {path}: tets index vertices outside 0..{len(V) - 1}")
        vol = signed_volumes(out["vertices"], out["tets"])
        scale = float(np.ptp(V, axis=0).max()) ** 3
        bad = np.flatnonzero(vol <= 1e-12 * scale)
        if len(bad):
            raise EngineError(f"degenerate cage {path}: {len(bad)} of {len(T)} tets have zero or negative volume (first: tet {bad[0]})")
    return out
