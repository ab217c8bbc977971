"""Open a zip nobody vouches for, such as an upload.

Its entries are only ever read by the code's own names, never extracted by theirs; still, a zip that carries paths
meant to escape a folder, or links, or that expands past the caller's limit, is refused as hostile before any entry is
read. A damaged zip, found as it is opened or read, is a DatasetError like any other bad file.
"""
from __future__ import annotations

import re
import stat
import zipfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from .data_rows import DatasetLimits
from .errors import DatasetError


def _check(zf: zipfile.ZipFile, limits: DatasetLimits) -> None:
    total = 0
    for info in zf.infolist():
        name = info.filename
        parts = name.replace("\\", "/").split("/")
        if name.startswith(("/", "\\")) or re.match(r"[A-Za-z]:", name) or ".." in parts:
            raise DatasetError(f"zip entry {name!r}: an absolute path or a '..' component; not allowed")
        if stat.S_ISLNK(info.external_attr >> 16):
            raise DatasetError(f"zip entry {name!r}: a symbolic link; not allowed")
        total += info.file_size
    limits.check_zip(total)


@contextmanager
def open_zip(path: Path, limits: DatasetLimits) -> Iterator[zipfile.ZipFile]:
    """The zip at `path`, its entries checked; reading an entry stops at its declared size (and then fails its CRC)."""
    try:
        with zipfile.ZipFile(path) as zf:
            _check(zf, limits)
            yield zf
    except zipfile.BadZipFile as exc:
        raise DatasetError(f"file: broken zip ({exc})") from None
