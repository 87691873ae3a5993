"""The wire format between Blender (the add-on) and the engine worker process.

Standard library, plus numpy once arrays travel, so both sides import it (the
add-on may import engine modules that do not reach torch), and a worker on a
Python without numpy can still say so. One message is:

    b"NDW1" | u32 length of the JSON header | JSON header | raw array bytes...

The header's "_arrays" lists each array's name, dtype, shape and byte count, in
the order their bytes follow. Arrays travel as raw bytes, not pickles, so a
message never executes code when read and large frames cost one copy.
"""

from __future__ import annotations

import json
import struct
from typing import TYPE_CHECKING, BinaryIO

if TYPE_CHECKING:
    import numpy as np

MAGIC = b"NDW1"
_LENGTH = struct.Struct("<I")
_MAX_HEADER = 64 * 1024 * 1024


class ProtocolError(Exception):
    """The stream is not a worker conversation (bad magic, truncated message, bad header)."""


def write_message(stream: BinaryIO, header: dict, arrays: dict[str, np.ndarray] | None = None) -> int:
    """Write one message; returns its size in bytes (header and arrays)."""
    if arrays:
        import numpy as np

        arrays = {name: np.ascontiguousarray(a) for name, a in arrays.items()}
    else:
        arrays = {}
    header = dict(header)
    header["_arrays"] = [
        {"name": name, "dtype": a.dtype.str, "shape": list(a.shape), "nbytes": int(a.nbytes)}
        for name, a in arrays.items()
    ]
    body = json.dumps(header, separators=(",", ":")).encode()
    stream.write(MAGIC + _LENGTH.pack(len(body)) + body)
    for a in arrays.values():
        if a.nbytes:  # memoryview cannot cast an empty array
            stream.write(memoryview(a).cast("B"))
    stream.flush()
    return len(MAGIC) + _LENGTH.size + len(body) + sum(int(a.nbytes) for a in arrays.values())


def content_key(*arrays: np.ndarray) -> str:
    """A key for the worker session that changes whenever the content does: a hash of each array's
    dtype, shape and bytes (the same arrays give the same key in any process)."""
    import hashlib

    import numpy as np

    digest = hashlib.sha1()
    for a in arrays:
        a = np.ascontiguousarray(a)
        digest.update(f"{a.dtype.str}{a.shape};".encode())
        digest.update(memoryview(a).cast("B") if a.nbytes else b"")
    return digest.hexdigest()[:20]


def _read_exact(stream: BinaryIO, n: int) -> bytearray:
    """n bytes into a fresh bytearray: the arrays viewing it are writable (torch warns on read-only
    numpy arrays and would share them as if they were writable)."""
    buf = bytearray(n)
    view, got = memoryview(buf), 0
    while got < n:
        k = stream.readinto(view[got:])
        if not k:
            raise ProtocolError(f"stream ended {n - got} bytes into a {n}-byte read (truncated message)")
        got += k
    return buf


def read_message(stream: BinaryIO) -> tuple[dict, dict[str, np.ndarray]] | None:
    """The next (header, arrays), or None when the stream ended cleanly between messages.

    Each array is a writable view of its own received bytes."""
    start = stream.read(len(MAGIC))
    if not start:
        return None
    if len(start) < len(MAGIC):
        start += _read_exact(stream, len(MAGIC) - len(start))
    if start != MAGIC:
        raise ProtocolError(f"expected {MAGIC!r} at the start of a message, got {start!r}")
    (length,) = _LENGTH.unpack(_read_exact(stream, _LENGTH.size))
    if length > _MAX_HEADER:
        raise ProtocolError(f"message header of {length} bytes is larger than the {_MAX_HEADER} allowed")
    try:
        header = json.loads(_read_exact(stream, length))
        specs = header.pop("_arrays")
    except (ValueError, KeyError) as exc:
        raise ProtocolError(f"unreadable message header: {exc}") from None
    arrays = {}
    if specs:
        import numpy as np
    for spec in specs:
        data = _read_exact(stream, spec["nbytes"])
        arrays[spec["name"]] = np.frombuffer(data, dtype=np.dtype(spec["dtype"])).reshape(spec["shape"])
    return header, arrays
