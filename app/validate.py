"""Validate (and if needed convert) an uploaded dataset in a child process with memory, CPU and file-size limits.

The upload is untrusted: parsing HDF5 or a zip happens in a child forked from a fork server, never in the API
process, so a hostile or huge file can at worst kill the child. The child sends back the report or the error.
"""
from __future__ import annotations

import asyncio
import json
import multiprocessing
import os
import re
import resource
import shutil
import stat
import zipfile
from pathlib import Path

from .storage_errors import storage_errno

HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"
ZIP_MAGIC = b"PK\x03\x04"


class Invalid(Exception):
    pass


# ------------------------------------------------------------------------------------------------ child side
def _check_zip(zf: zipfile.ZipFile, cap: int) -> None:
    """Entries are only ever read by the code's own names, never extracted by theirs; still, a zip that carries
    paths meant to escape a folder, links, or more than `cap` bytes once expanded is refused as hostile."""
    total = 0
    for info in zf.infolist():
        name = info.filename
        parts = name.replace("\\", "/").split("/")
        if name.startswith(("/", "\\")) or re.match(r"[A-Za-z]:", name) or ".." in parts:
            raise Invalid(f"zip entry {name!r}: an absolute path or a '..' component; not allowed")
        if stat.S_ISLNK(info.external_attr >> 16):
            raise Invalid(f"zip entry {name!r}: a symbolic link; not allowed")
        total += info.file_size
    if total > cap:
        raise Invalid(f"zip: its entries expand to {total} bytes, over the limit of {cap} "
                      "(4x DROP_MAX_UPLOAD_BYTES)")


def _sniff(path: Path, cap: int) -> str:
    head = path.open("rb").read(8)
    if head.startswith(HDF5_MAGIC):
        return "hdf5"
    if head.startswith(ZIP_MAGIC):
        with zipfile.ZipFile(path) as zf:
            _check_zip(zf, cap)
            names = zf.namelist()
        if any(n.endswith("main_data.hdf5") for n in names):
            return "minari"
        if any(n.endswith(".npy") for n in names):
            return "npz"
        raise Invalid("file: a zip that is neither a Minari dataset (no data/main_data.hdf5) nor an .npz")
    raise Invalid("file: not an HDF5 file, an .npz or a Minari zip (unrecognised leading bytes)")


def _minari_env(zf: zipfile.ZipFile) -> str | None:
    """The env id recorded in the dataset's metadata.json, if any."""
    members = {Path(n).name: n for n in zf.namelist() if Path(n).parent.name == "data" or "/" not in n}
    if "metadata.json" not in members:
        return None
    try:
        meta = json.loads(zf.read(members["metadata.json"]))
        spec = meta.get("env_spec")
        spec = json.loads(spec) if isinstance(spec, str) else spec
        return (spec or {}).get("id")
    except (ValueError, AttributeError):
        return None


def _minari_arrays(raw: Path, cap: int) -> dict:
    """Concatenate Minari episodes into D4RL layout (observations[:-1] / [1:], terminations, truncations)."""
    import h5py
    import numpy as np

    from drop_engine.safe_hdf5 import SafeHDF5

    cols: dict[str, list] = {k: [] for k in ("observations", "actions", "rewards", "next_observations", "terminals",
                                             "timeouts")}
    try:
        with h5py.File(raw, "r") as handle:
            reader = SafeHDF5(handle, cap)
            episodes = sorted((k for k in handle if k.startswith("episode_")), key=lambda k: int(k.split("_")[1]))
            if not episodes:
                raise Invalid("main_data.hdf5: no episode_N groups")
            for name in episodes:
                ep = handle[name]
                for key in ("observations", "actions", "rewards", "terminations", "truncations"):
                    if key not in ep or not isinstance(ep[key], h5py.Dataset):
                        raise Invalid(f"{name}/{key}: missing or not an array (only Box observation spaces are supported)")
                obs, actions = reader.read(f"{name}/observations"), reader.read(f"{name}/actions")
                n = len(actions)
                if len(obs) != n + 1:
                    raise Invalid(f"{name}/observations: expected {n + 1} rows (actions + 1), found {len(obs)}")
                cols["observations"].append(obs[:-1])
                cols["next_observations"].append(obs[1:])
                cols["actions"].append(actions)
                cols["rewards"].append(reader.read(f"{name}/rewards"))
                term = reader.read(f"{name}/terminations").astype(bool)
                trunc = reader.read(f"{name}/truncations").astype(bool)
                cols["terminals"].append(term)
                cols["timeouts"].append(trunc & ~term)
    except OSError as exc:
        raise Invalid(f"main_data.hdf5: not a readable HDF5 file ({exc})") from None
    return {k: np.concatenate(v) for k, v in cols.items()}


def _minari_to_hdf5(src: Path, dest: Path, cap: int) -> None:
    from drop_engine.data import from_arrays, save_hdf5

    raw = dest.with_name("minari_main.hdf5")
    try:
        with zipfile.ZipFile(src) as zf:
            main = next(n for n in zf.namelist() if n.endswith("main_data.hdf5"))
            # zipfile stops at the entry's declared size (and then fails its CRC), which _check_zip has bounded.
            with zf.open(main) as fin, raw.open("wb") as fout:
                shutil.copyfileobj(fin, fout, 1 << 20)
            env_name = _minari_env(zf)
        arrays = _minari_arrays(raw, cap)
    finally:
        raw.unlink(missing_ok=True)
    from_arrays(arrays)  # validate before writing
    save_hdf5(dest, arrays, {"env_name": env_name} if env_name else {})


def _link_or_copy(src: Path, target: Path) -> None:
    try:
        os.link(src, target)
    except OSError:
        shutil.copyfile(src, target)


def _child(src: Path, dest_dir: Path, cap: int) -> dict:
    from drop_engine.data import DatasetError, describe, load_dataset

    try:
        kind = _sniff(src, cap)
        if kind == "minari":
            target = dest_dir / "data.hdf5"
            _minari_to_hdf5(src, target, cap)
        else:
            target = dest_dir / ("data.npz" if kind == "npz" else "data.hdf5")
            _link_or_copy(src, target)
        try:  # a converted Minari file is our own output, made from arrays already held to `cap`
            report = describe(load_dataset(target, max_bytes=None if kind == "minari" else cap)).to_dict()
        except BaseException:
            target.unlink(missing_ok=True)
            raise
        return {"ok": True, "format": kind, "file": target.name, "report": report}
    except (Invalid, DatasetError) as exc:
        return {"ok": False, "error": str(exc)}
    except zipfile.BadZipFile as exc:
        return {"ok": False, "error": f"file: broken zip ({exc})"}
    except MemoryError:
        return {"ok": False, "error": "file: too large to validate within the validator's memory limit"}


# ------------------------------------------------------------------------------------------------ parent side
_context = None


def _forkserver():
    """A fork server that has already imported the engine, so each validation starts in milliseconds, not seconds."""
    global _context
    if _context is None:
        ctx = multiprocessing.get_context("forkserver")
        ctx.set_forkserver_preload(["app.validate", "drop_engine.data"])
        _context = ctx
    return _context


def _entry(conn, src: str, dest_dir: str, cap: int, memory: int, cpu_s: int) -> None:
    """The child: limits first, then parse; the answer goes back over the pipe."""
    resource.setrlimit(resource.RLIMIT_AS, (memory, memory))
    resource.setrlimit(resource.RLIMIT_CPU, (cpu_s, cpu_s + 5))
    resource.setrlimit(resource.RLIMIT_FSIZE, (cap + (1 << 20), cap + (1 << 20)))
    try:
        out = _child(Path(src), Path(dest_dir), cap)
    except BaseException as exc:  # anything unexpected is still the file's fault, said without a traceback
        # ...unless the disk is full or read-only: then the parent raises the OSError it is.
        out = {"ok": False, "error": f"file: cannot be read ({type(exc).__name__}: {str(exc)[:200]})",
               "errno": storage_errno(exc)}
    conn.send(out)
    conn.close()


def _run(src: Path, dest_dir: Path, cap: int, memory: int, timeout: float) -> dict:
    ctx = _forkserver()
    receiver, sender = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_entry, args=(sender, str(src), str(dest_dir), cap, memory, int(timeout) + 1),
                       daemon=True)
    proc.start()
    sender.close()
    try:
        if not receiver.poll(timeout):
            raise Invalid(f"file: validation did not finish within {timeout:.0f} s")
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


async def validate_file(src: Path, dest_dir: Path, *, memory: int, timeout: float, max_bytes: int) -> dict:
    """Validate in a limited child process; returns {"format", "file", "report"} or raises Invalid with the message
    for the client. A Minari zip may expand to at most 4x the upload limit."""
    result = await asyncio.to_thread(_run, src, dest_dir, 4 * max_bytes, memory, timeout)
    if result.get("errno"):
        raise OSError(result["errno"], os.strerror(result["errno"]))
    if not result["ok"]:
        raise Invalid(result["error"])
    return result
