"""What one dataset may hold, whatever its file takes on disk: a few KB of lazy HDF5 that declare many rows is refused
for the rows or decoded bytes it declares, counts toward the storage quota at its decoded size, and validations run a
bounded number at once."""
from __future__ import annotations

import asyncio
import threading
import time
from pathlib import Path

import h5py
import httpx

from drop_engine.data_rows import DataShape

from .datasets import tiny_npz
from .private_api import private_api

ROWS = 100_000  # declared; 99,999 transitions once the last row (no successor) is dropped
DECODED = DataShape(ROWS - 1, 11, 3).decoded_bytes  # 10.8 MB


def _lazy(path: Path, rows: int = ROWS) -> Path:
    """Chunked arrays declaring `rows` rows of a hopper dataset, no chunk written: a few KB on disk."""
    with h5py.File(path, "w") as f:
        for key, shape in [("observations", (rows, 11)), ("actions", (rows, 3)), ("rewards", (rows,)),
                           ("terminals", (rows,)), ("timeouts", (rows,))]:
            f.create_dataset(key, shape=shape, dtype="f4", chunks=(min(rows, 10_000), *shape[1:]), compression="gzip")
    return path


def _problem(r: httpx.Response, status: int, code: str, *needles: str) -> dict:
    assert r.status_code == status, r.text
    body = r.json()
    assert body["code"] == code, body
    for needle in needles:
        assert needle in body["detail"], body
    return body


def test_a_lazy_file_is_refused_for_the_rows_it_declares(settings, tmp_path):
    path = _lazy(tmp_path / "lazy.hdf5")
    assert path.stat().st_size < 20_000
    with private_api(settings, max_dataset_rows=ROWS - 1) as (_, client):
        r = client.post("/v1/datasets", content=path.read_bytes())
        _problem(r, 422, "invalid_dataset", f"observations: declares {ROWS} rows", f"limit of {ROWS - 1} rows",
                 "DROP_MAX_DATASET_ROWS")
    with private_api(settings, max_dataset_bytes=DECODED) as (_, client):
        r = client.post("/v1/datasets", content=path.read_bytes())
        _problem(r, 422, "invalid_dataset", f"decode to {DataShape(ROWS, 11, 3).decoded_bytes} bytes",
                 f"limit of {DECODED} bytes", "DROP_MAX_DATASET_BYTES")
    assert not list((settings.data_dir / "uploads").glob("*.part"))


def test_a_lazy_file_counts_its_decoded_size_toward_the_quota(settings, tmp_path):
    """Two lazy files of 10.8 MB decoded each under a 16 MB quota: the first is stored and counts 10.8 MB, the second
    does not fit, though both files together take a few KB."""
    path = _lazy(tmp_path / "lazy.hdf5")
    with private_api(settings, max_stored_bytes_per_owner=16_000_000) as (_, client):
        first = client.post("/v1/datasets", content=path.read_bytes())
        assert first.status_code == 201, first.text
        assert first.json()["decoded_bytes"] == DECODED and first.json()["size_bytes"] == path.stat().st_size
        assert first.json()["report"]["transitions"] == ROWS - 1
        second = client.post("/v1/datasets", content=path.read_bytes())
        _problem(second, 413, "storage_quota_exceeded", f"this dataset counts {DECODED} bytes, its decoded size",
                 f"your datasets take {DECODED} of the 16000000 bytes")
        assert client.delete(f"/v1/datasets/{first.json()['id']}").status_code == 204


def test_validations_beyond_the_pool_wait_their_turn(settings, monkeypatch):
    """Three uploads at once with one validator slot: each validation runs alone, and all three are accepted."""
    import app.datasets.validate as validate

    running, peak, lock = 0, 0, threading.Lock()
    run = validate._run

    def counted(*args):
        nonlocal running, peak
        with lock:
            running += 1
            peak = max(peak, running)
        try:
            time.sleep(0.3)  # long enough for the others to arrive
            return run(*args)
        finally:
            with lock:
                running -= 1

    monkeypatch.setattr(validate, "_run", counted)
    with private_api(settings, max_concurrent_validations=1) as (app_, client):
        async def upload_three() -> list[httpx.Response]:
            transport = httpx.ASGITransport(app=app_)
            async with httpx.AsyncClient(transport=transport, base_url="http://test", headers=client.headers) as c:
                return await asyncio.gather(*(c.post("/v1/datasets", content=tiny_npz(seed)) for seed in range(3)))

        responses = asyncio.run(upload_three())
        assert [r.status_code for r in responses] == [201] * 3, [r.text for r in responses]
        assert peak == 1
        for r in responses:
            assert client.delete(f"/v1/datasets/{r.json()['id']}").status_code == 204
        threads = list(app_.state.validator._pool._threads)
    for thread in threads:  # the app's shutdown ends its validation threads
        thread.join(5)
    assert threads and not any(t.is_alive() for t in threads)


def test_a_recorded_env_that_contradicts_the_dims_is_a_warning(settings, tmp_path):
    """Walker2d's dims under a Hopper-v4 record: stored, with a warning, and matched by its dims (two envs fit, so
    none is chosen and a job names its env)."""
    path = _lazy(tmp_path / "walker.hdf5", 1000)
    with h5py.File(path, "a") as f:
        f.attrs["env_name"] = "Hopper-v4"
        for key, width in (("observations", 17), ("actions", 6)):
            del f[key]
            f.create_dataset(key, shape=(1000, width), dtype="f4")
    with private_api(settings) as (_, client):
        r = client.post("/v1/datasets", content=path.read_bytes())
        assert r.status_code == 201, r.text
        ds = r.json()
        assert ds["env"] is None and ds["report"]["env_candidates"] == ["walker2d", "halfcheetah"]
        assert any(w.startswith("env_name: the file says Hopper-v4, whose (obs, act) dims are (11, 3), but the data "
                                "has (17, 6)") for w in ds["report"]["warnings"]), ds["report"]["warnings"]
        job = client.post("/v1/jobs", json={"dataset_id": ds["id"], "env": "walker2d", "preset": "smoke"})
        assert job.status_code == 201, job.text
