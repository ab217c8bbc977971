"""Bearer tokens, stored as SHA-256 hashes; every request resolves to one owner whose objects it may see."""
from __future__ import annotations

import hashlib
import secrets

from fastapi import Request
from fastapi.concurrency import run_in_threadpool
from fastapi.security import HTTPBearer
from sqlalchemy import bindparam, select
from sqlalchemy.orm import Session, sessionmaker

from kernel.ids import new_id
from kernel.models import Owner, Token, utcnow

from .problems import Problem

LOCAL_OWNER = "local"


def hash_token(token: str) -> str:
    # Tokens are 256 random bits, so a plain fast hash is enough: there is nothing to brute-force.
    return hashlib.sha256(token.encode()).hexdigest()


def get_or_create_owner(session: Session, name: str) -> Owner:
    owner = session.scalar(select(Owner).where(Owner.name == name))
    if owner is None:
        owner = Owner(id=new_id("own"), name=name)
        session.add(owner)
        session.flush()
    return owner


def create_token(factory: sessionmaker[Session], name: str) -> str:
    """A new token for owner `name` (created if needed); only its hash is kept."""
    token = "drop_" + secrets.token_urlsafe(32)
    with factory() as session, session.begin():
        owner = get_or_create_owner(session, name)
        session.add(Token(id=new_id("tok"), owner_id=owner.id, name=name, token_hash=hash_token(token)))
    return token


class TokenNotFound(LookupError):
    pass


def list_tokens(factory: sessionmaker[Session], owner: str | None = None) -> list[tuple[Token, str]]:
    """(token, owner name) rows, oldest first; never the secrets, which are not stored."""
    q = select(Token, Owner.name).join(Owner, Owner.id == Token.owner_id).order_by(Token.id)
    if owner is not None:
        q = q.where(Owner.name == owner)
    with factory() as session:
        return [(row.Token, row.name) for row in session.execute(q)]


def revoke_token(factory: sessionmaker[Session], ref: str) -> Token:
    """Revoke the token with id `ref`, the one token whose id starts with `ref`, or the token `ref` itself.

    Each API process remembers a token's owner for DROP_TOKEN_CACHE_S seconds (app/core/token_cache.py), so a
    revoked token is refused from that long after at the latest.
    """
    if not ref:
        raise TokenNotFound("give a token id, the start of one, or the token itself")
    with factory() as session, session.begin():
        if ref.startswith("drop_"):
            rows = list(session.scalars(select(Token).where(Token.token_hash == hash_token(ref))))
        else:
            rows = list(session.scalars(select(Token).where(Token.id.startswith(ref, autoescape=True)).limit(2)))
        if not rows:
            raise TokenNotFound(f"no token matches {ref!r}; `drop token list` shows them")
        if len(rows) > 1:
            raise TokenNotFound(f"{ref!r} matches more than one token; give more of the id")
        row = rows[0]
        if row.revoked_at is None:
            row.revoked_at = utcnow()
    return row


def _unauthorized(detail: str) -> Problem:
    return Problem(401, "unauthorized", detail, headers={"WWW-Authenticate": "Bearer"})


def _local_owner(factory: sessionmaker[Session]) -> str:
    with factory() as session, session.begin():
        return get_or_create_owner(session, LOCAL_OWNER).id


TOKEN_OWNER = select(Token.owner_id).where(Token.token_hash == bindparam("digest"), Token.revoked_at.is_(None))


class OwnerBearer(HTTPBearer):
    """The owner id of a request, as one FastAPI dependency that also declares the bearer scheme in the OpenAPI
    schema. One dependency, not the owner over the scheme: each level of FastAPI's dependency solving costs a job
    read about 15 µs. It never answers 401 by itself (auto_error=False), so a missing or wrong header gets this
    module's problem+json 401, and `drop serve` may go without one. Async, so a remembered token costs no threadpool
    hop."""

    async def __call__(self, request: Request) -> str:
        state = request.app.state
        if state.settings.auth_disabled:
            owner_id = getattr(state, "local_owner_id", None)
            if owner_id is None:
                owner_id = state.local_owner_id = await run_in_threadpool(_local_owner, state.sessions)
            return owner_id
        credentials = await super().__call__(request)
        if credentials is None:  # no header, another scheme, or no token after `Bearer`
            raise _unauthorized("send `Authorization: Bearer <token>`; create one with `drop token create --name NAME`")
        digest = hash_token(credentials.credentials)
        owner_id = state.tokens.get(digest)
        if owner_id is None:
            row = await state.fast_reads.one(TOKEN_OWNER, digest=digest)
            if row is None:
                raise _unauthorized("unknown or revoked token")
            owner_id = row.owner_id
            state.tokens.put(digest, owner_id)
        return owner_id


current_owner = OwnerBearer(scheme_name="bearer", auto_error=False,
                            description="`Authorization: Bearer <token>`; create one with `drop token create --name "
                                        "NAME`. Not needed by `drop serve` unless it runs with `--auth`.")
