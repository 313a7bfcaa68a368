"""External structural operators: K, M (and optionally C) from files, for any FE model.

The matrices are over the structure's free DOFs (boundary conditions already applied). Formats,
chosen by the file's first bytes, then its name (any case):
    %%MatrixMarket, *.mtx  Matrix Market, coordinate (general, symmetric or skew-symmetric), real
    anything else         PETSc binary (MatView/VecView with a binary viewer)
Vectors (influence vector, support-motion mass load) may also be *.npy or *.txt (one value a line).

Every rank reads only its own rows into the distributed matrix; a Matrix Market file is parsed on
every rank (text is not seekable by row), which is fine for the sizes such files are used for. The
ranks agree on every check of a file each reads itself (errors.agreed): a file one node cannot read
is every rank's one-line error, not one rank's while the others wait.

Reading is collective on the communicator it is given (default COMM_WORLD).
"""
from __future__ import annotations

import contextlib
import hashlib
import io
import os
import warnings
from dataclasses import dataclass
from typing import Optional

import numpy as np
from petsc4py import PETSc

from .errors import InputError, agreed, decided_on_rank0, not_a_regular_file, warn
from .operators import Operators, PointValues
from .petsctools import aij_from_owned_triplets, owned_rows, petsc_comm

# ||A - A^T||_F / ||A||_F above this is not a symmetric operator.
SYMMETRY_TOL = 1e-10


def _readable(path: str, what: str) -> None:
    if not_a_regular_file(path):   # what it is (red team: a named pipe "does not exist")
        raise InputError(f"{what} file {path!r} {not_a_regular_file(path)}")
    if not os.access(path, os.R_OK):
        raise InputError(f"{what} file {path!r} is not readable")
    if os.path.getsize(path) == 0 and _format(path) != "mtx":   # (an empty .mtx has no header: said so)
        raise InputError(f"{what} file {path!r} is empty")


def _format(path: str) -> str:
    """"mtx", "npy", "txt" or "petsc" (PETSc binary, or anything else): a file that begins with
    Matrix Market's header is one whatever its name, otherwise the name's ending in any case decides.
    Red team (new user): a Matrix Market file named K.MTX (or K.mm) was refused as "not a PETSc
    binary matrix". Not collective (every rank reads the same bytes)."""
    try:
        with open(path, "rb") as f:
            if f.read(14).lower() == b"%%matrixmarket":
                return "mtx"
    except OSError:
        pass
    lower = path.lower()
    return next((ext for ext in ("mtx", "npy", "txt") if lower.endswith("." + ext)), "petsc")


def _check_finite(what: str, path: str, A) -> None:
    """An InputError for a matrix or vector with NaN or Inf entries. Collective."""
    norm = A.norm(PETSc.NormType.FROBENIUS) if isinstance(A, PETSc.Mat) else A.norm()
    if not np.isfinite(norm):
        raise InputError(f"{what} file {path!r} has NaN or Inf entries")


def _read_matrix_market(path: str, what: str):
    """(shape, rows, cols, values, symmetry) of a coordinate Matrix Market file, 0-based; symmetry is
    "general", "symmetric" or "skew-symmetric" (one triangle stored). Duplicate entries, and both
    triangles under a symmetric header, are refused: readers differ on them (summed or not)."""
    with open(path, encoding="ascii", errors="replace") as f:
        header = f.readline().lower().split()
        if len(header) < 5 or header[0] != "%%matrixmarket" or header[1] != "matrix":
            raise InputError(f"{what} file {path!r} is not a Matrix Market matrix")
        layout, field, symmetry = header[2], header[3], header[4]
        if layout == "array" and field in ("real", "integer"):
            # red team: scipy.io.mmwrite of a dense ndarray writes this, and the refusal named no way out
            raise InputError(f"{what} file {path!r} is a dense Matrix Market array (\"%%MatrixMarket matrix array "
                             f"...\", every entry listed): only real coordinate Matrix Market is read for a matrix; write it with "
                             f"scipy.io.mmwrite(path, scipy.sparse.coo_matrix(A)) (mmwrite of a dense ndarray writes "
                             f"the array format), or as PETSc binary")
        if (layout != "coordinate" or field not in ("real", "integer")
                or symmetry not in ("general", "symmetric", "skew-symmetric")):
            raise InputError(f"{what} file {path!r}: only real coordinate general, symmetric or skew-symmetric "
                             f"Matrix Market is supported, got {layout} {field} {symmetry}")
        line = f.readline()
        while line.startswith("%") or (line and not line.strip()):   # comments and blank lines
            line = f.readline()
        try:
            nrows, ncols, nnz = (int(v) for v in line.split())
            _check_index_range(path, what, max(nrows, ncols), nnz)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                data = np.loadtxt(f, ndmin=2) if nnz else np.zeros((0, 3))
        except ValueError as e:
            raise InputError(f"{what} file {path!r} is malformed: {e}") from None
    if data.shape != (nnz, 3):
        raise InputError(f"{what} file {path!r} declares {nnz} entries but holds {data.shape[0]}")
    if np.any(data[:, :2] != np.floor(data[:, :2])):
        raise InputError(f"{what} file {path!r} has an index that is not an integer")
    rows, cols, values = data[:, 0].astype(np.int64) - 1, data[:, 1].astype(np.int64) - 1, data[:, 2]
    if nnz and (rows.min() < 0 or cols.min() < 0 or rows.max() >= nrows or cols.max() >= ncols):
        raise InputError(f"{what} file {path!r} has an entry outside its {nrows} x {ncols} size")
    keys = np.sort(rows * ncols + cols)
    repeated = keys[1:][keys[1:] == keys[:-1]]
    if repeated.size:
        i, j = divmod(int(repeated[0]), ncols)
        raise InputError(f"{what} file {path!r} lists {repeated.size} entr{'y' if repeated.size == 1 else 'ies'} "
                         f"twice (e.g. row {i + 1}, column {j + 1}): readers differ on whether to sum them; write "
                         f"each entry once")
    if symmetry != "general" and np.any(rows < cols) and np.any(rows > cols):
        raise InputError(f"{what} file {path!r} has a {symmetry} header but entries on both sides of the "
                         f"diagonal: such a file stores one triangle (the other is implied); write it as general "
                         f"or keep one triangle")
    if symmetry == "skew-symmetric" and np.any((rows == cols) & (values != 0)):
        raise InputError(f"{what} file {path!r} is skew-symmetric but has a non-zero diagonal entry")
    return (nrows, ncols), rows, cols, values, symmetry


def _check_index_range(path: str, what: str, size: int, nnz: int) -> None:
    """Sizes this PETSc can index (PetscInt) and that the file can hold."""
    limit = np.iinfo(PETSc.IntType).max
    if size < 0 or nnz < 0:
        raise InputError(f"{what} file {path!r} declares a negative size")
    if size > limit or nnz > limit:
        raise InputError(f"{what} file {path!r} declares {max(size, nnz)} rows or entries, more than this PETSc's "
                         f"{np.dtype(PETSc.IntType).itemsize * 8}-bit indices can address ({limit})")


# The first 4 bytes of a PETSc binary matrix (MAT_FILE_CLASSID, big-endian)
MAT_CLASSID = (1211216).to_bytes(4, "big")
VEC_CLASSID = (1211214).to_bytes(4, "big")     # and of a vector (VEC_FILE_CLASSID)


def _begins_with(path: str, head: bytes) -> bool:
    try:
        with open(path, "rb") as f:
            return f.read(len(head)) == head
    except OSError:
        return False


def _check_petsc_binary_length(path: str, what: str) -> None:
    """An InputError for a file that begins as a PETSc binary matrix (this PETSc's integer and scalar
    sizes) but is shorter than its header says: rows M, columns N, nz entries, then M row lengths, nz
    column indices and nz values (nz < 0: dense, M N values); or as a vector: n, then n values. Red team (new user): a K.bin cut short
    (a copy that ran out of space) was "(rank 0) ... not a PETSc binary matrix" after 10 s on 2
    ranks: MatLoad failed on rank 0, which reads, while rank 1 waited for its rows. Not collective
    (load_matrix runs it on rank 0 and every rank follows)."""
    vector = _begins_with(path, VEC_CLASSID)
    if not (vector or _begins_with(path, MAT_CLASSID)):
        return
    isize, ssize = np.dtype(PETSc.IntType).itemsize, np.dtype(PETSc.ScalarType).itemsize
    count = 2 if vector else 4
    with open(path, "rb") as f:
        raw = f.read(count * isize)
    header = np.frombuffer(raw[:len(raw) - len(raw) % isize], dtype=np.dtype(f">i{isize}"))
    if header.size < count:
        raise InputError(f"{what} file {path!r} is cut short: it ends inside its PETSc binary header; write it again")
    size = os.path.getsize(path)
    if vector:
        n = int(header[1])
        if n >= 0 and size < 2 * isize + n * ssize:
            raise InputError(f"{what} file {path!r} is cut short: {size} bytes, where its PETSc binary header ({n} "
                             f"entries) needs {2 * isize + n * ssize}; write it again")
        return
    m, n, nz = (int(v) for v in header[1:4])
    needed = 4 * isize + ((m + nz) * isize + nz * ssize if nz >= 0 else m * n * ssize)
    if m >= 0 and n >= 0 and size < needed:
        raise InputError(f"{what} file {path!r} is cut short: {size} bytes, where its PETSc binary header ({m} x {n}, "
                         f"{nz} entries) needs {needed}; write it again")


def _readable_format(path: str, what: str) -> str:
    """_readable, then _format. Not collective (load_matrix and load_vector agree on it)."""
    _readable(path, what)
    return _format(path)


def _matrix_market_triplets(path: str, what: str, diagonal: bool) -> tuple:
    """(shape, rows, cols, values) of a square Matrix Market matrix, both triangles (the other one
    mirrored, negated for skew-symmetric), or an InputError; with `diagonal`, every row must hold a
    non-zero diagonal entry (load_matrix). Not collective: every rank parses the file (load_matrix
    agrees on the outcome)."""
    shape, rows, cols, values, symmetry = _read_matrix_market(path, what)
    if shape[0] != shape[1]:
        raise InputError(f"{what} file {path!r} is {shape[0]} x {shape[1]}, not square")
    held = np.unique(rows[(rows == cols) & (values != 0)]).size if diagonal else shape[0]
    if held < shape[0]:
        raise InputError(f"{what} file {path!r} declares {shape[0]} rows, but only {held} of them have a non-zero "
                         f"diagonal entry: a row without one is a DOF nothing holds (the matrix is singular); "
                         f"check the size line and that every DOF is in the file")
    if symmetry != "general":   # the other triangle, mirrored (negated for skew-symmetric)
        off = rows != cols
        sign = -1.0 if symmetry == "skew-symmetric" else 1.0
        rows, cols, values = (np.concatenate([rows, cols[off]]), np.concatenate([cols, rows[off]]),
                              np.concatenate([values, sign * values[off]]))
    return shape, rows, cols, values


def load_matrix(path: str, comm=None, what: str = "matrix", diagonal: bool = False) -> PETSc.Mat:
    """A distributed AIJ matrix from a Matrix Market or PETSc binary file. Collective. With `diagonal`
    (a stiffness), a Matrix Market file must hold a non-zero diagonal entry in every row: one
    without is a DOF nothing holds (K singular), and a size line far above the entries (a typo,
    8700000 for 87) is refused before the matrix's rows are allocated (37 GB for 870 million)."""
    comm = petsc_comm(comm, "load_matrix")
    # rank 0's reading of the kind for all: a rank that took another branch would wait in other collectives
    kind = comm.tompi4py().bcast(agreed(comm, _readable_format, path, what), root=0)
    if kind == "mtx":
        shape, rows, cols, values = agreed(comm, _matrix_market_triplets, path, what, diagonal)
        start, end = owned_rows(shape[0], comm)
        mine = (rows >= start) & (rows < end)
        return aij_from_owned_triplets(comm, shape[0], rows[mine], cols[mine], values[mine])
    decided_on_rank0(comm, _check_petsc_binary_length, path, what)
    viewer = PETSc.Viewer().createBinary(path, mode="r", comm=comm)
    A = PETSc.Mat().create(comm=comm)
    A.setType(PETSc.Mat.Type.AIJ)
    try:
        with options_as_they_were():
            A.load(viewer)
    except PETSc.Error:
        A.destroy()
        if _begins_with(path, MAT_CLASSID):
            raise InputError(f"{what} file {path!r} begins as a PETSc binary matrix but cannot be read: it is "
                             f"damaged, or was written by a PETSc with other integer or scalar sizes "
                             f"(this one: {np.dtype(PETSc.IntType).itemsize * 8}-bit indices, real "
                             f"{np.dtype(PETSc.ScalarType).itemsize * 8}-bit); write it again") from None
        raise InputError(f"{what} file {path!r} is not a PETSc binary matrix, nor Matrix Market (it does not begin "
                         f"with %%MatrixMarket): a matrix is read in one of those two formats (not .npy or text "
                         f"tables)") from None
    finally:
        viewer.destroy()
    m, n = A.getSize()
    if m != n:
        A.destroy()
        raise InputError(f"{what} file {path!r} is {m} x {n}, not square")
    return A


@contextlib.contextmanager
def options_as_they_were():
    """The PETSc options database as it was before the block, whatever the block added or changed.
    Loading a PETSc binary file reads the `.info` file beside it into the database (`petsc4py`'s
    ASCII writer adds one with `-matload_block_size 1`); the options are part of every run, cache
    and sweep identity, so a second run in one process (a study script) asked another question than
    the first, and an output or checkpoint it made was not recognised by a fresh process (red team).
    The load has read them by then. Not collective (every rank loads)."""
    options = PETSc.Options()
    before = options.getAll()
    try:
        yield
    finally:
        after = options.getAll()
        for name, value in after.items():
            if name not in before:
                options.delValue(name)
            elif before[name] != value:
                options.setValue(name, before[name])


def load_vector(path: str, template: PETSc.Vec, what: str = "vector", owned: bool = False) -> PETSc.Vec:
    """A Vec laid out like `template` from .npy, .txt, .mtx (array or coordinate) or PETSc binary.
    Collective. With owned, the template is destroyed (also when loading fails)."""
    try:
        return _load_vector(path, template, what)
    finally:
        if owned:
            template.destroy()


def _vector_values(path: str, what: str, kind: str, n: int) -> np.ndarray:
    """The n finite real values of a .npy, text or Matrix Market vector file, or an InputError. Not
    collective (every rank reads the file; _load_vector agrees on the outcome)."""
    try:
        if kind == "npy":
            values = np.load(path, allow_pickle=False)
        elif kind == "txt":
            values = np.loadtxt(path, ndmin=1)
        else:
            values = _read_matrix_market_vector(path, what)
    except (ValueError, OSError, EOFError) as e:
        raise InputError(f"{what} file {path!r} is malformed: {e}") from None
    values = np.asarray(values)
    if not np.issubdtype(values.dtype, np.number) or np.iscomplexobj(values):
        raise InputError(f"{what} file {path!r} must hold real numbers, got {values.dtype}")
    values = values.astype(float).ravel()
    if not np.all(np.isfinite(values)):
        raise InputError(f"{what} file {path!r} has NaN or Inf entries")
    if values.size != n:
        raise InputError(f"{what} file {path!r} has {values.size} entries; the matrices have {n} rows")
    return values


def _load_vector(path: str, template: PETSc.Vec, what: str) -> PETSc.Vec:
    comm = template.getComm()
    n = template.getSize()
    kind = comm.tompi4py().bcast(agreed(comm, _readable_format, path, what), root=0)
    if kind != "petsc":
        values = agreed(comm, _vector_values, path, what, kind, n)
        vec = template.duplicate()
        start, end = vec.getOwnershipRange()
        vec.array[:] = values[start:end]
        return vec
    decided_on_rank0(template.getComm(), _check_petsc_binary_length, path, what)
    viewer = PETSc.Viewer().createBinary(path, mode="r", comm=template.getComm())
    try:
        with options_as_they_were():
            loaded = PETSc.Vec().load(viewer)
    except PETSc.Error:
        raise InputError(f"{what} file {path!r} is not a PETSc binary vector") from None
    finally:
        viewer.destroy()
    try:
        if loaded.getSize() != n:
            raise InputError(f"{what} file {path!r} has {loaded.getSize()} entries; the matrices have {n} rows")
        _check_finite(what, path, loaded)
        # Reload into the matrices' layout (a loaded Vec takes PETSc's default split, which may differ).
        # (PETSc refuses a scatter between two parallel layouts with default indices: each rank names
        # the global rows it owns in the matrices' layout.)
        vec = template.duplicate()
        start, end = vec.getOwnershipRange()
        rows = PETSc.IS().createStride(end - start, first=start, step=1, comm=vec.getComm())
        scatter = PETSc.Scatter().create(loaded, rows, vec, rows)
        scatter.scatter(loaded, vec, PETSc.InsertMode.INSERT, PETSc.ScatterMode.FORWARD)
        scatter.destroy()
        rows.destroy()
        return vec
    finally:
        loaded.destroy()


def _read_matrix_market_vector(path: str, what: str) -> np.ndarray:
    with open(path, encoding="ascii", errors="replace") as f:
        header = f.readline().lower().split()
    if len(header) >= 3 and header[2] == "array":
        try:
            with open(path, encoding="ascii") as f:
                lines = [ln for ln in f if ln.strip() and not ln.startswith("%")]
            rows, cols = (int(v) for v in lines[0].split())
            _check_index_range(path, what, rows, 0)
            values = np.array([float(v) for v in lines[1:]])
        except (IndexError, ValueError, UnicodeDecodeError) as e:
            raise InputError(f"{what} file {path!r} is malformed ({type(e).__name__})") from None
        if cols != 1:
            raise InputError(f"{what} file {path!r} is a {rows} x {cols} array, not a vector")
        return values
    shape, rows, cols, values, _ = _read_matrix_market(path, what)
    if shape[1] != 1:
        raise InputError(f"{what} file {path!r} is {shape[0]} x {shape[1]}, not a vector")
    out = np.zeros(shape[0])
    np.add.at(out, rows, values)
    return out


def asymmetry(A: PETSc.Mat, skew: bool = False) -> float:
    """||A - A^T||_F / ||A||_F (with `skew`: ||A + A^T||_F / ||A||_F). Collective."""
    At = A.transpose(PETSc.Mat())
    At.axpy(1.0 if skew else -1.0, A, structure=PETSc.Mat.Structure.DIFFERENT_NONZERO_PATTERN)
    norm = A.norm(PETSc.NormType.FROBENIUS)
    value = At.norm(PETSc.NormType.FROBENIUS) / norm if norm > 0 else 0.0
    At.destroy()
    return value


def one_triangle(A: PETSc.Mat) -> Optional[str]:
    """"lower" or "upper" when every non-zero off-diagonal entry of A lies in that triangle (and there
    is one), else None. Collective."""
    from mpi4py import MPI

    lo, hi = A.getOwnershipRange()
    indptr, cols, values = A.getValuesCSR()
    rows = np.repeat(np.arange(lo, hi), np.diff(indptr))
    stored = values != 0
    below = int(np.count_nonzero(stored & (cols < rows)))
    above = int(np.count_nonzero(stored & (cols > rows)))
    below, above = A.getComm().tompi4py().allreduce(np.array([below, above]), op=MPI.SUM)
    return "lower" if below and not above else "upper" if above and not below else None


def decoupled_dofs(K: PETSc.Mat, M: PETSc.Mat) -> tuple:
    """(how many DOFs K and M couple to no other DOF, the first few of them with their sqrt(k_ii /
    m_ii) in rad/s (inf where m_ii = 0)), counted only when other DOFs are coupled (a diagonal model
    is all decoupled, and says nothing). Such a DOF in a coupled model is an oscillator of its own,
    not part of the structure: the mark of a boundary condition kept in the matrices as a zeroed row
    and column with a diagonal (1 in K and M: a spurious mode at 1 rad/s). Red team (new user): a
    frame exported so had its 6 reference modes all at 0.159 Hz, and the run failed on a DBF's
    stiffness, naming neither. Collective (0 and () when K and M are not laid out alike)."""
    from mpi4py import MPI

    comm = K.getComm().tompi4py()
    if not comm.allreduce(int(K.getOwnershipRange() == M.getOwnershipRange()), op=MPI.MIN):
        return 0, ()
    lo, hi = K.getOwnershipRange()
    coupled = np.zeros(hi - lo, dtype=bool)
    diagonal = {}
    for name, A in (("K", K), ("M", M)):
        indptr, cols, values = A.getValuesCSR()
        rows = np.repeat(np.arange(lo, hi), np.diff(indptr))
        off = (cols != rows) & (values != 0)
        coupled[np.unique(rows[off]) - lo] = True
        d = np.zeros(hi - lo)
        on = (cols == rows)
        d[rows[on] - lo] = values[on]
        diagonal[name] = d
    lonely = np.flatnonzero(~coupled)
    counts = comm.allreduce(np.array([lonely.size, int(coupled.sum())]))
    if not counts[0] or not counts[1]:
        return 0, ()
    with np.errstate(divide="ignore", invalid="ignore"):
        omega = np.sqrt(np.abs(diagonal["K"][lonely]) / diagonal["M"][lonely])
    first = [(int(i) + lo, float(w)) for i, w in zip(lonely[:6], omega[:6])]
    return int(counts[0]), tuple(sorted(sum(comm.allgather(first), []))[:6])


def _not_symmetric(name: str, path: str, A: PETSc.Mat, skew: bool, value: float, letter: str = "A") -> InputError:
    """The error for a matrix that is not (skew-)symmetric, naming the likeliest cause when it holds one
    triangle only: a symmetric matrix stored as one triangle (as FE codes do) and written with a
    Matrix Market "general" header or as a full PETSc matrix. Collective."""
    what = "skew-symmetric" if skew else "symmetric"
    norm = f"||{letter} + {letter}^T||" if skew else f"||{letter} - {letter}^T||"
    message = f"{name} matrix {path!r} is not {what} ({norm} / ||{letter}|| = {value:.3g})"
    triangle = one_triangle(A)
    if triangle:
        message += f": it holds only its {triangle} triangle, "
        if _format(path) == "mtx":   # as the file was read (K.MTX, K.mm)
            message += (f"under a \"general\" header, which means every entry is listed; write the header as "
                        f"\"%%MatrixMarket matrix coordinate real {what}\" (one triangle stored, the other implied) "
                        f"or write both triangles")
        else:
            message += "the way symmetric storage keeps it; write both triangles"
    return InputError(message)


def mass_outside_stiffness(K: PETSc.Mat, M: PETSc.Mat) -> int:
    """How many non-zero entries of M lie outside K's stored pattern (0 for K and M of one FE mesh and
    DOF numbering: an element's mass couples no DOFs its stiffness does not). Red team: a K and an M
    of the same size from two different meshes ran with no word, the first mode 8 % off. A writer
    that drops K's zero entries could count a few: the caller warns, it does not refuse. Collective
    (0 when the two are not laid out alike)."""
    from mpi4py import MPI

    same = int(K.getOwnershipRange() == M.getOwnershipRange())
    comm = K.getComm().tompi4py()
    if not comm.allreduce(same, op=MPI.MIN):
        return 0
    lo = K.getOwnershipRange()[0]
    n = K.getSize()[1]
    k_ptr, k_cols, _ = K.getValuesCSR()
    m_ptr, m_cols, m_vals = M.getValuesCSR()
    k_keys = np.repeat(np.arange(k_ptr.size - 1, dtype=np.int64) + lo, np.diff(k_ptr)) * n + k_cols
    m_keys = np.repeat(np.arange(m_ptr.size - 1, dtype=np.int64) + lo, np.diff(m_ptr)) * n + m_cols
    outside = int(np.count_nonzero(~np.isin(m_keys[m_vals != 0], k_keys)))
    return comm.allreduce(outside)


def _semidefinite_violation(A: PETSc.Mat, tol: float):
    """The first visible sign that the symmetric A is not positive semi-definite, on every rank:
    ("diagonal", row, value) for a negative diagonal entry, ("minor", i, j, a_ij, a_ii, a_jj) for
    an entry with a_ij^2 > a_ii a_jj (a 2 x 2 principal minor below 0, so A has a negative
    eigenvalue), `tol` the relative excess allowed for rounding; None if neither. Necessary
    conditions, checked in O(nnz). Collective."""
    diagonal = A.getDiagonal()
    try:
        lowest = diagonal.min()
        scale = diagonal.norm(PETSc.NormType.NORM_INFINITY)
        if lowest[1] < -1e-12 * scale:
            return ("diagonal", int(lowest[0]), float(lowest[1]))
        lo, hi = A.getOwnershipRange()
        indptr, cols, values = A.getValuesCSR()
        rows = np.repeat(np.arange(lo, hi), np.diff(indptr))
        needed = np.unique(cols).astype(PETSc.IntType)
        index = PETSc.IS().createGeneral(needed, comm=PETSc.COMM_SELF)
        local = PETSc.Vec().createSeq(needed.size, comm=PETSc.COMM_SELF)
        scatter = PETSc.Scatter().create(diagonal, index, local, None)
        scatter.scatter(diagonal, local, PETSc.InsertMode.INSERT, PETSc.ScatterMode.FORWARD)
        d_col = local.getArray(readonly=True)[np.searchsorted(needed, cols)]
        d_row = diagonal.getArray(readonly=True)[rows - lo]
        scatter.destroy(), index.destroy(), local.destroy()
        excess = values**2 - np.maximum(d_row, 0.0) * np.maximum(d_col, 0.0)
        bad = np.flatnonzero(excess > tol * np.maximum(values**2, 1e-300))
        first = (int(rows[bad[0]]), int(cols[bad[0]]), float(values[bad[0]]),
                 float(d_row[bad[0]]), float(d_col[bad[0]])) if bad.size else None
        found = [f for f in A.getComm().tompi4py().allgather(first) if f is not None]
    finally:
        diagonal.destroy()
    return ("minor", *found[0]) if found else None


def _check_dissipative(C: PETSc.Mat, path: str) -> None:
    """An InputError for a damping matrix that is visibly not positive semi-definite (a negative
    diagonal entry, or a 2 x 2 principal minor below 0: _semidefinite_violation), so that C has a
    negative eigenvalue and the damping feeds energy in. Collective."""
    found = _semidefinite_violation(C, 1e-10)
    if found and found[0] == "diagonal":
        raise InputError(f"damping matrix {path!r} has a negative diagonal entry ({found[2]:.3g} in row "
                         f"{found[1]}): damping must dissipate (C positive semi-definite)")
    if found:
        _, i, j, c, ci, cj = found
        raise InputError(f"damping matrix {path!r} has |C[{i}, {j}]| = {abs(c):.3g} above sqrt(C[{i}, {i}] "
                         f"C[{j}, {j}]) = {np.sqrt(max(ci, 0.0) * max(cj, 0.0)):.3g}: C is indefinite and would feed "
                         f"energy in (damping must dissipate: C positive semi-definite)")


# The relative excess a_ij^2 / (a_ii a_jj) - 1 a mass matrix may show for rounding: a point mass on
# an offset (a rank-one 2 x 2 block, a_ij^2 = a_ii a_jj exactly) written with 6 significant digits
# can exceed 1 by a few 1e-6; an indefinite M from a sign error or a corrupt file exceeds it by far.
MASS_MINOR_TOL = 1e-4


def _check_mass(M: PETSc.Mat, path: str) -> None:
    """An InputError for a mass matrix that is visibly not positive semi-definite (a negative diagonal
    entry or 2 x 2 principal minor: _semidefinite_violation). Red team (new user): an M with one
    negated diagonal entry ran the reduced model with no word (its negative-mass eigenvalue, far from
    0, is not among the lowest modes the eigensolver finds) and the full-order model grew without
    bound to "the state is not finite". Zero rows (massless DOFs, a lumped M without rotary inertia)
    pass. Collective."""
    found = _semidefinite_violation(M, MASS_MINOR_TOL)
    if found and found[0] == "diagonal":
        raise InputError(f"mass matrix {path!r} has a negative diagonal entry ({found[2]:.3g} in row {found[1]}): "
                         f"a mass matrix is positive semi-definite (kinetic energy >= 0); check the file and how "
                         f"it was exported")
    if found:
        _, i, j, m, mi, mj = found
        raise InputError(f"mass matrix {path!r} has |M[{i}, {j}]| = {abs(m):.3g} above sqrt(M[{i}, {i}] "
                         f"M[{j}, {j}]) = {np.sqrt(max(mi, 0.0) * max(mj, 0.0)):.3g}: M is indefinite (a negative "
                         f"kinetic energy); a mass matrix is positive semi-definite: check the file and how it was "
                         f"exported")


@dataclass(frozen=True)
class MatrixFiles:
    """A structure given as matrix files over its free DOFs (paths as the files system sees them).

    stiffness, mass   K and M (required)
    damping           C (optional)
    gyroscopic        G (optional), skew-symmetric: M u'' + (C + G) u' + K u = f (axial transport)
    influence         r over the free DOFs, for base excitation
    base_mass_load    M_(free, all) r_all including the coupling to the prescribed support DOFs; when
                      not given, M r is used, which neglects that coupling (docs/design.md)
    nodes, dofs       optional node map: the nodes' coordinates (a text file, one node a row, 1 to 3
                      columns, m) and for each free DOF its node and direction (a text file, one DOF a
                      row: node index from 0, then x, y, z, rx, ry or rz); outputs and plots then show
                      displacement vectors at the nodes
    cells             optional, with the node map: the mesh's cells for ParaView (load_cells), so that
                      its XDMF files show the solid instead of points. Only the display: no number of a
                      result depends on it, and the basis cache and checkpoints ignore it
    cell_type         the cells' XDMF type (xdmf.XDMF_TYPES, not a file) when their node count is not
                      enough: "Quadrilateral" for 4 nodes a row (else tetrahedra) ...; default by count
    """

    stiffness: str
    mass: str
    damping: Optional[str] = None
    influence: Optional[str] = None
    base_mass_load: Optional[str] = None
    nodes: Optional[str] = None
    dofs: Optional[str] = None
    gyroscopic: Optional[str] = None
    cells: Optional[str] = None
    cell_type: Optional[str] = None

    def __post_init__(self):
        """Each file a path (str or os.PathLike, kept as str), the optional ones None. Red team:
        MatrixFiles(None, None) and MatrixFiles(1, 2) were taken, and FullOrderModel.build failed in
        os.stat with a bare TypeError."""
        for name in ("stiffness", "mass", "damping", "influence", "base_mass_load", "nodes", "dofs", "gyroscopic",
                     "cells"):
            value = getattr(self, name)
            if value is None and name not in ("stiffness", "mass"):
                continue
            path = os.fspath(value) if isinstance(value, (str, os.PathLike)) else None
            if not isinstance(path, str) or not path:
                raise InputError(f"MatrixFiles {name}: give the path of a file (a str), got {value!r}")
            object.__setattr__(self, name, path)
        from .xdmf import XDMF_TYPES

        if self.cell_type is not None and self.cell_type not in XDMF_TYPES:
            raise InputError(f"cell_type {self.cell_type!r} is no XDMF cell type dbf-hpc writes; give one of "
                             f"{', '.join(XDMF_TYPES)} (or none: the node count decides)")
        if self.cell_type is not None and not self.cells:
            raise InputError(f"cell_type {self.cell_type!r} names the type of the cells of [structure] cells: "
                             f"give that file as well")

    def fingerprint(self, comm) -> dict:
        """What identifies the operators for the basis cache: the bytes of K and M (and G). Collective."""
        keys = ("stiffness", "mass", "gyroscopic") if self.gyroscopic else ("stiffness", "mass")
        return {key: file_digest(getattr(self, key), comm, key) for key in keys}


COMPONENTS = ("x", "y", "z", "rx", "ry", "rz")


def load_node_map(nodes: str, dofs: str, n: int) -> tuple:
    """(coordinates (nodes x 3), node of each DOF (n,), direction of each DOF (n,), 0..5 as
    COMPONENTS) from the two text files of MatrixFiles. Not collective (load_operators calls it on
    rank 0 and broadcasts)."""
    for path, what in ((nodes, "nodes"), (dofs, "dofs")):
        _readable(path, what)
    # new-user pass: a parse error read "node map: could not convert string 'x' to float64 at row 0,
    # column 2." (the two files swapped), naming neither file nor what a row holds
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            xyz = np.loadtxt(nodes, ndmin=2, dtype=float)
        except ValueError as e:
            raise InputError(f"nodes file {nodes!r}: {str(e).rstrip('.')}; it holds one node a row, 1 to 3 "
                             f"coordinates (m)") from None
        try:
            table = np.loadtxt(dofs, ndmin=2, dtype=str)
        except ValueError as e:
            raise InputError(f"dofs file {dofs!r}: {str(e).rstrip('.')}; it holds one DOF a row: its node "
                             f"index from 0, then x, y, z, rx, ry or rz") from None
    if not 1 <= xyz.shape[1] <= 3 or not np.all(np.isfinite(xyz)):
        numbered = numbered_nodes(xyz) if xyz.shape[1] == 4 and np.all(np.isfinite(xyz)) else ""
        hint = (f"; its first column is {numbered}, as node numbers are: remove it (a node's row, from 0, is its "
                f"number)" if numbered else "")
        raise InputError(f"nodes file {nodes!r} must hold 1 to 3 finite coordinates a row (m){hint}")
    if table.shape != (n, 2):
        raise InputError(f"dofs file {dofs!r} must have one row 'node direction' for each of the {n} DOFs, "
                         f"got {table.shape[0]} rows of {table.shape[1] if table.ndim == 2 else 0}")
    try:
        node = table[:, 0].astype(np.int64)
    except ValueError:
        raise InputError(f"dofs file {dofs!r}: the first column must be node indices (from 0)") from None
    names = np.char.lower(table[:, 1])
    bad = [d for d in set(names) if d not in COMPONENTS]
    if bad:
        raise InputError(f"dofs file {dofs!r}: directions must be one of {', '.join(COMPONENTS)} (got {bad[0]!r})")
    outside = np.flatnonzero((node < 0) | (node >= xyz.shape[0]))
    if outside.size:   # new-user pass: the nodes file went unnamed, and a count from 1 unsaid
        i = int(outside[0])
        from_one = node.min() == 1 and node.max() == xyz.shape[0]
        raise InputError(f"dofs file {dofs!r}: DOF {i} (row {i + 1}) names node {node[i]}, but the nodes file "
                         f"{nodes!r} has {xyz.shape[0]} nodes, 0 to {xyz.shape[0] - 1}" +
                         ("; node numbers count from 0 (if these count from 1, subtract 1; if not, the two files "
                          "describe different meshes)" if from_one else ": the two files must describe one mesh"))
    component = np.array([COMPONENTS.index(d) for d in names], dtype=np.int64)
    keys, first = np.unique(node * len(COMPONENTS) + component, return_index=True)
    if keys.size != n:     # one DOF's value would be shown for another's (red team)
        twice = np.setdiff1d(np.arange(n), first)[0]
        raise InputError(f"dofs file {dofs!r}: DOF {twice} (row {twice + 1}) repeats node {node[twice]} "
                         f"{names[twice]}, which an earlier row already has; each node and direction is one DOF")
    coordinates = np.zeros((xyz.shape[0], 3))
    coordinates[:, :xyz.shape[1]] = xyz
    return coordinates, node, component


def numbered_nodes(coordinates: np.ndarray) -> str:
    """"0, 1, ..., N-1" or "1, 2, ..., N" when the nodes' x are exactly the row numbers (from 0 or 1)
    and another coordinate is not all 0: a nodes file written with a node-number column first (the
    "id x y" of many FE exports) read as x = id, y = x, z = y; else "". A chain of nodes 1 m apart
    along x alone is not flagged. Not collective. Red team (new user): such a file was taken with no
    word and every displacement was drawn at another place."""
    n = coordinates.shape[0]
    x, rest = coordinates[:, 0], coordinates[:, 1:]
    if n < 3 or not np.any(rest != 0):
        return ""
    for first in (0, 1):
        if np.array_equal(x, np.arange(first, first + n, dtype=float)):
            return f"{first}, {first + 1}, ..., {first + n - 1}"
    return ""


def load_cells(path: str, coordinates: np.ndarray, cell_type: Optional[str] = None) -> tuple:
    """(cells (E x k, int64), their XDMF type, sha256 of the file's bytes) from a cells file: one
    cell a row, the indices (from 0) of its k nodes in the nodes file, in XDMF's (VTK's) node order;
    .npy (an integer array E x k) or text (whitespace-separated). `cell_type` (xdmf.XDMF_TYPES), or
    else k, gives the XDMF topology (xdmf.CELL_TYPES: 4 a tetrahedron, 8 a hexahedron ...). Refused:
    another k, rows of different lengths, an index that is not an integer or not a node, a node twice
    in a cell, a flat tetrahedron, a hexahedron whose corners are not in XDMF's order (its corner
    Jacobians change sign: the lexicographic order of many generators draws a twisted brick), a
    quadrilateral whose corners do not go round it. Not collective (load_operators calls it on rank 0
    and broadcasts what it finds)."""
    from .xdmf import CELL_TYPES, XDMF_TYPES

    _readable(path, "cells")
    with open(path, "rb") as f:
        data = f.read()
    try:
        if path.endswith(".npy"):
            table = np.load(io.BytesIO(data), allow_pickle=False)
        else:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                table = np.loadtxt(io.StringIO(data.decode("ascii")), ndmin=2, dtype=float)
    except (ValueError, OSError, EOFError, UnicodeDecodeError) as e:
        why = str(e).splitlines()[0].split(";")[0] if str(e) else type(e).__name__   # (not numpy's `usecols` advice)
        raise InputError(f"cells file {path!r} is malformed ({why}): one cell a row, every row the same number of "
                         f"node indices") from None
    table = np.asarray(table)
    if table.ndim != 2 or table.shape[0] == 0:
        raise InputError(f"cells file {path!r} holds no table of cells (one cell a row), got shape {table.shape}")
    if not (np.issubdtype(table.dtype, np.integer) or np.issubdtype(table.dtype, np.floating)) or \
            not np.all(np.isfinite(table)) or np.any(table != np.floor(table)):
        raise InputError(f"cells file {path!r}: node indices must be integers (from 0)")
    k = table.shape[1]
    if cell_type is not None and XDMF_TYPES[cell_type] != k:
        raise InputError(f"cells file {path!r} has {k} nodes a row, but a {cell_type} (cell_type) has "
                         f"{XDMF_TYPES[cell_type]}")
    if k not in CELL_TYPES:
        raise InputError(f"cells file {path!r}: rows of {k} nodes are no cell type dbf-hpc writes; give " +
                         ", ".join(f"{n} ({name})" for n, name in CELL_TYPES.items()) + " nodes a row")
    n = coordinates.shape[0]
    outside = np.flatnonzero((table < 0).any(axis=1) | (table >= n).any(axis=1))
    if outside.size:
        i = int(outside[0])
        bad = int(table[i][(table[i] < 0) | (table[i] >= n)][0])
        raise InputError(f"cells file {path!r}: cell {i} (row {i + 1}) names node {bad}; the nodes file has {n} "
                         f"nodes (0 to {n - 1})")
    cells = table.astype(np.int64)
    ordered = np.sort(cells, axis=1)
    twice = np.flatnonzero((ordered[:, 1:] == ordered[:, :-1]).any(axis=1))
    if twice.size:
        i = int(twice[0])
        raise InputError(f"cells file {path!r}: cell {i} (row {i + 1}) lists node "
                         f"{int(ordered[i][1:][ordered[i][1:] == ordered[i][:-1]][0])} twice")
    kind = cell_type or CELL_TYPES[k]
    if kind.startswith(("Tetrahedron", "Hexahedron")):
        _check_solid_cells(path, kind, cells, coordinates, cell_type is None)
    elif kind.startswith("Quadrilateral"):
        _check_quadrilaterals(path, cells, coordinates)
    return cells, kind, hashlib.sha256(data).hexdigest()


# XDMF's (VTK's) hexahedron: corners 0-3 around the bottom face, 4-7 above them; each corner's three
# neighbours, in the order that makes the edge triple's determinant positive for a right-handed brick
HEX_NEIGHBOURS = np.array([(1, 3, 4), (2, 0, 5), (3, 1, 6), (0, 2, 7), (7, 5, 0), (4, 6, 1), (5, 7, 2), (6, 4, 3)])


def _check_solid_cells(path: str, kind: str, cells: np.ndarray, coordinates: np.ndarray, by_count: bool) -> None:
    """An InputError for a flat tetrahedron, or a hexahedron whose 8 corner Jacobians are not all of one
    sign (a mirrored cell, all negative, ParaView draws as it is). `by_count`: the type came from the
    node count (a flat cell may be a quadrilateral: cell_type says so)."""
    corners = 4 if kind.startswith("Tetrahedron") else 8
    xyz = coordinates[cells[:, :corners]]                                    # (E, corners, 3)
    scale = np.ptp(xyz, axis=1).max(axis=1) ** 3                             # (E,)
    if corners == 4:
        det = np.linalg.det(xyz[:, 1:] - xyz[:, :1])[:, None]                # (E, 1)
    else:
        edges = xyz[:, HEX_NEIGHBOURS] - xyz[:, :, None, :]                  # (E, 8, 3, 3)
        det = np.linalg.det(edges)                                           # (E, 8)
    tiny = 1e-10 * scale[:, None]
    flat = np.flatnonzero((np.abs(det) <= tiny).any(axis=1))
    if flat.size:
        i = int(flat[0])
        flat_type = {4: "Quadrilateral", 8: "Quadrilateral_8"}.get(cells.shape[1]) if by_count else None
        what = "quadrilaterals" if cells.shape[1] == 4 else "8-node quadrilaterals"
        hint = f"; for {what} give [structure] cell_type = \"{flat_type}\"" if flat_type else ""
        raise InputError(f"cells file {path!r}: {kind.lower()} {i} (row {i + 1}, nodes "
                         f"{' '.join(map(str, cells[i]))}) has no volume: its corners must be apart in 3-D (the "
                         f"nodes file needs z){hint}")
    twisted = np.flatnonzero((det > 0).any(axis=1) & (det < 0).any(axis=1))
    if twisted.size:
        i = int(twisted[0])
        raise InputError(f"cells file {path!r}: hexahedron {i} (row {i + 1}, nodes {' '.join(map(str, cells[i]))}) is "
                         f"not in XDMF's node order (it would be drawn twisted): list the 4 corners around one face, "
                         f"then the 4 opposite them in the same turn")


def _check_quadrilaterals(path: str, cells: np.ndarray, coordinates: np.ndarray) -> None:
    """An InputError for a quadrilateral without area or whose corners do not go round it (the normals
    at its 4 corners disagree: drawn as a bow tie)."""
    xyz = coordinates[cells[:, :4]]                                          # (E, 4, 3)
    normals = np.cross(np.roll(xyz, -1, axis=1) - xyz, np.roll(xyz, 1, axis=1) - xyz)   # (E, 4, 3)
    total = normals.sum(axis=1)                                              # (E, 3)
    agree = np.einsum("ecd,ed->ec", normals, total)                          # (E, 4)
    scale = np.ptp(xyz, axis=1).max(axis=1) ** 2
    bad = np.flatnonzero((agree <= 1e-10 * scale[:, None] ** 2).any(axis=1))
    if bad.size:
        i = int(bad[0])
        raise InputError(f"cells file {path!r}: quadrilateral {i} (row {i + 1}, nodes {' '.join(map(str, cells[i]))}) "
                         f"has no area or its corners do not go round it (it would be drawn as a bow tie): list "
                         f"them in turn")


def file_digest(path: str, comm, what: str = "input") -> str:
    """sha256 of a file's bytes, read on rank 0 only; a file that cannot be read is every rank's
    InputError naming it (`what` file ...). Collective."""
    return decided_on_rank0(comm, _digest, path, what)


def _digest(path: str, what: str) -> str:
    # red team: a scene's missing matrix file (a typo) was "internal error (FileNotFoundError) on rank 0"
    # in `dbf-hpc run`, which hashes the inputs before it loads them
    if not_a_regular_file(path):
        raise InputError(f"{what} file {path!r} {not_a_regular_file(path)}")
    h = hashlib.sha256()
    try:
        with open(path, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
    except OSError as e:
        raise InputError(f"{what} file {path!r} cannot be read: {e.strerror or e}") from None
    return h.hexdigest()


def load_operators(files: MatrixFiles, comm=None) -> Operators:
    """Operators of an external FE model. Collective on comm (default COMM_WORLD).

    Sizes must agree, K, M (and C) must be symmetric and G skew-symmetric, M and C show no sign of being
    indefinite (_check_mass, _check_dissipative); anything else is an InputError, and what was loaded
    before it is freed.
    """
    comm = petsc_comm(comm, "load_operators")
    if files.base_mass_load and not files.influence:
        raise InputError("a base mass load needs the influence vector as well")
    if files.cells and not (files.nodes and files.dofs):
        raise InputError(f"cells file {files.cells!r}: cells are drawn between the nodes of a node map: give "
                         f"[structure] nodes and dofs as well")
    if files.cells:   # before the matrices, which take a while (read in full with the node map)
        decided_on_rank0(comm, _readable, files.cells, "cells")
    ops = Operators(comm=comm, K=load_matrix(files.stiffness, comm, "stiffness", diagonal=True), M=None)
    try:
        ops.M = load_matrix(files.mass, comm, "mass")
        ops.C = load_matrix(files.damping, comm, "damping") if files.damping else None
        ops.G = load_matrix(files.gyroscopic, comm, "gyroscopic") if files.gyroscopic else None
        n = ops.K.getSize()[0]
        for name, A, path in (("mass", ops.M, files.mass), ("damping", ops.C, files.damping),
                              ("gyroscopic", ops.G, files.gyroscopic)):
            if A is not None and A.getSize()[0] != n:
                raise InputError(f"{name} matrix {path!r} is {A.getSize()[0]} x {A.getSize()[0]}; "
                                 f"the stiffness is {n} x {n}")
        for name, A, path in (("stiffness", ops.K, files.stiffness), ("mass", ops.M, files.mass),
                              ("damping", ops.C, files.damping)):
            if A is not None:
                _check_finite(name, path, A)
            skew = asymmetry(A) if A is not None else 0.0
            if skew > SYMMETRY_TOL:
                raise _not_symmetric(name, path, A, False, skew)
        _check_mass(ops.M, files.mass)
        lonely, first = decoupled_dofs(ops.K, ops.M)
        if lonely:
            listed = ", ".join(f"{i} ({w / (2 * np.pi):.4g} Hz)" for i, w in first) + (", ..." if lonely > len(first) else "")
            warn(f"{lonely} DOF(s) of {files.stiffness!r} and {files.mass!r} are coupled to no other DOF: {listed}; each "
                 f"is an oscillator of its own, not part of the structure, with a mode of the model at that frequency "
                 f"(a boundary condition kept as a zeroed row and column with a diagonal?): remove fixed DOFs from "
                 f"K, M and the other files", comm)
        outside = mass_outside_stiffness(ops.K, ops.M)
        if outside:
            warn(f"the mass matrix {files.mass!r} has {outside} non-zero entries where the stiffness "
                 f"{files.stiffness!r} has none: K and M of one mesh and one DOF numbering couple the same "
                 f"DOFs; check that both files come from the same model", comm)
        if ops.C is not None:
            _check_dissipative(ops.C, files.damping)
        if ops.G is not None:
            _check_finite("gyroscopic", files.gyroscopic, ops.G)
            skew = asymmetry(ops.G, skew=True)
            if skew > SYMMETRY_TOL:
                raise _not_symmetric("gyroscopic", files.gyroscopic, ops.G, True, skew, "G")
        if bool(files.nodes) != bool(files.dofs):
            raise InputError("a node map needs both [structure] nodes and dofs")
        if files.nodes:
            # the node map and the cells are read and checked on rank 0, which every rank follows (a
            # rank that could not read them alone would have left the others waiting)
            coordinates, node, component = decided_on_rank0(comm, load_node_map, files.nodes, files.dofs, n)
            numbered = numbered_nodes(coordinates)
            if numbered:
                warn(f"the first column of the nodes file {files.nodes!r} is {numbered}, as node numbers are: a row "
                     f"holds a node's coordinates only (its row, from 0, is its number); if that column numbers the "
                     f"nodes, remove it, or the outputs draw every node elsewhere", comm)
            moves = np.flatnonzero(component < 3)          # translations: what a displacement field shows
            ops.rotations = np.flatnonzero(component >= 3)   # rad, not m: the error estimate scales them apart
            cells, cell_type, digest = (decided_on_rank0(comm, load_cells, files.cells, coordinates, files.cell_type)
                                        if files.cells else (None, "", ""))
            if cells is not None:
                unseen = np.setdiff1d(node[moves], cells.ravel()).size
                if unseen:
                    are = "s with a displacement DOF are" if unseen > 1 else " with a displacement DOF is"
                    warn(f"{unseen} node{are} in no cell of {files.cells!r}: ParaView shows no displacement there "
                         f"(give every element's cell)", comm)
            ops.field = PointValues.at_rows(moves, moves, kind="nodes", node=node[moves], component=component[moves],
                                            coordinates=coordinates, cells=cells, cell_type=cell_type,
                                            cells_sha256=digest)
        if files.influence:
            ops.influence = load_vector(files.influence, ops.K.createVecRight(), "influence vector", owned=True)
            if files.base_mass_load:
                ops.base_mass_load = load_vector(files.base_mass_load, ops.influence, "base mass load")
            else:
                ops.base_mass_load = ops.influence.duplicate()
                ops.M.mult(ops.influence, ops.base_mass_load)
    except Exception:
        ops.destroy()
        raise
    return ops
