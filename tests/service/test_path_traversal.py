"""Path traversal: every client string that could reach the filesystem (upload names, ids in URLs, the policy format,
job fields) is tried with `..`, absolute paths, URL-encoded separators, NUL bytes and very long values. Each answers
a 4xx problem+json, never a 500, and nothing changes on disk outside the files named by the ids the server made.

The API here runs over its own data directory inside a fresh parent folder, so the whole tree can be compared."""
from __future__ import annotations

import os
from pathlib import Path

import h5py
import pytest

from .datasets import d4rl_arrays

HOSTILE = ["../../etc/passwd", "/etc/passwd", "..%2f..%2fetc%2fpasswd", "%2e%2e%2f%2e%2e%2fetc%2fpasswd",
           "..\\..\\windows\\win.ini", "~root/.ssh/authorized_keys", "a" * 300]
BAD_IDS = ["..%2f..%2fetc", "%2e%2e%2f%2e%2e%2fetc%2fpasswd", "%2fetc%2fpasswd", "%00", "ds_%00", "job_%00",
           "ds_..%2f..", "a" * 5000]


def _tree(root: Path) -> dict[str, tuple | None]:
    """Every path below root, with size and mtime for files (a folder's own mtime moves as files come and go)."""
    out = {}
    for path in sorted(root.rglob("*")):
        info = path.lstat()
        out[str(path.relative_to(root))] = None if path.is_dir() else (info.st_size, info.st_mtime_ns)
    return out


@pytest.fixture(scope="module")
def sandbox(settings, tmp_path_factory):
    """(client, root): an API whose data directory is root/data, next to decoys a traversal would hit."""
    from fastapi.testclient import TestClient

    from app.main import create_app

    root = tmp_path_factory.mktemp("sandbox")
    (root / "etc").mkdir()
    (root / "etc" / "passwd").write_text("decoy\n")
    (root / "secret.hdf5").write_bytes(b"decoy")
    app = create_app(settings.model_copy(update={"data_dir": root / "data"}))
    with TestClient(app, raise_server_exceptions=False) as client:
        yield client, root


@pytest.fixture
def api(sandbox, tokens):
    client, root = sandbox
    before, passwd = _tree(root), os.stat("/etc/passwd").st_mtime_ns
    yield client, {"Authorization": f"Bearer {tokens['alice']}"}, root
    assert _tree(root) == before
    assert os.stat("/etc/passwd").st_mtime_ns == passwd


@pytest.fixture(scope="module")
def small_file(tmp_path_factory) -> bytes:
    path = tmp_path_factory.mktemp("small") / "small.hdf5"
    with h5py.File(path, "w") as f:
        for key, value in d4rl_arrays(50).items():
            f.create_dataset(key, data=value)
    return path.read_bytes()


def _problem(r, *statuses: int) -> dict:
    assert r.status_code in statuses, (r.status_code, r.text[:300])
    assert r.headers["content-type"] == "application/problem+json"
    return r.json()


def _created_then_deleted(client, headers, root: Path, r) -> None:
    """A 201 whose only file is datasets/<its id>/data.hdf5, removed again by DELETE."""
    assert r.status_code == 201, r.text[:300]
    ds = r.json()
    files = [p for p in (root / "data").rglob("*") if p.is_file() and "datasets" in p.parts]
    assert files == [root / "data" / "datasets" / ds["id"] / "data.hdf5"]
    assert client.delete(f"/v1/datasets/{ds['id']}", headers=headers).status_code == 204


@pytest.mark.parametrize("name", HOSTILE, ids=range(len(HOSTILE)))
def test_upload_names_are_labels_not_paths(api, small_file, name):
    client, headers, root = api
    r = client.post("/v1/datasets", headers=headers, files={"file": (name, small_file, "application/x-hdf5")})
    assert r.status_code != 201 or r.json()["name"] == name
    _created_then_deleted(client, headers, root, r)
    r = client.post("/v1/datasets", headers=headers, params={"name": name}, content=small_file)
    assert r.status_code != 201 or r.json()["name"] == name
    _created_then_deleted(client, headers, root, r)


def test_upload_names_with_nul_or_too_long(api, small_file):
    client, headers, _ = api
    body = _problem(client.post("/v1/datasets", headers=headers, params={"name": "x\x00/../../etc/passwd"},
                                content=small_file), 422)
    assert body["code"] == "invalid_name" and "control characters" in body["detail"]
    boundary = "b0undary"
    multipart = (f"--{boundary}\r\nContent-Disposition: form-data; name=\"file\"; filename=\"a\x00../../x\"\r\n"
                 f"Content-Type: application/x-hdf5\r\n\r\n").encode() + small_file + f"\r\n--{boundary}--\r\n".encode()
    r = client.post("/v1/datasets", headers={**headers, "Content-Type": f"multipart/form-data; boundary={boundary}"},
                    content=multipart)
    assert _problem(r, 422)["code"] == "invalid_name"
    _problem(client.post("/v1/datasets", headers=headers, params={"name": "x" * 301}, content=small_file), 422)
    r = client.post("/v1/datasets", headers=headers, files={"file": ("x" * 70_000, small_file, "application/x-hdf5")})
    _problem(r, 400, 413, 422)


@pytest.mark.parametrize("bad", BAD_IDS, ids=range(len(BAD_IDS)))
def test_ids_in_urls(api, bad):
    client, headers, _ = api
    for method, url in [("GET", f"/v1/datasets/{bad}"), ("DELETE", f"/v1/datasets/{bad}"), ("GET", f"/v1/jobs/{bad}"),
                        ("POST", f"/v1/jobs/{bad}/cancel"), ("GET", f"/v1/jobs/{bad}/policy"),
                        ("GET", f"/v1/jobs/{bad}/policy?format=onnx"), ("GET", f"/v1/jobs/{bad}/checkpoints"),
                        ("GET", f"/v1/jobs/{bad}/events"), ("GET", f"/v1/jobs/{bad}/metrics"),
                        ("GET", f"/v1/jobs/{bad}/evaluations"), ("GET", f"/v1/jobs/{bad}/curve.png")]:
        _problem(client.request(method, url, headers=headers), 404, 405)


@pytest.mark.parametrize("fmt", HOSTILE + ["policy.pt", "torchscript\x00"], ids=range(len(HOSTILE) + 2))
def test_policy_format(api, fmt):
    client, headers, _ = api
    _problem(client.get("/v1/jobs/job_0660d61a6842d90498d6dc/policy", headers=headers, params={"format": fmt}), 422)


@pytest.fixture(scope="module")
def dataset_id(sandbox, tokens, small_file):
    client, _ = sandbox
    headers = {"Authorization": f"Bearer {tokens['alice']}"}
    r = client.post("/v1/datasets", headers=headers, params={"name": "small"}, content=small_file)
    assert r.status_code == 201, r.text
    yield r.json()["id"]
    assert client.delete(f"/v1/datasets/{r.json()['id']}", headers=headers).status_code == 204


@pytest.mark.parametrize("value", HOSTILE + ["x\x00y"], ids=range(len(HOSTILE) + 1))
def test_job_fields(dataset_id, api, value):
    """No job is created (nothing is queued): every field is refused before the row is written.

    Only the set of job ids is compared: another test's job may change status meanwhile, and that is not ours."""
    client, headers, _ = api

    def job_ids() -> set[str]:
        return {job["id"] for job in client.get("/v1/jobs", headers=headers, params={"limit": 100}).json()["data"]}

    before = job_ids()
    for body in [{"dataset_id": value}, {"dataset_id": dataset_id, "env": value},
                 {"dataset_id": dataset_id, "task": value}, {"dataset_id": dataset_id, "preset": value},
                 {"dataset_id": dataset_id, "algorithm": value},
                 {"dataset_id": dataset_id, "overrides": {value: 1}},
                 {"dataset_id": dataset_id, "overrides": {"checkpoint_dir": value}},
                 {"dataset_id": dataset_id, "overrides": {"sac.hidden": value}}]:
        _problem(client.post("/v1/jobs", headers=headers, json=body), 404, 422)
    assert job_ids() == before
