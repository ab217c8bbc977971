"""The arrays of an .npz read a block of rows at a time from the zip, where `np.load` would decode each one whole.

Only each member's .npy header is read up front, so a small compressed file cannot make the reader allocate what its
headers declare before the caller has checked that.
"""
from __future__ import annotations

import math
import zipfile
import zlib
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import IO, Iterator

import numpy as np
from numpy.lib import format as npy

from .errors import DatasetError

_HEADERS = {(1, 0): npy.read_array_header_1_0, (2, 0): npy.read_array_header_2_0}


class NpyRows:
    """One .npy member: `shape` and `dtype` from its header, rows read forward as sliced (a step back of one row, as
    a block that reads its successor makes, is served from the last row read)."""

    def __init__(self, key: str, handle: IO[bytes]):
        try:
            version = npy.read_magic(handle)
            if version not in _HEADERS:
                raise ValueError(f".npy format version {version} is not supported")
            shape, self._fortran, self.dtype = _HEADERS[version](handle)
        except ValueError as exc:
            raise DatasetError(f"{key}: not a readable .npy array ({exc})") from None
        self.key, self.shape, self._handle = key, tuple(shape), handle
        self._row_bytes = self.dtype.itemsize * math.prod(self.shape[1:])
        self._data_start, self._next = handle.tell(), 0
        self._last: np.ndarray | None = None
        self._whole: np.ndarray | None = None

    def _bytes(self, count: int) -> bytes:
        data = self._handle.read(count)
        if len(data) != count:
            raise DatasetError(f"{self.key}: the .npy data is shorter than its header declares")
        return data

    def __getitem__(self, rows: slice) -> np.ndarray:
        start, stop = rows.start, min(rows.stop, self.shape[0])
        # Column-major: rows are not contiguous, so the array is read once (the caller has bounded it).
        if self._fortran:
            if self._whole is None:
                self._whole = np.frombuffer(self._bytes(math.prod(self.shape) * self.dtype.itemsize), self.dtype)
                self._whole = self._whole.reshape(self.shape, order="F")
            return self._whole[start:stop]
        head = []
        if start == self._next - 1 and self._last is not None:
            head, start = [self._last], self._next
        elif start != self._next:
            self._handle.seek(self._data_start + start * self._row_bytes)
        body = np.frombuffer(self._bytes((stop - start) * self._row_bytes), self.dtype)
        block = np.concatenate([*head, body.reshape(stop - start, *self.shape[1:])])
        self._next, self._last = stop, block[-1:].copy()
        return block


@contextmanager
def open_npz(path: Path, keys: tuple[str, ...]) -> Iterator[dict[str, NpyRows]]:
    """The members named `keys` (those present) of the .npz at `path`."""
    try:
        with zipfile.ZipFile(path) as zf, ExitStack() as stack:
            names = set(zf.namelist())
            yield {key: NpyRows(key, stack.enter_context(zf.open(f"{key}.npy"))) for key in keys
                   if f"{key}.npy" in names}
    except (zipfile.BadZipFile, zlib.error, EOFError, OSError) as exc:  # a damaged zip, found as it is read
        raise DatasetError(f"file: not a readable .npz file ({exc})") from None
