"""Bad uploads get a 4xx problem+json that says what is wrong, and leave nothing behind."""
from __future__ import annotations

import io
import zipfile
import zlib
from pathlib import Path

import h5py
import numpy as np
import pytest

from .datasets import d4rl_arrays, minari_zip
from .problems import assert_problem, upload_refused


def _write(path: Path, arrays: dict) -> Path:
    with h5py.File(path, "w") as f:
        for k, v in arrays.items():
            f.create_dataset(k, data=v)
    return path


def test_truncated_hdf5(alice, clean, hopper_file, tmp_path):
    bad = tmp_path / "truncated.hdf5"
    bad.write_bytes(hopper_file.read_bytes()[: hopper_file.stat().st_size // 2])
    assert_problem(upload_refused(alice.api, bad), 422)


def test_wrong_keys(alice, clean, tmp_path):
    arrays = d4rl_arrays()
    arrays["acts"] = arrays.pop("actions")
    assert_problem(upload_refused(alice.api, _write(tmp_path / "keys.hdf5", arrays)), 422, "actions", "missing")


def test_nans(alice, clean, tmp_path):
    arrays = d4rl_arrays()
    arrays["rewards"][[3, 7]] = np.nan
    assert_problem(upload_refused(alice.api, _write(tmp_path / "nan.hdf5", arrays)), 422, "rewards", "NaN")


def test_dims_of_no_supported_env(alice, clean, tmp_path):
    """A well-formed file no job could train on (no env has its dims) is refused at upload, naming the envs' dims,
    rather than stored against the owner's quota to fail every job later."""
    path = _write(tmp_path / "odd.hdf5", d4rl_arrays(obs=5, act=3))
    assert_problem(upload_refused(alice.api, path), 422, "(5, 3) match no supported env", "hopper (11, 3)")


def test_not_a_dataset(alice, clean):
    r = alice.post("/v1/datasets", content=b"hello, world" * 10, headers={"Content-Type": "application/octet-stream"})
    assert_problem(r, 422, "not an HDF5")


def test_empty_and_missing_part(alice, clean):
    assert_problem(alice.post("/v1/datasets", content=b""), 422, "empty")
    r = alice.post("/v1/datasets", files={"other": ("x.hdf5", b"abc", "application/x-hdf5")})
    assert_problem(r, 422, "'file'")


def test_over_the_size_limit(alice, clean, settings):
    too_big = b"\0" * (settings.max_upload_bytes + 1)
    assert_problem(alice.post("/v1/datasets", content=too_big), 413, "DROP_MAX_UPLOAD_BYTES")
    r = alice.post("/v1/datasets", files={"file": ("big.hdf5", too_big, "application/x-hdf5")})
    assert_problem(r, 413)

    def chunks():  # no Content-Length: the limit is enforced while streaming
        for _ in range(settings.max_upload_bytes // 65536 + 2):
            yield b"\0" * 65536

    assert_problem(alice.post("/v1/datasets", content=chunks()), 413)


@pytest.mark.parametrize("part", ["data", "header"])
def test_parts_besides_the_file_count_toward_the_limit(alice, clean, settings, part):
    """Other parts are read and dropped, and a part's headers are held until they end: without the limit a stream of
    either, with no Content-Length, would hold the request and the header's memory without bound."""
    boundary = "drop-rl-test-boundary"
    filler = (b"\0" if part == "data" else b"a") * 65536

    def body():
        yield f'--{boundary}\r\nContent-Disposition: form-data; name="padding"\r\n'.encode()
        if part == "header":
            yield b"X-Padding: "
        else:
            yield b"\r\n"
        for _ in range(settings.max_upload_bytes // len(filler) + 2):
            yield filler
        yield f"\r\n--{boundary}--\r\n".encode()

    headers = {"Content-Type": f"multipart/form-data; boundary={boundary}"}
    r = alice.post("/v1/datasets", content=body(), headers=headers)
    assert_problem(r, 413, "DROP_MAX_UPLOAD_BYTES")


def test_raw_body_upload_and_name(alice, hopper_file):
    r = alice.post("/v1/datasets", params={"name": "mine.hdf5"}, content=hopper_file.read_bytes(),
                   headers={"Content-Type": "application/x-hdf5"})
    assert r.status_code == 201 and r.json()["name"] == "mine.hdf5"
    assert alice.delete(f"/v1/datasets/{r.json()['id']}").status_code == 204


def test_npz_upload(alice, tmp_path):
    path = tmp_path / "data.npz"
    np.savez(path, **d4rl_arrays(40))
    r = alice.post("/v1/datasets", content=path.read_bytes())
    assert r.status_code == 201, r.text
    report = r.json()["report"]
    assert r.json()["format"] == "npz" and report["transitions"] == 39  # the last row has no next observation
    assert any(w.startswith("next_observations: missing") for w in report["warnings"])
    assert alice.delete(f"/v1/datasets/{r.json()['id']}").status_code == 204


def test_minari_zip_is_converted(alice):
    r = alice.post("/v1/datasets", files={"file": ("hopper-test-v0.zip", minari_zip(), "application/zip")})
    assert r.status_code == 201, r.text
    ds = r.json()
    assert ds["format"] == "minari" and ds["env"] == "hopper"
    assert ds["report"]["transitions"] == 60 and ds["report"]["episodes"] == 3
    assert (ds["report"]["terminals"], ds["report"]["timeouts"]) == (1, 2)
    assert alice.delete(f"/v1/datasets/{ds['id']}").status_code == 204


def test_bad_zip(alice, clean):
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        z.writestr("readme.txt", "hi")
    r = alice.post("/v1/datasets", files={"file": ("x.zip", buf.getvalue(), "application/zip")})
    assert_problem(r, 422, "Minari")


def _one_chunk_of_zeros(ds, nbytes: int) -> None:
    """Write `ds`'s single chunk as gzip of `nbytes` zeros without holding them: a few MB on disk."""
    deflate, piece = zlib.compressobj(9), bytes(1 << 20)
    body = b"".join(deflate.compress(piece) for _ in range(nbytes // len(piece))) + deflate.flush()
    ds.id.write_direct_chunk((0, 0), body)


def test_decompression_bomb_hits_the_validator_memory_limit(tmp_path):
    """One gzip chunk of 700 MB of zeros, under dataset limits set high enough to let the read start: reading any row
    of it inflates the whole chunk, which the child's 512 MB address space cannot hold (HDF5 says its filter failed),
    and the API process is untouched. (Within the service's limits the declared size already refuses it; see
    test_hostile_uploads.)"""
    import asyncio

    from app.datasets.validate import Invalid, Validator
    from kernel.settings import Settings

    rows = 16_000_000
    bomb = tmp_path / "bomb.hdf5"
    with h5py.File(bomb, "w") as f:
        obs = f.create_dataset("observations", shape=(rows, 11), dtype="f4", compression="gzip", chunks=(rows, 11))
        _one_chunk_of_zeros(obs, rows * 11 * 4)
        for key, width in (("actions", (3,)), ("rewards", ()), ("terminals", ()), ("timeouts", ())):
            f.create_dataset(key, shape=(rows, *width), dtype="f4", chunks=(100_000, *width))
    assert bomb.stat().st_size < 10_000_000
    out = tmp_path / "out"
    out.mkdir()
    validator = Validator(Settings(data_dir=tmp_path, validate_memory_bytes=512 * 1024**2, max_dataset_rows=10**8,
                                   max_dataset_bytes=10**10, validate_timeout_s=60))
    with pytest.raises(Invalid, match="observations: cannot be read .*filter returned failure"):
        asyncio.run(validator.validate(bomb, out))
    assert not any(out.iterdir())


def test_an_api_start_removes_what_a_killed_process_left(settings, tmp_path):
    """A `.part` untouched for longer than an upload can be quiet (idle body, queued validation) is one a killed API
    process was writing: the next start removes it, the partial upload or the validator's unfinished folder. So is the
    old folder of a job recorded as deleted (killed between the delete's commit and its removal). A fresh one may be
    another process's live upload or job, and stays; so does any folder the database has no record of at all, as an
    API started on the wrong database would have none."""
    import os
    import time

    from sqlalchemy import delete

    from app.datasets.service import longest_quiet_s
    from app.main import create_app
    from kernel.db import make_engine, make_sessionmaker
    from kernel.ids import new_id
    from kernel.models import DeletedJob

    own = settings.model_copy(update={"data_dir": tmp_path / "data"})
    own.ensure_dirs()
    quiet = 2 * longest_quiet_s(own)

    def made(path: Path, age: float, folder: bool = False) -> Path:
        if folder:
            path.mkdir()
            (path / "data.hdf5").write_bytes(b"half a file")
        else:
            path.write_bytes(b"half an upload")
        os.utime(path, (time.time() - age, time.time() - age))
        return path

    uploads, datasets, jobs = (own.data_dir / name for name in ("uploads", "datasets", "jobs"))
    for name, age in (("dead", quiet + 60), ("live", 0), ("edge", quiet - 60)):
        made(uploads / f"ds_{name}.part", age)
    made(datasets / "ds_dead.part", quiet + 60, folder=True)
    made(datasets / "ds_live.part", 0, folder=True)
    deleted_old, deleted_fresh = new_id("job"), new_id("job")
    engine = make_engine(own.sqlalchemy_url)
    sessions = make_sessionmaker(engine)
    with sessions.begin() as s:
        s.add_all(DeletedJob(id=job_id, attempts=1) for job_id in (deleted_old, deleted_fresh))
    try:
        kept = [made(jobs / deleted_fresh, 0, folder=True), made(jobs / new_id("job"), quiet + 60, folder=True),
                made(datasets / new_id("ds"), quiet + 60, folder=True)]
        gone = made(jobs / deleted_old, quiet + 60, folder=True)
        app = create_app(own)
        app.state.engine.dispose()
        assert sorted(p.name for p in uploads.iterdir()) == ["ds_edge.part", "ds_live.part"]
        assert sorted(p.name for p in datasets.iterdir()) == sorted(["ds_live.part", kept[2].name])
        assert all(p.is_dir() for p in kept) and not gone.exists()
    finally:
        with sessions.begin() as s:
            s.execute(delete(DeletedJob).where(DeletedJob.id.in_([deleted_old, deleted_fresh])))
        engine.dispose()


def test_a_dataset_delete_cut_off_before_its_folder_leaves_that_folder_to_the_next_start(alice, app, settings,
                                                                                          hopper_file, monkeypatch):
    """Cut off between the delete's commit and the folder's removal, the dataset is deleted (204, gone from the API)
    and its tombstone stays; the next API start removes its folder and the tombstone, and nothing of a live dataset.
    A delete that is not cut off leaves neither. A tombstone whose folder is not there stays: on an unmounted data
    volume every folder looks gone."""
    from sqlalchemy import delete, select

    from app.datasets import service
    from app.leftovers import sweep_abandoned
    from kernel.ids import new_id
    from kernel.models import DeletedDataset
    from kernel.storage import dataset_dir

    def tombstones() -> set[str]:
        with app.state.sessions() as s:
            return set(s.scalars(select(DeletedDataset.id)))

    def upload() -> str:
        r = alice.post("/v1/datasets", content=hopper_file.read_bytes(), headers={"Content-Type": "application/x-hdf5"})
        assert r.status_code == 201, r.text
        return r.json()["id"]

    cut, whole, live, elsewhere = upload(), upload(), upload(), new_id("ds")
    assert alice.delete(f"/v1/datasets/{whole}").status_code == 204
    assert not dataset_dir(settings, whole).exists() and whole not in tombstones()

    def killed(path):
        raise SystemError("killed")

    with monkeypatch.context() as m:
        m.setattr(service, "remove_tree", killed)
        assert alice.delete(f"/v1/datasets/{cut}").status_code == 204
    assert alice.get(f"/v1/datasets/{cut}").status_code == 404
    assert dataset_dir(settings, cut).is_dir() and cut in tombstones()
    with app.state.sessions.begin() as s:
        s.add(DeletedDataset(id=elsewhere))
    try:
        assert f"datasets/{cut}" in sweep_abandoned(settings, app.state.sessions)
        assert not dataset_dir(settings, cut).exists() and cut not in tombstones() and elsewhere in tombstones()
        assert dataset_dir(settings, live).is_dir() and alice.get(f"/v1/datasets/{live}").status_code == 200
    finally:
        with app.state.sessions.begin() as s:
            s.execute(delete(DeletedDataset).where(DeletedDataset.id == elsewhere))
        assert alice.delete(f"/v1/datasets/{live}").status_code == 204


def test_a_dataset_is_found_where_another_machine_mounts_the_data_dir(settings, tmp_path):
    """The row holds the file's path relative to DROP_DATA_DIR, so a worker that mounts the shared volume elsewhere
    finds it; a row of before, with an absolute path, is read as it is."""
    from kernel.models import Dataset
    from kernel.storage import from_stored, to_stored

    from .datasets import tiny_npz
    from .private_api import private_api

    with private_api(settings, data_dir=tmp_path / "here") as (app, client):
        r = client.post("/v1/datasets", content=tiny_npz(0))
        assert r.status_code == 201, r.text
        with app.state.sessions() as s:
            stored = s.get(Dataset, r.json()["id"]).path
    (tmp_path / "here").rename(tmp_path / "there")
    there = settings.model_copy(update={"data_dir": tmp_path / "there"})
    assert not Path(stored).is_absolute() and from_stored(there, stored).is_file()
    assert from_stored(there, str(tmp_path / "old.npz")) == tmp_path / "old.npz"
    # a folder linked to another disk is still under the data dir; a file outside it keeps its absolute path
    (tmp_path / "disk").mkdir()
    (tmp_path / "there" / "linked").symlink_to(tmp_path / "disk")
    assert to_stored(there, tmp_path / "there" / "linked" / "f.pt") == "linked/f.pt"
    assert to_stored(there, tmp_path / "elsewhere.pt") == str(tmp_path / "elsewhere.pt")
