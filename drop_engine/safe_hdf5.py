"""Read arrays from an HDF5 file nobody vouches for, such as an upload.

HDF5 lets a file make a read reach other files (external links, external raw storage, virtual datasets), load plugin
code (a filter that is not built in) or allocate whatever size a header declares. All of that shows in the file's
structure, so it is checked before any array is read, and refused with a message that names the key.
"""
from __future__ import annotations

import math

import h5py
import numpy as np
from h5py import h5d, h5l

from .data import DatasetError

# gzip, shuffle and fletcher32 are built into HDF5; lzf is built into h5py, which wrote many existing files.
ALLOWED_FILTERS = {1: "gzip", 2: "shuffle", 3: "fletcher32", 32000: "lzf"}
NUMERIC_KINDS = "biuf"  # bool, signed, unsigned, float


def _foreign_link(handle: h5py.File) -> tuple[str, int] | None:
    """The first link that is neither hard nor soft (soft links stay inside the file once no external link exists).

    Uses the low-level visit, which walks hard links only and resolves nothing, so no other file is opened."""
    links = handle.id.links

    def check(name: bytes):
        kind = links.get_info(name).type
        return None if kind in (h5l.TYPE_HARD, h5l.TYPE_SOFT) else (name.decode("utf-8", "replace"), kind)

    return links.visit(check)


def _kind(dtype: np.dtype) -> str:
    if h5py.check_string_dtype(dtype) is not None:
        return "strings"
    if h5py.check_vlen_dtype(dtype) is not None:
        return "variable-length arrays"
    if dtype.kind == "c":
        return "complex numbers"
    return "a compound of fields" if dtype.names else "a non-numeric type"


class SafeHDF5:
    """An open file whose arrays are read only after their storage, filters and dtype pass; `max_bytes` (if set)
    bounds the declared uncompressed size of everything read, so a tiny file cannot claim terabytes."""

    def __init__(self, handle: h5py.File, max_bytes: int | None = None):
        found = _foreign_link(handle)
        if found is not None:
            name, kind = found
            what = "an external link to another file" if kind == h5l.TYPE_EXTERNAL else "a user-defined link"
            raise DatasetError(f"{name}: {what}; only links inside the file are allowed")
        self.handle, self.max_bytes, self.used = handle, max_bytes, 0

    def read(self, key: str) -> np.ndarray:
        node = self.handle[key]
        if not isinstance(node, h5py.Dataset):
            raise DatasetError(f"{key}: expected an array, found a {type(node).__name__.lower()}")
        self._check(key, node)
        try:
            return node[()]
        except (OSError, ValueError, TypeError) as exc:
            raise DatasetError(f"{key}: cannot be read ({exc})") from None

    def _check(self, key: str, node: h5py.Dataset) -> None:
        plist = node.id.get_create_plist()
        if plist.get_layout() == h5d.VIRTUAL:
            raise DatasetError(f"{key}: a virtual dataset, whose data would come from other files; not allowed")
        if plist.get_external_count():
            raise DatasetError(f"{key}: its data is stored in external files; only data inside the file is allowed")
        for index in range(plist.get_nfilters()):
            code = plist.get_filter(index)[0]
            if code not in ALLOWED_FILTERS:
                raise DatasetError(f"{key}: compressed with HDF5 filter {code}, which is not accepted (only "
                                   f"{', '.join(ALLOWED_FILTERS.values())})")
        if node.dtype.kind not in NUMERIC_KINDS:
            raise DatasetError(f"{key}: must be numeric (bool, int or float), found {_kind(node.dtype)} "
                               f"(dtype {node.dtype})")
        size = math.prod(node.shape) * node.dtype.itemsize
        if self.max_bytes is not None and self.used + size > self.max_bytes:
            raise DatasetError(f"{key}: declares shape {node.shape} of {node.dtype} ({size} bytes uncompressed), "
                               f"over the limit of {self.max_bytes} bytes for the whole dataset")
        self.used += size
