"""Hostile uploads: HDF5 files that would make a read reach other files, load a plugin, or allocate what a header
claims, and zips built to escape a folder or expand without bound. Each is refused with a 422 that names the key and
the reason, before anything is read from elsewhere, and leaves no file and no row behind."""
from __future__ import annotations

import io
import secrets
import stat
import zipfile
from pathlib import Path

import h5py
import hostile_hdf5
import numpy as np
import pytest

from .datasets import d4rl_arrays, minari_zip
from .problems import assert_problem, upload_refused

SECRET_REWARD = 123456.0  # what a report would show if the upload had read the other file


@pytest.fixture
def secret(tmp_path) -> Path:
    """A file outside the data directory that an upload must never be able to read."""
    path = tmp_path / "secret.hdf5"
    with h5py.File(path, "w") as f:
        f["rewards"] = np.full(50, SECRET_REWARD, np.float32)
    return path


def _upload_with(alice, path: Path, replace: str, make) -> dict:
    """Write a valid D4RL file whose `replace` key is built by `make(handle)`, upload it, return the 422 body."""
    with h5py.File(path, "w") as f:
        for key, value in d4rl_arrays(50).items():
            if key != replace:
                f.create_dataset(key, data=value)
        make(f)
    r = upload_refused(alice.api, path)
    assert r.status_code == 422, r.text
    return r.json()


@pytest.mark.parametrize("make, needle", [
    (hostile_hdf5.external_link, "external link"),
    (hostile_hdf5.soft_link_through_external_group, "external link"),
    (hostile_hdf5.external_storage, "external files"),
    (hostile_hdf5.virtual, "virtual dataset"),
], ids=hostile_hdf5.IDS)
def test_hdf5_reaching_other_files(alice, clean, tmp_path, secret, make, needle):
    body = _upload_with(alice, tmp_path / "hostile.hdf5", "rewards", make(secret))
    _assert_problem_body(body, needle)
    assert body["detail"].split(":")[0] in ("rewards", "elsewhere")
    assert str(SECRET_REWARD) not in body["detail"] and "123456" not in body["detail"]


def _assert_problem_body(body: dict, *needles: str) -> None:
    assert body["status"] == 422 and body["code"] == "invalid_dataset" and body["type"] and body["title"]
    for needle in needles:
        assert needle in body["detail"], body


def test_hdf5_filter_that_is_not_built_in(alice, clean, tmp_path):
    """Filter 32015 (zstd) would make HDF5 look for a plugin library on disk; the chunk is written raw, so only the
    structure check can stop it."""
    def make(f):
        ds = f.create_dataset("rewards", shape=(50,), dtype="f4", chunks=(50,), compression=32015,
                              allow_unknown_filter=True)
        ds.id.write_direct_chunk((0,), np.zeros(50, "f4").tobytes())

    body = _upload_with(alice, tmp_path / "plugin.hdf5", "rewards", make)
    _assert_problem_body(body, "rewards", "filter 32015", "gzip")


def test_hdf5_builtin_filters_are_accepted(alice, tmp_path):
    """gzip + shuffle + fletcher32 on one key and lzf on another: the filters a D4RL or h5py file uses."""
    path = tmp_path / "filters.hdf5"
    with h5py.File(path, "w") as f:
        for key, value in d4rl_arrays(50).items():
            options = {"compression": "lzf"} if key == "actions" else {"compression": "gzip", "shuffle": True,
                                                                         "fletcher32": True}
            f.create_dataset(key, data=value, **options)
    ds = alice.api.upload_dataset(path)
    assert alice.delete(f"/v1/datasets/{ds['id']}").status_code == 204


def test_hdf5_absurd_declared_shape(alice, clean, tmp_path):
    """A chunked (10**12, 11) float32 array with 50 rows written: a few KB on disk, 44 TB if read."""
    def make(f):
        ds = f.create_dataset("observations", shape=(10**12, 11), dtype="f4", chunks=(1000, 11), compression="gzip")
        ds[:50] = 1.0

    path = tmp_path / "absurd.hdf5"
    body = _upload_with(alice, path, "observations", make)
    assert path.stat().st_size < 100_000
    _assert_problem_body(body, "observations", "(1000000000000, 11)", "over the limit")


def test_hdf5_compression_bomb(alice, clean, tmp_path):
    """Gzip chunks of zeros: a few KB that declare 880 MB, refused from the header before any chunk is inflated."""
    def make(f):
        f.create_dataset("observations", shape=(20_000_000, 11), dtype="f4", compression="gzip", chunks=(100_000, 11))

    path = tmp_path / "bomb.hdf5"
    body = _upload_with(alice, path, "observations", make)
    assert path.stat().st_size < 100_000
    _assert_problem_body(body, "observations", "over the limit")


def _vlen_floats() -> np.ndarray:
    value = np.empty(50, dtype=h5py.vlen_dtype(np.float32))
    for i in range(50):
        value[i] = np.zeros(1 + i % 3, np.float32)
    return value


@pytest.mark.parametrize("value, needle", [
    (np.array([b"not a number"] * 50), "strings"),
    (np.array(["text"] * 50, dtype=h5py.string_dtype()), "strings"),
    (np.zeros(50, dtype=[("a", "f4"), ("b", "i4")]), "compound"),
    (_vlen_floats(), "variable-length"),
    (np.zeros(50, dtype=np.complex64), "complex"),
], ids=["bytes", "vlen-str", "compound", "vlen-float", "complex"])
def test_hdf5_non_numeric_dtypes(alice, clean, tmp_path, value, needle):
    body = _upload_with(alice, tmp_path / "dtype.hdf5", "rewards", lambda f: f.create_dataset("rewards", data=value))
    _assert_problem_body(body, "rewards", "must be numeric", needle)


# ------------------------------------------------------------------------------------------------ zips
def _with_entry(base: bytes, info: zipfile.ZipInfo | str, data: bytes) -> bytes:
    """`base` (a zip) plus one more entry."""
    buf = io.BytesIO(base)
    with zipfile.ZipFile(buf, "a", compression=zipfile.ZIP_DEFLATED) as z:
        z.writestr(info, data)
    return buf.getvalue()


def _symlink(name: str, target: str) -> zipfile.ZipInfo:
    info = zipfile.ZipInfo(name)
    info.create_system = 3  # unix, so external_attr carries the mode
    info.external_attr = (stat.S_IFLNK | 0o777) << 16
    return info


def _post_zip(alice, data: bytes):
    return alice.post("/v1/datasets", files={"file": ("hostile.zip", data, "application/zip")})


ESCAPE = f"drop-escape-{secrets.token_hex(4)}"


@pytest.mark.parametrize("entry, needle", [
    (f"/tmp/{ESCAPE}", "absolute path"),
    ("hopper-test-v0/" + "../" * 12 + f"tmp/{ESCAPE}", "'..'"),
    ("..\\..\\" + ESCAPE, "'..'"),
    (_symlink("hopper-test-v0/data/main_data.hdf5.link", "/etc/passwd"), "symbolic link"),
], ids=["absolute", "dot-dot", "dot-dot-backslash", "symlink"])
def test_minari_zip_with_escaping_entries(alice, clean, entry, needle):
    r = _post_zip(alice, _with_entry(minari_zip(), entry, b"/etc/passwd"))
    body = assert_problem(r, 422, "zip entry", needle)
    assert body["code"] == "invalid_dataset"
    assert not Path("/tmp", ESCAPE).exists()


def test_zip_that_expands_past_the_limit(alice, clean, settings):
    """A few KB of deflated zeros that expand to 5x the upload limit: refused from the zip's directory."""
    data = _with_entry(minari_zip(), "hopper-test-v0/data/padding.bin", bytes(5 * settings.max_upload_bytes))
    assert len(data) < settings.max_upload_bytes // 20
    assert_problem(_post_zip(alice, data), 422, "expand to", "over the limit")


def test_npz_that_expands_past_the_limit(alice, clean, settings):
    buf = io.BytesIO()
    arrays = d4rl_arrays(50)
    arrays["observations"] = np.zeros((5 * settings.max_upload_bytes // 44, 11), np.float32)
    np.savez_compressed(buf, **arrays)
    assert_problem(_post_zip(alice, buf.getvalue()), 422, "expand to", "over the limit")


def test_zip_entry_that_expands_past_its_declared_size(alice, clean):
    """The central directory says main_data.hdf5 is 1 KB; it inflates to far more. zipfile stops at the declared
    size and the CRC check fails, so nothing beyond what was declared (and bounded) is ever written."""
    deflated = io.BytesIO()
    with zipfile.ZipFile(io.BytesIO(minari_zip())) as src, \
            zipfile.ZipFile(deflated, "w", compression=zipfile.ZIP_DEFLATED) as dst:
        for info in src.infolist():
            dst.writestr(info.filename, src.read(info))
    data = bytearray(deflated.getvalue())
    central = data.index(b"PK\x01\x02")
    assert data[central + 46:central + 46 + 16].startswith(b"hopper-test-v0/d")
    data[central + 24:central + 28] = (1024).to_bytes(4, "little")  # uncompressed size of the first entry
    assert_problem(_post_zip(alice, bytes(data)), 422, "broken zip")


def test_minari_main_data_with_an_external_link(alice, clean, secret):
    """The HDF5 inside a Minari zip gets the same structure checks as a plain upload."""
    h5 = io.BytesIO()
    with h5py.File(h5, "w") as f:
        ep = f.create_group("episode_0")
        ep["observations"] = np.zeros((51, 11), np.float32)
        ep["actions"] = np.zeros((50, 3), np.float32)
        ep["rewards"] = h5py.ExternalLink(str(secret), "/rewards")
        ep["terminations"] = np.zeros(50, bool)
        ep["truncations"] = np.eye(1, 50, 49, dtype=bool)[0]
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        z.writestr("hopper-test-v0/data/main_data.hdf5", h5.getvalue())
    assert_problem(_post_zip(alice, buf.getvalue()), 422, "episode_0/rewards", "external link")
