"""Binary PLY point clouds: a writer for satsweep's ``cloud.ply`` and a minimal reader.

The cloud is written as ``binary_little_endian 1.0`` with one ``vertex`` element whose properties
are ``double x, y, z`` then, optionally, ``uchar red, green, blue`` then any extra ``float``
scalar properties (e.g. ``confidence``). Coordinates are stored as float64 because map
coordinates need it: a UTM northing is up to 10,000,000 m, and float32 has a 24-bit mantissa, so
near 7.6e6 m its spacing is 0.5 m, as coarse as the DSM cells themselves; float64 keeps them to
about 1e-9 m. CloudCompare, MeshLab, PDAL and Open3D read double vertex properties.

The coordinate reference system travels in header comments (``comment crs EPSG:32740``), which is
what CloudCompare and PDAL show; PLY has no standard CRS field.
"""

from __future__ import annotations

import os
from typing import Mapping, Sequence

import numpy as np

from satsweep.errors import InputError
from satsweep.io.atomic import atomic_output

# PLY type names -> little-endian numpy dtypes (both the PLY 1.0 names and the sized aliases).
_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "<i2", "int16": "<i2", "ushort": "<u2", "uint16": "<u2",
    "int": "<i4", "int32": "<i4", "uint": "<u4", "uint32": "<u4",
    "float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8",
}
# Numpy dtype -> PLY name used by the writer.
_WRITE_NAMES = {np.dtype("<f8"): "double", np.dtype("<f4"): "float", np.dtype("u1"): "uchar"}


def _vertex_dtype(
    *, with_colors: bool, scalar_names: Sequence[str]
) -> np.dtype:
    """Structured little-endian dtype of one vertex record."""
    fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    if with_colors:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    fields += [(name, "<f4") for name in scalar_names]
    return np.dtype(fields)


class PLYWriter:
    """A binary little-endian PLY file written in pieces: ``append`` points as they come (a
    tile's, a view's), ``commit`` writes the file (atomically: temporary name, then rename).

    The vertex records go to a temporary body file beside ``path`` as they are appended, so only
    one piece is in memory at a time; ``commit`` writes the header (which holds the count) and
    copies the body after it. ``abort`` (or leaving a ``with`` block by an exception) removes
    the body and writes nothing. ``with_colors``, ``comments`` and ``scalar_names``: as
    ``write_ply``'s colours, comments and scalars, fixed for every piece.
    """

    def __init__(self, path: str | os.PathLike, *, with_colors: bool, comments: Sequence[str] = (),
                 scalar_names: Sequence[str] = ()):
        import tempfile  # noqa: PLC0415

        reserved = {"x", "y", "z", "red", "green", "blue"}
        for name in scalar_names:
            if not name.isidentifier() or name in reserved:
                raise ValueError(f"write_ply: invalid scalar property name {name!r}")
        for line in comments:
            if "\n" in line or "\r" in line:
                raise ValueError(f"write_ply: comment {line!r} spans several lines")
        self.path = os.fspath(path)
        self.comments = list(comments)
        self.scalar_names = list(scalar_names)
        self.dtype = _vertex_dtype(with_colors=with_colors, scalar_names=self.scalar_names)
        self.count = 0
        folder, name = os.path.split(os.path.abspath(self.path))
        fd, self._body_path = tempfile.mkstemp(prefix=f".{name}.", suffix=".body", dir=folder)
        self._body = os.fdopen(fd, "wb")

    def append(self, x, y, z, *, colors: np.ndarray | None = None,
               scalars: Mapping[str, np.ndarray] | None = None) -> None:
        """Add points (the arguments as ``write_ply``'s); ValueError for inconsistent ones."""
        x, y, z = (np.asarray(a, dtype=np.float64).ravel() for a in (x, y, z))
        n = x.size
        if y.size != n or z.size != n:
            raise ValueError(f"write_ply: x, y, z lengths differ ({x.size}, {y.size}, {z.size})")
        with_colors = "red" in self.dtype.names
        if (colors is not None) != with_colors:
            raise ValueError("write_ply: colours given for a file without them, or missing"
                             if colors is not None else "write_ply: this file needs colours")
        scalars = dict(scalars or {})
        if sorted(scalars) != sorted(self.scalar_names):
            raise ValueError(f"write_ply: scalars {sorted(scalars)}, the file has "
                             f"{sorted(self.scalar_names)}")
        records = np.empty(n, dtype=self.dtype)
        records["x"], records["y"], records["z"] = x, y, z
        if colors is not None:
            c = np.asarray(colors)
            if c.dtype != np.uint8:
                raise ValueError(f"write_ply: colors must be uint8, got {c.dtype}")
            if c.shape == (n,):
                c = np.repeat(c[:, None], 3, axis=1)
            if c.shape != (n, 3):
                raise ValueError(f"write_ply: colors must have shape ({n}, 3) or ({n},), got {c.shape}")
            records["red"], records["green"], records["blue"] = c[:, 0], c[:, 1], c[:, 2]
        for name, values in scalars.items():
            if np.asarray(values).size != n:
                raise ValueError(f"write_ply: scalar {name!r} has {np.asarray(values).size} "
                                 f"values, need {n}")
            records[name] = np.asarray(values, dtype=np.float32).ravel()
        self._body.write(records.tobytes())
        self.count += n

    def commit(self) -> None:
        """Write the file: the header for the points appended, then their records."""
        import shutil  # noqa: PLC0415

        header = ["ply", "format binary_little_endian 1.0"]
        header += [f"comment {line}" for line in self.comments]
        header.append(f"element vertex {self.count}")
        for name in self.dtype.names:
            header.append(f"property {_WRITE_NAMES[self.dtype.fields[name][0]]} {name}")
        header.append("end_header")
        try:
            self._body.close()
            with atomic_output(self.path) as tmp:
                with open(tmp, "wb") as fh, open(self._body_path, "rb") as body:
                    fh.write(("\n".join(header) + "\n").encode("ascii"))
                    shutil.copyfileobj(body, fh, BODY_COPY_BYTES)
        finally:
            self._remove_body()

    def abort(self) -> None:
        """Drop what was appended; nothing is written."""
        self._body.close()
        self._remove_body()

    def _remove_body(self) -> None:
        try:
            os.remove(self._body_path)
        except FileNotFoundError:
            pass

    def __enter__(self) -> "PLYWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.commit()
        else:
            self.abort()


# Bytes copied at a time from a PLYWriter's body into the file.
BODY_COPY_BYTES = 16 * 2**20


def write_ply(
    path: str | os.PathLike,
    x: np.ndarray,
    y: np.ndarray,
    z: np.ndarray,
    *,
    colors: np.ndarray | None = None,
    comments: Sequence[str] = (),
    scalars: Mapping[str, np.ndarray] | None = None,
) -> None:
    """Write points as a binary little-endian PLY file (atomically: temporary name, then rename).

    ``x``, ``y``, ``z``: 1D arrays of the same length (e.g. UTM easting, northing, ellipsoidal
    height, metres), stored as float64 (see the module docstring for why). ``colors``: (N, 3)
    uint8 RGB, or (N,) uint8 grey (written as equal red/green/blue). ``comments``: header comment
    lines, e.g. ``"crs EPSG:32740"``. ``scalars``: extra per-point values stored as float32
    properties, e.g. ``{"confidence": c}``. Raises ValueError for inconsistent lengths or names.
    A cloud that comes in pieces: ``PLYWriter``.
    """
    scalars = dict(scalars or {})
    with PLYWriter(path, with_colors=colors is not None, comments=comments,
                   scalar_names=list(scalars)) as writer:
        writer.append(x, y, z, colors=colors, scalars=scalars)


def read_ply(path: str | os.PathLike) -> dict:
    """Read a binary little-endian PLY file with a single ``vertex`` element of scalar properties.

    Returns ``{"comments": [str, ...], "vertex": structured array}`` plus one entry per property
    (``"x"``, ``"y"``, ``"red"``...) holding that column. Meant for tests and tools; list
    properties (faces) and ASCII/big-endian files are rejected with an InputError naming the file.
    """
    path = os.fspath(path)
    try:
        fh = open(path, "rb")
    except OSError as exc:
        raise InputError(path, f"cannot open PLY file ({exc.strerror})") from None
    with fh:
        if fh.readline().rstrip(b"\r\n") != b"ply":
            raise InputError(path, "not a PLY file (no 'ply' magic line)")
        comments: list[str] = []
        fields: list[tuple[str, str]] = []
        count = None
        fmt = None
        while True:
            raw = fh.readline()
            if not raw:
                raise InputError(path, "truncated PLY header (no end_header)")
            line = raw.decode("ascii", "replace").strip()
            words = line.split()
            if not words:
                continue
            if words[0] == "end_header":
                break
            if words[0] == "format":
                fmt = words[1] if len(words) > 1 else None
            elif words[0] == "comment":
                comments.append(line[len("comment"):].strip())
            elif words[0] == "element":
                if count is not None or len(words) != 3 or words[1] != "vertex":
                    raise InputError(path, f"unsupported PLY element line {line!r} (only one 'vertex' element)")
                count = int(words[2])
            elif words[0] == "property":
                if len(words) != 3 or words[1] not in _PLY_TYPES:
                    raise InputError(path, f"unsupported PLY property line {line!r}")
                fields.append((words[2], _PLY_TYPES[words[1]]))
            elif words[0] != "obj_info":
                raise InputError(path, f"unexpected PLY header line {line!r}")
        if fmt != "binary_little_endian":
            raise InputError(path, f"unsupported PLY format {fmt!r} (need binary_little_endian)")
        if count is None:
            raise InputError(path, "PLY header declares no vertex element")
        dtype = np.dtype(fields)
        data = fh.read()
    if len(data) < count * dtype.itemsize:
        raise InputError(path, f"truncated PLY body: {len(data)} bytes for {count} vertices of {dtype.itemsize} bytes")
    vertex = np.frombuffer(data, dtype=dtype, count=count)
    out: dict = {"comments": comments, "vertex": vertex}
    for name in dtype.names:
        out[name] = vertex[name].astype(vertex[name].dtype.newbyteorder("="))
    return out
