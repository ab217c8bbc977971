"""Bearer tokens and ownership: a missing, malformed or revoked token answers 401, another owner's objects 404."""
from __future__ import annotations

import secrets
import time

import pytest
from sqlalchemy import select

from .processes import settings_env


def test_tokens_are_stored_hashed(app, tokens):
    from kernel.models import Token

    with app.state.sessions() as s:
        stored = list(s.scalars(select(Token.token_hash)))
    assert tokens["alice"] not in stored and all(len(h) == 64 for h in stored)


def test_owner_cannot_see_another_owners_objects(alice, bob, hopper_file):
    ds = alice.api.upload_dataset(hopper_file)
    job = alice.post("/v1/jobs", json={"dataset_id": ds["id"], "preset": "smoke"}).json()
    alice.post(f"/v1/jobs/{job['id']}/cancel")
    alice.api.wait(job["id"], timeout=120)

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


@pytest.fixture
def carol(app):
    """A fresh owner with two tokens, so one can be revoked while the other still works."""
    from app.core.auth import create_token

    name = f"carol-{secrets.token_hex(4)}"
    return name, create_token(app.state.sessions, name), create_token(app.state.sessions, name)


def _bearer(token: str) -> dict:
    return {"Authorization": f"Bearer {token}"}


def _assert_401(r, needle: str) -> None:
    assert r.status_code == 401, r.text
    assert r.headers["content-type"] == "application/problem+json" and r.headers["www-authenticate"] == "Bearer"
    body = r.json()
    assert body["code"] == "unauthorized" and needle in body["detail"], body


def test_malformed_headers_are_401(client, carol):
    _, token, _ = carol
    missing = "send `Authorization: Bearer <token>`"
    cases = [
        ({}, missing),
        ({"Authorization": ""}, missing),
        ({"Authorization": "Bearer"}, missing),
        ({"Authorization": "Bearer    "}, missing),
        ({"Authorization": token}, missing),  # no scheme
        ({"Authorization": f"Token {token}"}, missing),  # a real token under the wrong scheme
        ({"Authorization": "Basic YWxpY2U6c2VjcmV0"}, missing),
        ({"Authorization": "Bearer garbage"}, "unknown or revoked"),
        ({"Authorization": f"Bearer {token[:-1]}"}, "unknown or revoked"),
        ({"Authorization": f"Bearer {token}x"}, "unknown or revoked"),
        ({"Authorization": "Bearer " + "x" * 100_000}, "unknown or revoked"),
        ({"Authorization": "Bearer drop_ключ€🔑".encode()}, "unknown or revoked"),  # non-ASCII bytes
        ({"Authorization": b"Bearer drop_\xff\xfe\x80"}, "unknown or revoked"),  # not even UTF-8
    ]
    for headers, needle in cases:
        _assert_401(client.get("/v1/datasets", headers=headers), needle)
    # The scheme is case-insensitive (RFC 9110) and spaces around the token do not matter.
    assert client.get("/v1/datasets", headers={"Authorization": f"bearer   {token}  "}).status_code == 200


def _cli(settings, monkeypatch, capsys, *argv: str) -> tuple[int, str, str]:
    from app.cli import main

    for key, value in settings_env(settings).items():
        if key.startswith("DROP_"):
            monkeypatch.setenv(key, value)
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def _refused_within(client, token: str, seconds: float) -> None:
    """Refused (401) at the latest `seconds` after its revocation, and from then on: API processes trust a token
    lookup for DROP_TOKEN_CACHE_S."""
    deadline = time.monotonic() + seconds
    while True:
        sent = time.monotonic()  # when the request went out, not when its answer was read (a descheduled test)
        if client.get("/v1/datasets", headers=_bearer(token)).status_code != 200:
            break
        assert sent < deadline, f"a revoked token still works after {seconds} s"
        time.sleep(0.2)
    for _ in range(3):
        _assert_401(client.get("/v1/datasets", headers=_bearer(token)), "unknown or revoked")


def test_revoked_token_is_refused_within_seconds(client, settings, carol, monkeypatch, capsys):
    name, first, second = carol
    assert client.get("/v1/datasets", headers=_bearer(first)).status_code == 200

    code, out, _ = _cli(settings, monkeypatch, capsys, "token", "list", "--owner", name)
    ids = [line.split()[0] for line in out.splitlines()[1:]]
    assert code == 0 and len(ids) == 2 and all(line.endswith(" -") for line in out.splitlines()[1:])

    code, out, _ = _cli(settings, monkeypatch, capsys, "token", "revoke", first)  # by the token itself
    assert code == 0 and "revoked" in out
    _refused_within(client, first, settings.token_cache_s + 1)
    assert client.get("/v1/datasets", headers=_bearer(second)).status_code == 200  # the owner's other token

    revoked = next(i for i in ids if i in out)
    other = next(i for i in ids if i != revoked)
    code, out, _ = _cli(settings, monkeypatch, capsys, "token", "revoke", other[:-3])  # by the start of its id
    assert code == 0 and other in out
    _refused_within(client, second, settings.token_cache_s + 1)

    code, out, _ = _cli(settings, monkeypatch, capsys, "token", "list", "--owner", name)
    assert code == 0 and not any(line.endswith(" -") for line in out.splitlines()[1:])


def test_revoke_needs_exactly_one_match(settings, carol, monkeypatch, capsys):
    code, _, err = _cli(settings, monkeypatch, capsys, "token", "revoke", "tok_")
    assert code == 2 and "more than one token" in err
    code, _, err = _cli(settings, monkeypatch, capsys, "token", "revoke", "tok_nope")
    assert code == 2 and "no token matches 'tok_nope'" in err
    code, _, err = _cli(settings, monkeypatch, capsys, "token", "revoke", "drop_not-a-real-token")
    assert code == 2 and "no token matches" in err


def test_token_lookups_are_cached_briefly():
    from app.core.token_cache import TokenCache

    now = [100.0]  # a clock of the test's own: a descheduled test process cannot expire an entry early
    cache = TokenCache(ttl_s=5, clock=lambda: now[0])
    cache.put("h", "own_1")
    now[0] += 4.9
    assert cache.get("h") == "own_1" and cache.get("other") is None
    now[0] += 0.1
    assert cache.get("h") is None
    off = TokenCache(ttl_s=0)
    off.put("h", "own_1")
    assert off.get("h") is None
