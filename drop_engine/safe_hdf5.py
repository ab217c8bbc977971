"""Read arrays from an HDF5 file nobody vouches for, such as an upload.

HDF5 lets a file make a read reach other files (external links, external raw storage, virtual datasets), load plugin
code (a filter that is not built in) or declare any size. All of that shows in the file's structure, so it is checked
before any array is read, and refused with a message that names the key; the caller checks the declared shapes.
"""
from __future__ import annotations

import h5py
import numpy as np
from h5py import h5d, h5l

from .errors import DatasetError

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
    """An open file whose arrays are handed out only after their storage, filters and dtype pass; their rows are read
    when the caller slices them, after it has checked what their shapes declare."""

    def __init__(self, handle: h5py.File):
        found = _foreign_link(handle)
        if found is not None:
            name, kind = found
            what = "an external link to another file" if kind == h5l.TYPE_EXTERNAL else "a user-defined link"
            raise DatasetError(f"{name}: {what}; only links inside the file are allowed")
        self.handle = handle

    def array(self, key: str) -> h5py.Dataset:
        node = self.handle[key]
        if not isinstance(node, h5py.Dataset):
            raise DatasetError(f"{key}: expected an array, found a {type(node).__name__.lower()}")
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
        return node
