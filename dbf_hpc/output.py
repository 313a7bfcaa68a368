"""HDF5 output of a run (one file; the layout is a contract, see README "Outputs").

The file is written by rank 0 under a temporary name `OUT.h5.partial` while the run goes, samples
streamed in blocks (memory stays flat however long the run), and renamed to OUT.h5 only when it is
complete: a crash leaves a `.partial` file, never one that looks finished, and never touches an
existing OUT.h5.
"""
from __future__ import annotations

import json
import os

import h5py
import numpy as np

from . import __version__
from .errors import InputError

BLOCK = 1024  # samples buffered between writes


def check_output_path(path: str) -> str:
    """An output path must lie in an existing, writable directory: checked before any work, so bad
    input never leaves a file behind."""
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise InputError(f"output {path!r}: directory {folder!r} does not exist")
    if not os.access(folder, os.W_OK):
        raise InputError(f"output {path!r}: directory {folder!r} is not writable")
    return path


class OutputWriter:
    """Rank 0's writer. Series: time, constraint displacement/velocity/force, the peak force since
    the previous sample (impacts are often shorter than a sample), probe displacement, reduced q and
    q'. Fixed-size data (positions, basis, reduced operators, snapshots) at `finish`."""

    def __init__(self, path: str, n_constraints: int, n_probes: int, r: int):
        self.path = path
        self.partial = f"{path}.partial"
        self.file = h5py.File(self.partial, "w")
        self.file.attrs["complete"] = False
        shapes = {"time": (), "constraints/displacement": (n_constraints,), "constraints/velocity": (n_constraints,),
                  "constraints/force": (n_constraints,), "constraints/force_peak": (n_constraints,),
                  "probes/displacement": (n_probes,),
                  "reduced/q": (r,), "reduced/qdot": (r,)}
        # Zero-width series (no constraints, no probes) are written empty at the end: HDF5 cannot
        # chunk a zero-size dimension.
        self.empty = [name for name, shape in shapes.items() if shape and shape[0] == 0]
        self.series = {name: self.file.create_dataset(name, shape=(0, *shape), maxshape=(None, *shape),
                                                      chunks=(BLOCK, *shape), dtype="f8")
                       for name, shape in shapes.items() if name not in self.empty}
        self.buffer = {name: [] for name in self.series}
        self.count = 0

    def append(self, **values) -> None:
        for name, buffer in self.buffer.items():
            buffer.append(values[name])
        if len(self.buffer["time"]) >= BLOCK:
            self.flush()

    def flush(self) -> None:
        n = len(self.buffer["time"])
        if not n:
            return
        for name, dataset in self.series.items():
            block = np.asarray(self.buffer[name], dtype=float).reshape((n, *dataset.shape[1:]))
            dataset.resize(self.count + n, axis=0)
            dataset[self.count:] = block
            self.buffer[name].clear()
        self.count += n
        self.file.flush()

    @classmethod
    def reopen(cls, path: str, samples: int) -> "OutputWriter":
        """Continue a .partial file from a checkpoint: keep its first `samples` samples."""
        self = cls.__new__(cls)
        self.path, self.partial = path, f"{path}.partial"
        self.file = h5py.File(self.partial, "r+")
        if self.file.attrs.get("complete", True):
            raise KeyError("not an incomplete dbf-hpc output")
        self.series, self.empty = {}, []
        for name in ("time", "constraints/displacement", "constraints/velocity", "constraints/force",
                     "constraints/force_peak", "probes/displacement", "reduced/q", "reduced/qdot"):
            if name not in self.file:  # zero-width series are only written at the end
                self.empty.append(name)
                continue
            dataset = self.file[name]
            if dataset.shape[0] < samples:
                raise KeyError(f"{name} holds {dataset.shape[0]} samples, the checkpoint {samples}")
            dataset.resize(samples, axis=0)
            self.series[name] = dataset
        self.buffer = {name: [] for name in self.series}
        self.count = samples
        return self

    def close(self) -> None:
        self.flush()
        self.file.close()

    def series_data(self, name: str) -> np.ndarray:
        """A series as written so far (rank 0 reads back what it streamed out)."""
        self.flush()
        if name in self.empty:
            return np.zeros((self.count, 0))
        return self.series[name][...]

    def finish(self, datasets: dict, attrs: dict, dataset_attrs: dict | None = None) -> None:
        """Write the fixed-size data and the attributes, close, and rename into place."""
        self.flush()
        for name in self.empty:
            self.file.create_dataset(name, shape=(self.count, 0), dtype="f8")
        for name, value in datasets.items():
            self.file.create_dataset(name, data=np.asarray(value))
        for name, extra in (dataset_attrs or {}).items():
            self.file[name].attrs.update(extra)
        for key, value in attrs.items():
            self.file.attrs[key] = value if isinstance(value, (str, int, float, bool, np.number)) else json.dumps(value)
        self.file.attrs["dbf_hpc_version"] = __version__
        self.file.attrs["complete"] = True
        self.file.close()
        os.replace(self.partial, self.path)

    def abort(self) -> None:
        """Close after a failure, leaving only the .partial file (it says complete = False)."""
        try:
            self.flush()
            self.file.close()
        except Exception:  # the run already failed; keep its error, not this one
            pass
