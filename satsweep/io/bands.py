"""Rasters on disk read and written by windows: a run's grid never has to fit in memory.

A ``RawBand`` is a 2-D array stored row-major in a plain binary file (no header), read and
written window by window with positioned I/O (``os.pread``/``os.pwrite``, not memory maps, whose
pages would count in the process's resident memory). A band starts as its ``fill`` value: the
file is created sparse, and ``covered`` cells are tracked so that never-written cells read as
``fill`` whatever the file holds. ``read_npy_window`` reads a window of a ``.npy`` file the same
way.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np

# Bytes read or written at once at most when a window is moved row by row (a row segment
# longer than this is split).
_IO_CHUNK = 1 << 26


@dataclasses.dataclass(eq=False)
class RawBand:
    """A (height, width) raster of ``dtype`` in the file ``path``, with cells never written
    reading as ``fill``."""

    path: Path
    shape: tuple[int, int]
    dtype: np.dtype
    fill: float | int

    @classmethod
    def create(cls, path: str | os.PathLike, shape: tuple[int, int], dtype,
               fill: float | int) -> "RawBand":
        """A new band (an empty sparse file of the band's size, and its coverage file)."""
        band = cls(Path(path), (int(shape[0]), int(shape[1])), np.dtype(dtype), fill)
        for p, size in ((band.path, band.nbytes), (band._mask_path, band.shape[0] * band.shape[1])):
            with open(p, "wb") as fh:
                fh.truncate(size)
        return band

    @property
    def nbytes(self) -> int:
        return self.shape[0] * self.shape[1] * self.dtype.itemsize

    @property
    def _mask_path(self) -> Path:
        return self.path.with_name(self.path.name + ".covered")

    def _check_window(self, r0: int, r1: int, c0: int, c1: int) -> None:
        h, w = self.shape
        if not (0 <= r0 <= r1 <= h and 0 <= c0 <= c1 <= w):
            raise ValueError(f"window rows {r0}:{r1}, columns {c0}:{c1} outside the band "
                             f"{self.path.name} of {h} x {w}")

    def write(self, r0: int, c0: int, values: np.ndarray) -> None:
        """Write ``values`` (2-D) with its first cell at (r0, c0)."""
        values = np.ascontiguousarray(values, dtype=self.dtype)
        rows, cols = values.shape
        self._check_window(r0, r0 + rows, c0, c0 + cols)
        _put_rows(self.path, values, r0, c0, self.shape[1], self.dtype.itemsize)
        _put_rows(self._mask_path, np.ones((rows, cols), np.uint8), r0, c0, self.shape[1], 1)

    def read(self, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        """The window rows r0:r1, columns c0:c1 (ends excluded), never-written cells at
        ``fill``."""
        self._check_window(r0, r1, c0, c1)
        out = _get_rows(self.path, r0, r1, c0, c1, self.shape[1], self.dtype)
        covered = _get_rows(self._mask_path, r0, r1, c0, c1, self.shape[1], np.dtype(np.uint8))
        out[covered == 0] = self.fill
        return out

    def remove(self) -> None:
        for p in (self.path, self._mask_path):
            p.unlink(missing_ok=True)


def _put_rows(path: Path, values: np.ndarray, r0: int, c0: int, width: int, itemsize: int) -> None:
    rows, cols = values.shape
    fd = os.open(path, os.O_WRONLY)
    try:
        for i in range(rows):
            data = values[i].tobytes()
            offset = ((r0 + i) * width + c0) * itemsize
            for k in range(0, len(data), _IO_CHUNK):
                os.pwrite(fd, data[k:k + _IO_CHUNK], offset + k)
    finally:
        os.close(fd)


def _get_rows(path: Path, r0: int, r1: int, c0: int, c1: int, width: int,
              dtype: np.dtype) -> np.ndarray:
    out = np.empty((r1 - r0, c1 - c0), dtype)
    if out.size == 0:
        return out
    row_bytes = (c1 - c0) * dtype.itemsize
    fd = os.open(path, os.O_RDONLY)
    try:
        if c0 == 0 and c1 == width:  # whole rows: one contiguous read per chunk
            _read_into(fd, out.reshape(-1).view(np.uint8), r0 * row_bytes)
        else:
            for i in range(r1 - r0):
                _read_into(fd, out[i].view(np.uint8), ((r0 + i) * width + c0) * dtype.itemsize)
    finally:
        os.close(fd)
    return out


def _read_into(fd: int, buffer: np.ndarray, offset: int) -> None:
    """Fill the uint8 ``buffer`` from ``offset`` (a sparse file reads as zeros)."""
    done = 0
    while done < buffer.size:
        size = min(_IO_CHUNK, buffer.size - done)
        data = os.pread(fd, size, offset + done)
        if not data:  # past the end of a file truncated shorter: zeros
            buffer[done:] = 0
            return
        buffer[done:done + len(data)] = np.frombuffer(data, np.uint8)
        done += len(data)


def read_npy_window(path: str | os.PathLike, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
    """The window rows r0:r1, columns c0:c1 of a 2-D C-ordered ``.npy`` file, read without
    loading (or mapping) the rest."""
    with open(path, "rb") as fh:
        version = np.lib.format.read_magic(fh)
        read_header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                       else np.lib.format.read_array_header_2_0)
        shape, fortran, dtype = read_header(fh)
        offset = fh.tell()
    if len(shape) != 2 or fortran:
        raise ValueError(f"{path}: expected a 2-D C-ordered array, got shape {shape}")
    h, w = shape
    if not (0 <= r0 <= r1 <= h and 0 <= c0 <= c1 <= w):
        raise ValueError(f"{path}: window {r0}:{r1}, {c0}:{c1} outside {h} x {w}")
    out = np.empty((r1 - r0, c1 - c0), dtype)
    fd = os.open(path, os.O_RDONLY)
    try:
        for i in range(r1 - r0):
            _read_into(fd, out[i].view(np.uint8), offset + ((r0 + i) * w + c0) * dtype.itemsize)
    finally:
        os.close(fd)
    return out
