"""Dataset files: which format a file is, told by its bytes, and its arrays opened for `data` to check.

An HDF5 file in D4RL's layout and an .npz with the same keys are read in place, a block of rows at a time; a Minari
dataset (a zip of its directory) is converted to the D4RL layout first (`minari.py`). Every file is read as one
nobody vouches for (`safe_hdf5.py`, `safe_zip.py`), as the service hands the engine its uploads.
"""
from __future__ import annotations

import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator, Literal

from .data_rows import OPTIONAL, REQUIRED, DatasetLimits, Rows
from .errors import DatasetError
from .safe_zip import open_zip

Format = Literal["hdf5", "npz", "minari"]
HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"
ZIP_MAGIC = b"PK\x03\x04"


def sniff(path: str | Path, limits: DatasetLimits = DatasetLimits()) -> Format:
    """The file's format, from its leading bytes and, for a zip, its entries' names (checked as `safe_zip` does)."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"file: {path} does not exist")
    with path.open("rb") as handle:
        head = handle.read(8)
    if head.startswith(HDF5_MAGIC):
        return "hdf5"
    if head.startswith(ZIP_MAGIC):
        with open_zip(path, limits) as zf:
            names = zf.namelist()
        if any(n.endswith("main_data.hdf5") for n in names):
            return "minari"
        if any(n.endswith(".npy") for n in names):
            return "npz"
        raise DatasetError("file: a zip that is neither a Minari dataset (no data/main_data.hdf5) nor an .npz")
    raise DatasetError("file: not an HDF5 file, an .npz or a Minari zip (unrecognised leading bytes)")


@contextmanager
def _hdf5_arrays(path: Path) -> Iterator[tuple[dict[str, Rows], dict]]:
    import h5py

    from .safe_hdf5 import SafeHDF5

    try:
        handle = h5py.File(path, "r")
    except OSError as exc:
        raise DatasetError(f"file: not a readable HDF5 file ({exc})") from None
    with handle:
        reader = SafeHDF5(handle)
        arrays = {key: reader.array(key) for key in REQUIRED + OPTIONAL if key in handle}
        yield arrays, {k: (v.decode() if isinstance(v, bytes) else v) for k, v in handle.attrs.items()}


@contextmanager
def open_arrays(path: str | Path, limits: DatasetLimits = DatasetLimits()) -> Iterator[tuple[dict[str, Rows], dict]]:
    """The file's arrays, unread (their rows are read when sliced), and its attributes, whatever its format; a Minari
    zip is converted into a temporary directory first (within `limits`), and its metadata's env id becomes the
    `env_name` attribute."""
    path = Path(path)
    kind = sniff(path, limits)
    if kind == "npz":
        from .npz_rows import open_npz

        with open_npz(path, REQUIRED + OPTIONAL) as arrays:
            yield arrays, {}
    elif kind == "minari":
        from .minari import convert

        with tempfile.TemporaryDirectory(prefix="drop-minari-") as tmp:
            converted = Path(tmp, "data.hdf5")
            convert(path, converted, limits)
            with _hdf5_arrays(converted) as found:
                yield found
    else:
        with _hdf5_arrays(path) as found:
            yield found
