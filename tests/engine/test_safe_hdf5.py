"""HDF5 files nobody vouches for, at the engine level: a file that would make a read reach another file, load a
plugin, or allocate what a header claims is refused with a message that names the key, before any of that happens."""
import h5py
import hostile_hdf5
import numpy as np
import pytest

from drop_engine.data import load_dataset, scan
from drop_engine.data_rows import DatasetLimits
from drop_engine.errors import DatasetError, DatasetTooLarge
from drop_engine.safe_hdf5 import SafeHDF5

SECRET_REWARD = 123456.0  # what a dataset would hold if the read had reached the other file


def _arrays(n: int = 50) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    return {"observations": rng.normal(size=(n, 11)).astype(np.float32),
            "actions": rng.uniform(-1, 1, size=(n, 3)).astype(np.float32),
            "rewards": rng.normal(size=n).astype(np.float32),
            "terminals": np.zeros(n, bool), "timeouts": np.eye(1, n, n - 1, dtype=bool)[0]}


@pytest.fixture
def secret(tmp_path):
    """A file that a dataset must never be able to read from."""
    path = tmp_path / "secret.hdf5"
    with h5py.File(path, "w") as f:
        f["rewards"] = np.full(50, SECRET_REWARD, np.float32)
    return path


def _file_with(path, replace: str, make):
    """A valid D4RL file whose `replace` key is built by `make(handle)`."""
    with h5py.File(path, "w") as f:
        for key, value in _arrays().items():
            if key != replace:
                f.create_dataset(key, data=value)
        make(f)
    return path


@pytest.mark.parametrize("make, message", [
    (hostile_hdf5.external_link, "rewards: an external link to another file"),
    (hostile_hdf5.soft_link_through_external_group, "elsewhere: an external link to another file"),
    (hostile_hdf5.external_storage, "rewards: its data is stored in external files"),
    (hostile_hdf5.virtual, "rewards: a virtual dataset, whose data would come from other files"),
], ids=hostile_hdf5.IDS)
def test_reads_that_would_reach_other_files_are_refused(tmp_path, secret, make, message):
    path = _file_with(tmp_path / "hostile.hdf5", "rewards", make(secret))
    with pytest.raises(DatasetError) as info:
        load_dataset(path)
    assert str(info.value).startswith(message)
    assert "123456" not in str(info.value)


def test_an_external_link_anywhere_refuses_the_file(tmp_path, secret):
    """A soft link could lead through it, so the file is refused as it is opened, whichever keys are asked for."""
    def make(f):
        f["infos"] = h5py.ExternalLink(str(secret), "/")

    path = _file_with(tmp_path / "hostile.hdf5", "", make)
    with h5py.File(path, "r") as handle, pytest.raises(DatasetError, match="^infos: an external link"):
        SafeHDF5(handle)


def test_a_filter_that_is_not_built_in_is_refused(tmp_path):
    """Filter 32015 (zstd) would make HDF5 look for a plugin library on disk; the chunk is written raw, so only the
    structure check can stop it."""
    def make(f):
        ds = f.create_dataset("rewards", shape=(50,), dtype="f4", chunks=(50,), compression=32015,
                              allow_unknown_filter=True)
        ds.id.write_direct_chunk((0,), np.zeros(50, "f4").tobytes())

    with pytest.raises(DatasetError, match=r"^rewards: compressed with HDF5 filter 32015, which is not accepted \(only "
                                           r"gzip, shuffle, fletcher32, lzf\)"):
        load_dataset(_file_with(tmp_path / "plugin.hdf5", "rewards", make))


def test_the_built_in_filters_are_accepted(tmp_path):
    """gzip + shuffle + fletcher32 on some keys and lzf on another: the filters a D4RL or h5py file uses."""
    arrays = _arrays()
    path = tmp_path / "filters.hdf5"
    with h5py.File(path, "w") as f:
        for key, value in arrays.items():
            options = {"compression": "lzf"} if key == "actions" else {"compression": "gzip", "shuffle": True,
                                                                         "fletcher32": True}
            f.create_dataset(key, data=value, **options)
    data = load_dataset(path)
    np.testing.assert_array_equal(data.actions, arrays["actions"][:-1])  # the last row has no successor
    np.testing.assert_array_equal(data.rewards, arrays["rewards"][:-1])


def _absurd_declared_shape(f):
    """A chunked (10**12, 11) float32 array with 50 rows written: a few KB on disk, 44 TB if read."""
    f.create_dataset("observations", shape=(10**12, 11), dtype="f4", chunks=(1000, 11), compression="gzip")[:50] = 1.0


def _compression_bomb(f):
    """Gzip chunks of zeros: a few KB that declare 880 MB."""
    f.create_dataset("observations", shape=(20_000_000, 11), dtype="f4", chunks=(100_000, 11), compression="gzip")


@pytest.mark.parametrize("make, message", [
    (_absurd_declared_shape,
     "observations: declares 1000000000000 rows (shape (1000000000000, 11)), over the limit of 1000000 rows"),
    (_compression_bomb, "observations: declares 20000000 rows (shape (20000000, 11)), over the limit of 1000000 rows"),
], ids=["absurd-declared-shape", "compression-bomb"])
def test_declared_sizes_are_refused_before_any_row_is_read(tmp_path, make, message):
    path = _file_with(tmp_path / "big.hdf5", "observations", make)
    assert path.stat().st_size < 100_000
    with pytest.raises(DatasetTooLarge) as info:
        scan(path, DatasetLimits(rows=1_000_000))
    assert str(info.value).startswith(message) and info.value.limit == "rows"


@pytest.mark.parametrize("value, kind", [
    (np.array([b"not a number"] * 50), "strings"),
    (np.array(["text"] * 50, dtype=h5py.string_dtype()), "strings"),
    (np.zeros(50, dtype=[("a", "f4"), ("b", "i4")]), "a compound of fields"),
    (np.array([np.zeros(1 + i % 3, np.float32) for i in range(50)], dtype=h5py.vlen_dtype(np.float32)),
     "variable-length arrays"),
    (np.zeros(50, dtype=np.complex64), "complex numbers"),
], ids=["bytes", "vlen-str", "compound", "vlen-float", "complex"])
def test_non_numeric_dtypes_are_refused(tmp_path, value, kind):
    path = _file_with(tmp_path / "dtype.hdf5", "rewards", lambda f: f.create_dataset("rewards", data=value))
    with pytest.raises(DatasetError, match=f"^rewards: must be numeric \\(bool, int or float\\), found {kind}"):
        load_dataset(path)
