"""Bearer tokens and ownership: another owner's objects answer 404, as if they did not exist."""
from __future__ import annotations

from sqlalchemy import select


def test_requests_without_a_valid_token_are_401(client):
    for headers in ({}, {"Authorization": "Bearer nope"}, {"Authorization": "Basic abc"}):
        r = client.get("/v1/datasets", headers=headers)
        assert r.status_code == 401
        assert r.headers["content-type"] == "application/problem+json" and r.json()["code"] == "unauthorized"


def test_tokens_are_stored_hashed(app, tokens):
    from app.models import Token

    with app.state.sessions() as s:
        stored = list(s.scalars(select(Token.token_hash)))
    assert tokens["alice"] not in stored and all(len(h) == 64 for h in stored)


def test_owner_cannot_see_another_owners_objects(alice, bob, hopper_file):
    ds = alice.upload(hopper_file).json()
    job = alice.post("/v1/jobs", json={"dataset_id": ds["id"], "preset": "smoke"}).json()
    alice.post(f"/v1/jobs/{job['id']}/cancel")
    alice.wait(job["id"], {"cancelled", "succeeded", "failed"})

    for path in (f"/v1/datasets/{ds['id']}", f"/v1/jobs/{job['id']}", f"/v1/jobs/{job['id']}/events",
                 f"/v1/jobs/{job['id']}/metrics", f"/v1/jobs/{job['id']}/policy", f"/v1/jobs/{job['id']}/curve.png"):
        r = bob.get(path)
        assert r.status_code == 404, path
        assert r.json()["code"] == "not_found"
    assert bob.delete(f"/v1/datasets/{ds['id']}").status_code == 404
    assert bob.post(f"/v1/jobs/{job['id']}/cancel").status_code == 404
    assert bob.post("/v1/jobs", json={"dataset_id": ds["id"], "preset": "smoke"}).status_code == 404
    assert ds["id"] not in [d["id"] for d in bob.get("/v1/datasets").json()["data"]]
    assert job["id"] not in [j["id"] for j in bob.get("/v1/jobs").json()["data"]]

    assert alice.get(f"/v1/datasets/{ds['id']}").status_code == 200
    assert alice.delete(f"/v1/datasets/{ds['id']}").status_code == 204
