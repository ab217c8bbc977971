"""HDF5 structures whose reads would reach another file: the engine's SafeHDF5 and the upload path must both refuse
them. Each builder takes the other file's path and returns a function that writes the structure into an open file."""
from __future__ import annotations

from pathlib import Path

import h5py


def external_link(secret: Path):
    def make(f):
        f["rewards"] = h5py.ExternalLink(str(secret), "/rewards")
    return make


def soft_link_through_external_group(secret: Path):
    def make(f):
        f["elsewhere"] = h5py.ExternalLink(str(secret), "/")
        f["rewards"] = h5py.SoftLink("/elsewhere/rewards")
    return make


def external_storage(secret: Path):
    def make(f):
        f.create_dataset("rewards", shape=(50,), dtype="f4", external=[(str(secret), 0, 200)])
    return make


def virtual(secret: Path):
    def make(f):
        layout = h5py.VirtualLayout(shape=(50,), dtype="f4")
        layout[:] = h5py.VirtualSource(str(secret), "rewards", shape=(50,))
        f.create_virtual_dataset("rewards", layout)
    return make


IDS = ["external-link", "soft-link-via-external", "external-storage", "virtual-dataset"]
