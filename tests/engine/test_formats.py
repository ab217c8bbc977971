"""Dataset formats at the engine level: a file's format told by its bytes, a Minari zip loaded and trained on like any
dataset, and zips built to escape a folder or expand without bound refused before any entry is read."""
import io
import json
import stat
import zipfile
from pathlib import Path

import h5py
import numpy as np
import pytest

from drop_engine.cli import main
from drop_engine.data import describe, from_arrays, load_dataset, save_hdf5, scan
from drop_engine.data_rows import DatasetLimits
from drop_engine.errors import DatasetError, DatasetTooLarge
from drop_engine.formats import sniff
from drop_engine.minari import convert

D4RL_KEYS = ("observations", "actions", "rewards", "next_observations", "terminals", "timeouts")
MAIN = "hopper-test-v0/data/main_data.hdf5"


def _episodes_hdf5(arrays: dict[str, np.ndarray]) -> bytes:
    """Minari's main_data.hdf5 for D4RL-layout arrays whose episodes are contiguous and whose last row ends one."""
    ends = np.flatnonzero(arrays["terminals"] | arrays["timeouts"])
    h5 = io.BytesIO()
    with h5py.File(h5, "w") as f:
        for i, (start, stop) in enumerate(zip(np.r_[0, ends[:-1] + 1], ends + 1)):
            episode = f.create_group(f"episode_{i}")
            episode["observations"] = np.concatenate([arrays["observations"][start:stop],
                                                      arrays["next_observations"][stop - 1:stop]])
            episode["actions"] = arrays["actions"][start:stop]
            episode["rewards"] = arrays["rewards"][start:stop].astype(np.float64)  # as Minari writes them
            episode["terminations"] = arrays["terminals"][start:stop]
            episode["truncations"] = arrays["timeouts"][start:stop]
    return h5.getvalue()


def _write_zip(path: Path, entries: dict[str, bytes | str]) -> Path:
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as z:
        for name, data in entries.items():
            z.writestr(name, data)
    return path


def _minari_zip(path: Path, arrays: dict[str, np.ndarray], env_id: str = "Hopper-v5") -> Path:
    metadata = {"dataset_id": "hopper-test-v0", "env_spec": json.dumps({"id": env_id})}
    return _write_zip(path, {MAIN: _episodes_hdf5(arrays), "hopper-test-v0/data/metadata.json": json.dumps(metadata)})


def test_a_minari_zip_loads_as_the_rows_it_was_made_of(tmp_path, hopper_arrays):
    path = _minari_zip(tmp_path / "hopper.zip", hopper_arrays)
    data = load_dataset(path, env="hopper")
    expected = from_arrays({k: hopper_arrays[k] for k in D4RL_KEYS})
    for key in D4RL_KEYS:
        np.testing.assert_array_equal(getattr(data, key), getattr(expected, key), err_msg=key)
    assert data.attrs["env_name"] == "Hopper-v5" and data.env_version == "v5"
    assert scan(path).to_dict() == describe(data).to_dict() == {**describe(expected).to_dict(), "env": "hopper"}


def test_drop_train_takes_a_minari_zip_and_evaluates_in_its_env_version(tmp_path, hopper_arrays, capsys):
    out = tmp_path / "run"
    code = main(["train", "--dataset", str(_minari_zip(tmp_path / "hopper.zip", hopper_arrays)), "--preset", "smoke",
                 "--set", "epochs=1", "--set", "eval_episodes=1", "--threads", "1", "--no-model-cache",
                 "--no-progress", "--out", str(out)])
    assert code == 0, capsys.readouterr().err
    assert json.loads(capsys.readouterr().out)["status"] == "completed"
    assert json.loads((out / "policy" / "last" / "metadata.json").read_text())["gym_id"] == "Hopper-v5"


def test_sniff_tells_formats_by_their_bytes(tmp_path, hopper_arrays):
    arrays = {k: hopper_arrays[k] for k in D4RL_KEYS}
    save_hdf5(tmp_path / "named.npz", arrays)  # the name says npz, the bytes say HDF5
    with open(tmp_path / "named.hdf5", "wb") as f:  # np.savez would add .npz to the name
        np.savez(f, **arrays)
    _minari_zip(tmp_path / "minari.bin", hopper_arrays)
    assert [sniff(tmp_path / name) for name in ("named.npz", "named.hdf5", "minari.bin")] == ["hdf5", "npz", "minari"]
    assert len(load_dataset(tmp_path / "named.hdf5")) == len(load_dataset(tmp_path / "named.npz")) == 1500


@pytest.mark.parametrize("content, message", [
    (b"observations,actions\n", "not an HDF5 file, an .npz or a Minari zip"),
    ({"readme.txt": "hi"}, "neither a Minari dataset (no data/main_data.hdf5) nor an .npz"),
], ids=["text", "zip-of-neither"])
def test_files_of_no_known_format(tmp_path, content, message):
    path = tmp_path / "data.zip"
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        _write_zip(path, content)
    with pytest.raises(DatasetError, match="^file: ") as info:
        load_dataset(path)
    assert message in str(info.value)


def _symlink(name: str) -> zipfile.ZipInfo:
    info = zipfile.ZipInfo(name)
    info.create_system = 3  # unix, so external_attr carries the mode
    info.external_attr = (stat.S_IFLNK | 0o777) << 16
    return info


@pytest.mark.parametrize("entry, needle", [
    ("/tmp/escape", "absolute path"),
    ("hopper-test-v0/../../tmp/escape", "'..'"),
    ("..\\..\\escape", "'..'"),
    ("C:/escape", "absolute path"),
    (_symlink("hopper-test-v0/data/main_data.hdf5.link"), "symbolic link"),
], ids=["absolute", "dot-dot", "dot-dot-backslash", "drive", "symlink"])
def test_zips_with_escaping_entries_are_refused(tmp_path, hopper_arrays, entry, needle):
    path = _minari_zip(tmp_path / "hostile.zip", hopper_arrays)
    with zipfile.ZipFile(path, "a") as z:
        z.writestr(entry, b"/etc/passwd")
    with pytest.raises(DatasetError, match="^zip entry ") as info:
        load_dataset(path)
    assert needle in str(info.value)


@pytest.mark.parametrize("kind", ["minari", "npz"])
def test_zips_that_expand_past_the_limit_are_refused_from_their_directory(tmp_path, hopper_arrays, kind):
    path = tmp_path / "big.zip"
    if kind == "minari":
        _minari_zip(path, hopper_arrays)
    else:
        with path.open("wb") as f:
            np.savez_compressed(f, **{k: hopper_arrays[k] for k in D4RL_KEYS})
    with zipfile.ZipFile(path) as z:
        expanded = sum(info.file_size for info in z.infolist())
    assert scan(path, DatasetLimits(zip_bytes=expanded)).transitions == 1500
    with pytest.raises(DatasetTooLarge, match=f"zip: its entries expand to {expanded} bytes, over the limit of "
                                              f"{expanded - 1}$") as info:
        scan(path, DatasetLimits(zip_bytes=expanded - 1))
    assert info.value.limit == "zip_bytes"


def test_a_zip_entry_that_expands_past_its_declared_size_is_a_broken_zip(tmp_path, hopper_arrays):
    """zipfile stops at the declared size and the CRC check fails, so no more than was declared is ever written."""
    path = _minari_zip(tmp_path / "hopper.zip", hopper_arrays)
    data = bytearray(path.read_bytes())
    central = data.index(b"PK\x01\x02")
    assert data[central + 46:central + 46 + len(MAIN)] == MAIN.encode()
    data[central + 24:central + 28] = (1024).to_bytes(4, "little")  # the uncompressed size of main_data.hdf5
    path.write_bytes(bytes(data))
    with pytest.raises(DatasetError, match="^file: broken zip"):
        load_dataset(path)


def _one_episode_zip(path: Path, change) -> Path:
    """A Minari zip of one 20-step episode of zeros, truncated at its end, as `change(episode)` leaves it."""
    episode = {"observations": np.zeros((21, 11), np.float32), "actions": np.zeros((20, 3), np.float32),
               "rewards": np.zeros(20), "terminations": np.zeros(20, bool), "truncations": np.eye(1, 20, 19)[0] > 0}
    change(episode)
    h5 = io.BytesIO()
    with h5py.File(h5, "w") as f:
        for key, value in episode.items():
            f[f"episode_0/{key}"] = value
    return _write_zip(path, {MAIN: h5.getvalue()})


def test_a_step_both_terminated_and_truncated_is_a_terminal(tmp_path):
    data = load_dataset(_one_episode_zip(tmp_path / "end.zip", lambda ep: ep["terminations"].__setitem__(19, True)))
    assert (data.terminals.sum(), data.timeouts.sum(), data.terminals[-1]) == (1, 0, True)


def test_converting_a_zip_that_is_no_minari_dataset(tmp_path):
    with pytest.raises(DatasetError, match=r"^file: not a Minari dataset \(no data/main_data.hdf5 in the zip\)"):
        convert(_write_zip(tmp_path / "other.zip", {"observations.npy": b""}), tmp_path / "out.hdf5", DatasetLimits())
    assert not (tmp_path / "out.hdf5").exists()


def test_minari_main_data_gets_the_hdf5_structure_checks(tmp_path):
    """An episode's rewards as an external link to another file: refused before the other file is opened."""
    secret = tmp_path / "secret.hdf5"
    with h5py.File(secret, "w") as f:
        f["rewards"] = np.full(20, 123456.0)
    path = _one_episode_zip(tmp_path / "hostile.zip", lambda ep: ep.update(rewards=h5py.ExternalLink(str(secret),
                                                                                                     "/rewards")))
    with pytest.raises(DatasetError, match="^episode_0/rewards: an external link to another file"):
        load_dataset(path)


@pytest.mark.parametrize("change, message", [
    (lambda ep: ep.pop("truncations"), "episode_0/truncations: missing or not an array"),
    (lambda ep: ep.update(observations=ep["observations"][:-1]), "episode_0/observations: expected 21 rows"),
    (lambda ep: ep.update(rewards=ep["rewards"][:-1]), "episode_0/rewards: expected shape (20,)"),
], ids=["missing-key", "observations-without-the-last", "short-rewards"])
def test_malformed_minari_episodes(tmp_path, change, message):
    with pytest.raises(DatasetError) as info:
        load_dataset(_one_episode_zip(tmp_path / "bad.zip", change))
    assert str(info.value).startswith(message)
