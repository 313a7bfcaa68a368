"""Sealed HDF5 files: a sha256 of everything after HDF5's user block, written into that block, and
checked before HDF5 parses the file. HDF5 1.10 crashes the process (a segmentation fault) or raises
assorted errors on some damaged metadata; the files dbf-hpc reads back (the basis cache, checkpoints)
are checked here first, so a damaged one is a line saying so, never a crash or a traceback.

Write with h5py.File(path, "w", userblock_size=USERBLOCK), close, then seal(path, tag). Not collective.
"""
from __future__ import annotations

import errno
import hashlib
import os

USERBLOCK = 512   # HDF5's user block, which the library skips: the tag and the sha256 of the rest


def _user_block(path: str, tag: bytes) -> tuple:
    """(the user block the file holds, the one that seals the bytes after it). An OSError for a path
    that is not a regular file: opening a named pipe there waited for a writer for ever (red team: a
    FIFO at a basis cache entry hung the run; at a checkpoint, the resume)."""
    if not os.path.isfile(path):
        raise OSError(errno.EINVAL, f"{path} is not a regular file")
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        header = handle.read(USERBLOCK)
        for chunk in iter(lambda: handle.read(1 << 20), b""):
            digest.update(chunk)
    return header, (tag + digest.hexdigest().encode() + b"\n").ljust(USERBLOCK, b"\0")


def seal(path: str, tag: bytes) -> None:
    """Write the sha256 of the file after its user block, after `tag`, into that block."""
    _, block = _user_block(path, tag)
    with open(path, "r+b") as handle:
        handle.write(block)


def seal_problem(path: str, tag: bytes, writer: str = "dbf-hpc") -> str | None:
    """Why the file's seal does not hold (None if it does), read without HDF5."""
    return check(path, tag, writer)[0]


def check(path: str, tag: bytes, writer: str = "dbf-hpc") -> tuple:
    """(seal_problem's answer, the user block read): the block names the file's content, so that
    whoever opens the path later can tell it is still the file checked (user_block_of_open)."""
    try:
        stored, expected = _user_block(path, tag)
    except OSError as e:
        return f"cannot be read ({type(e).__name__})", b""
    if not stored.startswith(tag):
        return f"has no file checksum (written by an older version, or not by {writer})", stored
    if stored != expected:
        return "fails its file checksum (damaged or truncated)", stored
    return None, stored


def user_block_of_open(h5file) -> bytes:
    """The user block of a file h5py holds open (its own descriptor: a path replaced since does not
    change what it reads)."""
    return os.pread(h5file.id.get_vfd_handle(), USERBLOCK, 0)
