"""Checkpoints: a run's state at the end of a step, so that a killed run continues to the result an
uninterrupted run gives (`dbf-hpc run --resume`).

A checkpoint is an HDF5 file (OUT.h5.checkpoint): data, never code. It holds
- the state (arrays and scalars: t, dt, step count, the integrator's state, the recorder's
  statistics, how many samples the .partial output holds);
- the identity of the run it belongs to, part by part (the scene, the structure's operators and
  files, the PETSc options, the rank count, the method); a resume that differs in any part is
  refused, naming the part;
- a sha256 checksum over every dataset and the identity: a flipped bit is refused, never resumed;
- a seal over the whole file (sealed.py), checked before HDF5 parses it: damaged metadata is the
  same one-line refusal, not an HDF5 crash or traceback.
It is written under a temporary name, fsynced and renamed, so a kill never leaves half of one.

Not collective: a Checkpoint is written and read by one rank (rank 0 of a run, or the rank running a
sweep's case); a run broadcasts what that rank decides (run.py).
"""
from __future__ import annotations

import hashlib
import json
import os

import h5py
import numpy as np

from . import sealed
from .errors import WRITE_ERRORS, InputError, not_a_regular_file, park

FORMAT = "dbf-hpc-checkpoint-2"
SEAL = b"dbf-hpc checkpoint sha256 "   # the tag of the file's seal (sealed.py)


def identity(**parts) -> dict:
    """The identity of a run from its parts (any JSON-able values), each part hashed alone so that a
    mismatch can be named."""
    return {name: hashlib.sha256(json.dumps(value, sort_keys=True, default=str).encode()).hexdigest()
            for name, value in parts.items()}


def arrays_sha256(arrays: dict, salt: bytes = b"") -> str:
    """sha256 of named arrays (each name, dtype, shape and bytes, in name order) after `salt`."""
    h = hashlib.sha256(salt)
    for name in sorted(arrays):
        value = np.ascontiguousarray(arrays[name])
        h.update(f"{name}|{value.dtype.str}|{value.shape}|".encode())
        h.update(value.tobytes())
    return h.hexdigest()


def _checksum(datasets: dict, ident: dict) -> str:
    return arrays_sha256(datasets, json.dumps(ident, sort_keys=True).encode())


class Checkpoint:
    """The checkpoint file of one output, for a run of the given identity (rank 0 only)."""

    def __init__(self, path: str, ident: dict):
        self.path, self.identity = path, ident

    def write(self, state: dict) -> None:
        """Store `state` (name -> array or scalar) atomically."""
        datasets = {name: np.asarray(value) for name, value in state.items()}
        tmp = f"{self.path}.tmp"
        f = None
        try:
            # a file left there (a killed run's, another run's) is removed, not written through: a symlink
            # there had HDF5 overwrite the file it pointed to (red team)
            if os.path.lexists(tmp):
                os.remove(tmp)
            f = h5py.File(tmp, "w", userblock_size=sealed.USERBLOCK)
            for name, value in datasets.items():
                f.create_dataset(name, data=value)
            f.attrs["format"] = FORMAT
            f.attrs["identity"] = json.dumps(self.identity, sort_keys=True)
            f.attrs["checksum"] = _checksum(datasets, self.identity)
            f.close()
            sealed.seal(tmp, SEAL)
            with open(tmp, "rb") as handle:
                os.fsync(handle.fileno())
            os.replace(tmp, self.path)
        except BaseException as e:
            # Red team (a full disk while a checkpoint was written): closing the file after the failed
            # write, as `with` did, or freeing it later crashed HDF5 (signal 11); it is kept instead
            # (errors.park), and the half-written file is removed, also after any other failure (red
            # team: a failed rename, or a bug, left OUT.h5.checkpoint.tmp behind)
            if isinstance(e, WRITE_ERRORS):
                park(f)
            if os.path.isfile(tmp) and not os.path.islink(tmp):   # this write's own file (a directory there stays)
                os.remove(tmp)
            raise

    def read(self) -> dict | None:
        """The stored state, or None if there is no checkpoint. An InputError, naming the cause,
        for one that belongs to another run or is corrupt."""
        if not os.path.exists(self.path):
            return None
        kind = not_a_regular_file(self.path)
        if kind:   # red team: a directory or a named pipe there "cannot be read (OSError)"
            raise InputError(f"{self.path} {kind}, not a checkpoint: remove it or choose another output name")
        problem = sealed.seal_problem(self.path, SEAL)   # before HDF5 parses it (it may crash on damage)
        if problem:
            from .output import is_dbf_checkpoint

            # new-user pass: a foreign file there was told "or rerun without --resume", which then
            # refuses it too ("exists and is not a dbf-hpc output"); only a checkpoint of an older
            # version (or a damaged one) is set aside by a run from t = 0
            advice = "rerun without --resume" if is_dbf_checkpoint(self.path) else "choose another output name"
            raise InputError(f"{self.path} {problem}; remove it or {advice}")
        try:
            with h5py.File(self.path, "r") as f:
                if f.attrs.get("format") != FORMAT:
                    raise InputError(f"{self.path} is not a dbf-hpc checkpoint of this version; remove it or rerun "
                                     f"without --resume")
                stored = json.loads(f.attrs["identity"])
                state = {}
                f.visititems(lambda name, obj: state.__setitem__(name, obj[()]) if isinstance(obj, h5py.Dataset)
                             else None)
                checksum = f.attrs["checksum"]
        except (OSError, KeyError, ValueError, RuntimeError, TypeError) as e:
            raise InputError(f"{self.path} cannot be read ({type(e).__name__}); remove it or rerun without "
                             f"--resume") from None
        different = [part for part in sorted(set(stored) | set(self.identity))
                     if stored.get(part) != self.identity.get(part)]
        if "request" in different:   # the question as asked (run.request_identity): named by the parts it holds
            different = [part for part in different if part != "request"] or ["scene"]
        if different:
            verb = "differs" if len(different) == 1 and not different[0].endswith("s") else "differ"  # options, ranks
            # only when nothing else that changes the basis differs (red team: a changed scene or
            # structure read as "the cache cleared, another rank count")
            why = ("; the basis was rebuilt since (the cache cleared, another rank count), and the state it "
                   "holds is another state in the new one" if "coordinates" in different
                   and set(different) <= {"coordinates", "ranks"} else "")
            raise InputError(f"{self.path} was written by a different scene or setup ({', '.join(different)} "
                             f"{verb}{why}); remove it or rerun without --resume")
        if _checksum(state, stored) != checksum:
            raise InputError(f"{self.path} is corrupt (its checksum does not match its data); remove it to start "
                             f"again from t = 0")
        return state

    def remove(self) -> None:
        for path in (self.path, f"{self.path}.tmp"):
            if os.path.exists(path):
                os.remove(path)
