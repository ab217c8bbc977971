"""A full or read-only DROP_DATA_DIR: an upload answers 507 problem+json and leaves neither a file nor a row, and a
job whose checkpoint cannot be written fails with code storage_full and leaves no partial checkpoint. The full disk is
a real tmpfs of 64 KiB mounted over one folder of the data directory (so these tests need root)."""
from __future__ import annotations

import subprocess
from pathlib import Path

import pytest
from sqlalchemy import select

from .authed import Authed
from .problems import upload_refused
from .processes import start_worker, stop_worker

pytestmark = pytest.mark.needs_root


@pytest.fixture
def tmpfs():
    """mount(folder, *options): a 64 KiB tmpfs over the folder until the test ends."""
    mounted: list[Path] = []

    def mount(folder: Path, *options: str) -> None:
        done = subprocess.run(["mount", "-t", "tmpfs", "-o", ",".join(("size=64k", *options)), "tmpfs", str(folder)],
                              capture_output=True, text=True)
        if done.returncode:
            pytest.fail(f"cannot mount a tmpfs on {folder} (these tests need root): {done.stderr.strip()}")
        mounted.append(folder)

    yield mount
    for folder in reversed(mounted):
        subprocess.run(["umount", str(folder)], check=True)


@pytest.fixture
def disk(own_settings, tmp_path):
    settings = own_settings.model_copy(update={"data_dir": tmp_path / "data"})
    settings.ensure_dirs()
    return settings


@pytest.fixture
def alice(disk):
    from fastapi.testclient import TestClient

    from app.core.auth import create_token
    from app.main import create_app

    with TestClient(create_app(disk), raise_server_exceptions=False) as c:
        yield Authed(c, create_token(c.app.state.sessions, "alice"))


def _files(folder: Path) -> list[Path]:
    return [p for p in folder.rglob("*") if p.is_file()]


@pytest.mark.parametrize("folder, options, code", [
    ("uploads", (), "storage_full"),  # while the upload streams in
    ("datasets", (), "storage_full"),  # while the validator copies it into place (another device: no hard link)
    ("uploads", ("ro",), "storage_unwritable"),
])
def test_upload_to_full_storage_is_507_and_keeps_nothing(disk, alice, tmpfs, hopper_file, folder, options, code):
    from kernel.models import Dataset

    tmpfs(disk.data_dir / folder, *options)
    r = upload_refused(alice.api, hopper_file)
    assert r.status_code == 507, r.text
    assert r.headers["content-type"] == "application/problem+json"
    body = r.json()
    assert body["code"] == code and body["title"] == "Insufficient Storage" and body["status"] == 507
    assert "storage is " + ("full" if code == "storage_full" else "not writable") in body["detail"]
    assert str(disk.data_dir) not in body["detail"]
    assert _files(disk.data_dir / "uploads") == [] and _files(disk.data_dir / "datasets") == []
    with alice.client.app.state.sessions() as s:
        assert s.scalars(select(Dataset)).all() == []
    assert alice.get("/v1/datasets").json()["data"] == []


def test_job_whose_checkpoint_cannot_be_written_fails_with_storage_full(disk, alice, tmpfs, hopper_file, tmp_path):
    tmpfs(disk.data_dir / "jobs")  # a checkpoint of the smoke preset is about 200 KiB
    ds = alice.api.upload_dataset(hopper_file)
    worker = start_worker(disk, tmp_path / "worker.log")
    try:
        job = alice.post("/v1/jobs", json={"dataset_id": ds["id"], "preset": "smoke"}).json()
        done = alice.api.wait(job["id"], timeout=120)  # the niced pool on a loaded machine
    finally:
        stop_worker(worker)
    assert done["status"] == "failed" and done["attempts"] == 1, done
    assert done["error"]["code"] == "storage_full"
    assert done["error"]["message"].startswith("the run's checkpoint or policy could not be written: the server's "
                                               "storage is full")
    assert alice.get(f"/v1/jobs/{job['id']}/checkpoints").json()["data"] == []
    assert _files(disk.data_dir / "jobs") == [], "no partial checkpoint is left behind"
