"""Serialise an owner's writes that must see each other: quota counts, and a dataset's delete against a job's creation.

The lock is a no-op UPDATE of the owner's row, taken before anything is read: PostgreSQL holds that row lock, and
SQLite (which has no row locks) its database write lock, until the transaction ends. On SQLite it must come first: a
transaction that read before it took the write lock could have read what another writer was about to change.
"""
from __future__ import annotations

from sqlalchemy import update
from sqlalchemy.orm import Session

from kernel.models import Owner


def lock_owner(s: Session, owner_id: str) -> None:
    s.execute(update(Owner).where(Owner.id == owner_id).values(name=Owner.name))
