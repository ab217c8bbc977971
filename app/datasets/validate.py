"""Validate (and if needed convert) an uploaded dataset in a child process with memory, CPU and file-size limits, a
bounded number at once.

The upload is untrusted: parsing HDF5 or a zip happens in a child forked from a fork server, never in the API
process, so a hostile or huge file can at worst kill the child. The child checks what the file declares against the
dataset limits before it reads a row, then reads a block of rows at a time (`drop_engine.data.scan`), so its memory
does not grow with the dataset, and sends back the report or the error. A `Validator` runs at most
DROP_MAX_CONCURRENT_VALIDATIONS children at once per API process; the others wait their turn (each still holds its
upload slot, so the queue is bounded by DROP_MAX_CONCURRENT_UPLOADS), so uploads at once take at most that many
times DROP_VALIDATE_MEMORY_BYTES.
"""
from __future__ import annotations

import asyncio
import multiprocessing
import os
import resource
import shutil
from concurrent.futures import ThreadPoolExecutor
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path
from typing import ContextManager

from drop_engine.data_rows import DatasetLimits
from kernel.settings import Settings
from kernel.storage_errors import storage_errno

LIMIT_SETTINGS = {"rows": "DROP_MAX_DATASET_ROWS", "decoded_bytes": "DROP_MAX_DATASET_BYTES",
                  "zip_bytes": "4x DROP_MAX_UPLOAD_BYTES"}


class Invalid(Exception):
    pass


@dataclass(frozen=True)
class Limits:
    """What one validation may take; sent to the child."""

    dataset: DatasetLimits  # rows, decoded bytes, and a zip's entries expanded
    file_bytes: int  # a file the child writes: a Minari zip's HDF5 entry, or what it converts that into
    memory: int  # the child's address space
    timeout: float

    @classmethod
    def of(cls, settings: Settings) -> Limits:
        zip_bytes = 4 * settings.max_upload_bytes
        return cls(DatasetLimits(settings.max_dataset_rows, settings.max_dataset_bytes, zip_bytes),
                   max(zip_bytes, settings.max_dataset_bytes) + (16 << 20), settings.validate_memory_bytes,
                   settings.validate_timeout_s)


# ------------------------------------------------------------------------------------------------ child side
def _link_or_copy(src: Path, target: Path) -> None:
    try:
        os.link(src, target)
    except OSError:
        shutil.copyfile(src, target)


def _child(src: Path, dest_dir: Path, limits: Limits) -> dict:
    from drop_engine.data import scan
    from drop_engine.errors import DatasetError, DatasetTooLarge
    from drop_engine.formats import sniff
    from drop_engine.minari import convert

    try:
        kind = sniff(src, limits.dataset)
        target = dest_dir / ("data.npz" if kind == "npz" else "data.hdf5")
        try:
            if kind == "minari":
                convert(src, target, limits.dataset)
            else:
                _link_or_copy(src, target)
            report = scan(target, limits.dataset).to_dict()
        except BaseException:
            target.unlink(missing_ok=True)
            raise
        return {"ok": True, "format": kind, "file": target.name, "report": report}
    except DatasetTooLarge as exc:
        return {"ok": False, "error": f"{exc} ({LIMIT_SETTINGS[exc.limit]})"}
    except DatasetError as exc:
        return {"ok": False, "error": str(exc)}
    except MemoryError:
        return {"ok": False, "error": "file: too large to validate within the validator's memory limit"}


# ------------------------------------------------------------------------------------------------ parent side
_context = None


def _forkserver():
    """A fork server that has already imported the engine, so each validation starts in milliseconds, not seconds."""
    global _context
    if _context is None:
        ctx = multiprocessing.get_context("forkserver")
        ctx.set_forkserver_preload(["app.datasets.validate", "drop_engine.data", "drop_engine.minari"])
        _context = ctx
    return _context


def _entry(conn, src: str, dest_dir: str, limits: Limits) -> None:
    """The child: limits first, then parse; the answer goes back over the pipe."""
    cpu_s = int(limits.timeout) + 1
    resource.setrlimit(resource.RLIMIT_AS, (limits.memory, limits.memory))
    resource.setrlimit(resource.RLIMIT_CPU, (cpu_s, cpu_s + 5))
    resource.setrlimit(resource.RLIMIT_FSIZE, (limits.file_bytes, limits.file_bytes))
    try:
        out = _child(Path(src), Path(dest_dir), limits)
    except BaseException as exc:  # anything unexpected is still the file's fault, said without a traceback
        # ...unless the disk is full or read-only: then the parent raises the OSError it is.
        out = {"ok": False, "error": f"file: cannot be read ({type(exc).__name__}: {str(exc)[:200]})",
               "errno": storage_errno(exc)}
    conn.send(out)
    conn.close()


def _run(src: Path, dest_dir: Path, limits: Limits) -> dict:
    ctx = _forkserver()
    receiver, sender = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_entry, args=(sender, str(src), str(dest_dir), limits), daemon=True)
    proc.start()
    sender.close()
    try:
        if not receiver.poll(limits.timeout):
            raise Invalid(f"file: validation did not finish within {limits.timeout:.0f} s")
        try:
            return receiver.recv()
        except EOFError:
            proc.join(5)
            raise Invalid(f"file: the validator died (exit {proc.exitcode}); the file may need more memory than "
                          "DROP_VALIDATE_MEMORY_BYTES allows") from None
    finally:
        receiver.close()
        if proc.is_alive():
            proc.kill()
        proc.join()


class Validator:
    """The API process's validations: at most `DROP_MAX_CONCURRENT_VALIDATIONS` children at once, the rest queued in
    arrival order (a queued one whose request is cancelled never starts)."""

    def __init__(self, settings: Settings):
        self.limits, self.concurrency = Limits.of(settings), settings.max_concurrent_validations
        self._pool: ThreadPoolExecutor | None = None

    def close(self) -> None:
        """At the app's shutdown: queued validations are cancelled and the idle threads end (a later lifespan of the
        same app starts a new pool)."""
        pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=False, cancel_futures=True)

    async def validate(self, src: Path, dest_dir: Path, timer: ContextManager = nullcontext()) -> dict:
        """{"format", "file", "report"} of the file at `src`, converted into `dest_dir`, or Invalid with the message
        for the client. `timer` is entered when the child starts, not while the validation waits its turn."""
        def timed() -> dict:
            with timer:
                return _run(src, dest_dir, self.limits)

        if self._pool is None:
            self._pool = ThreadPoolExecutor(self.concurrency, thread_name_prefix="validate")
        result = await asyncio.get_running_loop().run_in_executor(self._pool, timed)
        if result.get("errno"):
            raise OSError(result["errno"], os.strerror(result["errno"]))
        if not result["ok"]:
            raise Invalid(result["error"])
        return result
