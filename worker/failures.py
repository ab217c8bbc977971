"""What a failed job tells its owner about an error the worker did not foresee. The exception's own text is fine for
most errors, but a database error's quotes the SQL statement and its parameters: internals, and possibly another
job's data. Such an error is named by its type alone; the details go to the job's traceback event and the log."""
from __future__ import annotations

import sqlite3

import psycopg
from sqlalchemy.exc import SQLAlchemyError

from kernel.exc_chain import causes

DATABASE_ERRORS = (SQLAlchemyError, sqlite3.Error, psycopg.Error)


def unexpected_failure(exc: BaseException) -> tuple[str, str]:
    """(code, message) for the job's `error`."""
    database = next((e for e in causes(exc) if isinstance(e, DATABASE_ERRORS)), None)
    if database is not None:
        return "internal_error", (f"the run stopped on a database error ({type(database).__name__}); the details "
                                  "are in the job's traceback event")
    return "training_error", f"{type(exc).__name__}: {exc}"
