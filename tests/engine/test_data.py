"""Loading, validation and description of D4RL-layout datasets."""
import h5py
import numpy as np
import pytest

from drop_engine.data import describe, from_arrays, load_dataset, save_hdf5, scan
from drop_engine.data_rows import DatasetLimits
from drop_engine.errors import DatasetError, DatasetTooLarge


def _write(path, arrays):
    with h5py.File(path, "w") as f:
        for k, v in arrays.items():
            f.create_dataset(k, data=v)
    return path


def test_hdf5_round_trip_and_report(tmp_path, hopper_arrays):
    path = tmp_path / "d.hdf5"
    save_hdf5(path, hopper_arrays, {"env_name": "Hopper-v4"})
    data = load_dataset(path, env="hopper")
    assert len(data) == len(hopper_arrays["observations"])
    np.testing.assert_array_equal(data.next_observations, hopper_arrays["next_observations"])
    report = describe(data)
    assert report.env == "hopper" and report.obs_dim == 11 and report.act_dim == 3
    assert report.terminals == int(hopper_arrays["terminals"].sum())
    assert report.timeouts == int(hopper_arrays["timeouts"].sum())
    assert report.episodes == report.terminals + report.timeouts
    assert report.reward_min <= report.reward_mean <= report.reward_max


def test_npz_loads_like_hdf5(tmp_path, hopper_arrays):
    path = tmp_path / "d.npz"
    np.savez(path, **{k: v for k, v in hopper_arrays.items() if "/" not in k})
    assert len(load_dataset(path, env="hopper")) == len(hopper_arrays["observations"])


def test_timeouts_are_not_terminals(hopper_arrays):
    arrays = dict(hopper_arrays)
    arrays["timeouts"] = np.zeros_like(arrays["timeouts"])
    arrays["timeouts"][10] = True
    data = from_arrays(arrays)
    assert data.timeouts[10] and not data.terminals[10]


def test_rebuilds_next_observations():
    obs = np.arange(12, dtype=np.float32).reshape(6, 2)
    arrays = {"observations": obs, "actions": np.zeros((6, 1)), "rewards": np.arange(6.0),
              "terminals": np.array([0, 0, 1, 0, 0, 0]), "timeouts": np.zeros(6)}
    data = from_arrays(arrays)
    # Row 2 (terminal) and row 5 (file end) have no successor in the file and are dropped.
    np.testing.assert_array_equal(data.observations, obs[[0, 1, 3, 4]])
    np.testing.assert_array_equal(data.next_observations, obs[[1, 2, 4, 5]])
    assert data.timeouts.tolist() == [False, True, False, True]
    assert any("rebuilt" in w for w in data.warnings)


def _base():
    return {"observations": np.zeros((5, 11), np.float32), "actions": np.zeros((5, 3), np.float32),
            "rewards": np.zeros(5, np.float32), "next_observations": np.zeros((5, 11), np.float32),
            "terminals": np.zeros(5, bool), "timeouts": np.zeros(5, bool)}


def _without(key):
    a = _base()
    del a[key]
    return a


def _with(key, value):
    a = _base()
    a[key] = value
    return a


def _nan():
    a = _base()
    a["observations"][2, 3] = np.nan
    return a


@pytest.mark.parametrize("arrays, env, message", [
    (_without("actions"), None, "actions: missing"),
    (_without("rewards"), None, "rewards: missing"),
    (_with("actions", np.zeros((4, 3))), None, "actions: has 4 rows but observations has 5"),
    (_with("terminals", np.zeros(6)), None, "terminals: has 6 rows"),
    (_nan(), None, "observations: row 2 contains NaN or inf"),
    (_with("rewards", np.array([0, 0, np.inf, 0, 0])), None, "rewards: row 2 contains NaN or inf"),
    (_with("terminals", np.array([0, 2, 0, 0, 0])), None, "terminals: must hold only 0/1"),
    (_with("observations", np.zeros((0, 11))), None, "observations: dataset is empty"),
    (_with("observations", np.array(["a"] * 5)), None, "observations: must be numeric"),
    (_with("next_observations", np.zeros((5, 10))), None, "next_observations: shape (5, 10) differs"),
    (_base(), "walker2d", "do not match walker2d (17, 6)"),
])
def test_bad_datasets_raise_clear_errors(arrays, env, message):
    with pytest.raises(DatasetError, match=None) as info:
        from_arrays(arrays, env=env)
    assert message in str(info.value)


def test_bad_files(tmp_path):
    truncated = tmp_path / "t.hdf5"
    save_hdf5(truncated, _base())
    truncated.write_bytes(truncated.read_bytes()[:200])
    for path, message in [(tmp_path / "missing.hdf5", "does not exist"), (truncated, "not a readable HDF5 file")]:
        with pytest.raises(DatasetError) as info:
            load_dataset(path)
        assert message in str(info.value)
    grouped = tmp_path / "g.hdf5"
    with h5py.File(grouped, "w") as f:
        f.create_group("observations")
    with pytest.raises(DatasetError, match="observations: expected an array"):
        load_dataset(grouped)


def _drop_next(arrays):
    return {k: v for k, v in arrays.items() if k != "next_observations" and "/" not in k}


@pytest.mark.parametrize("kind", ["hdf5", "hdf5-without-next", "npz-without-next", "npz-fortran"])
def test_scan_reports_what_loading_describes(tmp_path, hopper_arrays, kind):
    """Blocks of 7 rows: every block boundary the rebuild of next observations and the episode count cross."""
    arrays = {k: v for k, v in hopper_arrays.items() if "/" not in k}
    arrays = arrays if kind == "hdf5" else _drop_next(arrays)
    if kind.startswith("npz"):
        path = tmp_path / "d.npz"
        if kind == "npz-fortran":
            arrays["observations"] = np.asfortranarray(arrays["observations"])
        np.savez(path, **arrays)
    else:
        path = tmp_path / "d.hdf5"
        save_hdf5(path, arrays, {"env_name": "Hopper-v4"})
    row_bytes = sum(v.dtype.itemsize * (v.shape[1] if v.ndim == 2 else 1) for v in arrays.values())
    scanned = scan(path, block_bytes=7 * row_bytes).to_dict()
    described = describe(load_dataset(path)).to_dict()
    assert scanned.pop("reward_mean") == pytest.approx(described.pop("reward_mean"), rel=1e-5)
    assert scanned == described
    assert scanned["transitions"] < len(arrays["observations"]) or kind == "hdf5"


def _lazy_file(path, rows: int, obs_dim: int = 11, act_dim: int = 3):
    """Chunked arrays that declare `rows` rows and hold none: a few KB on disk, whatever size once read."""
    with h5py.File(path, "w") as f:
        for key, shape in [("observations", (rows, obs_dim)), ("actions", (rows, act_dim)), ("rewards", (rows,)),
                           ("terminals", (rows,)), ("timeouts", (rows,))]:
            f.create_dataset(key, shape=shape, dtype="f4", chunks=(min(rows, 10_000), *shape[1:]))
    return path


def test_scan_refuses_what_a_lazy_file_declares_before_reading(tmp_path):
    path = _lazy_file(tmp_path / "lazy.hdf5", 10_000_000)
    assert path.stat().st_size < 100_000
    with pytest.raises(DatasetTooLarge, match=r"observations: declares 10000000 rows \(shape \(10000000, 11\)\), "
                                              "over the limit of 1000 rows") as info:
        scan(path, DatasetLimits(rows=1000))
    assert info.value.limit == "rows"
    row = (2 * 11 + 3 + 2) * 4
    with pytest.raises(DatasetTooLarge, match=f"10000000 rows of {row} bytes decode to {10_000_000 * row} bytes, "
                                              "over the limit of 1000000 bytes") as info:
        scan(path, DatasetLimits(decoded_bytes=1_000_000))
    assert info.value.limit == "decoded_bytes"


def test_scan_holds_one_block_not_the_dataset(tmp_path):
    """1,000,000 declared rows (about 100 MB once read, twice that converted): scanned in 1 MB blocks, the peak of
    what numpy allocates stays within a few blocks."""
    import tracemalloc

    path = _lazy_file(tmp_path / "lazy.hdf5", 1_000_000)
    tracemalloc.start()
    try:
        report = scan(path, block_bytes=1 << 20)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert report.transitions == 999_999 and report.episodes == 1  # no next_observations: the last row is dropped
    assert peak < 16 << 20, peak


def test_recorded_env_that_contradicts_the_dims_is_a_warning(tmp_path):
    """Hopper-v4 recorded on 17-dim observations: the dims choose the env (two match, so none is chosen)."""
    rng = np.random.default_rng(0)
    arrays = {"observations": rng.normal(size=(20, 17)).astype(np.float32),
              "actions": rng.uniform(-1, 1, size=(20, 6)).astype(np.float32),
              "rewards": np.zeros(20, np.float32), "terminals": np.zeros(20, bool), "timeouts": np.zeros(20, bool)}
    path = tmp_path / "d.hdf5"
    save_hdf5(path, arrays, {"env_name": "Hopper-v4"})
    for report in (scan(path), describe(load_dataset(path))):
        assert report.env is None and report.env_candidates == ["walker2d", "halfcheetah"]
        assert ("env_name: the file says Hopper-v4, whose (obs, act) dims are (11, 3), but the data has (17, 6); "
                "dims match: walker2d, halfcheetah") in report.warnings
    arrays["observations"] = arrays["observations"][:, :11]
    arrays["actions"] = arrays["actions"][:, :3]
    save_hdf5(path, arrays, {"env_name": "Walker2d-v4"})
    report = scan(path)
    assert report.env == "hopper" and report.warnings[-1].endswith("matched by dims instead: hopper")
