"""External operators from files: exact round trips, the same modes as the beam they came from,
and clear errors for files that cannot be operators."""
import os
import re

import shutil

import numpy as np
import pytest
import scipy.io
import scipy.sparse
from mpi4py import MPI
from petsc4py import PETSc

from conftest import assert_all, ends_a_hang, to_numpy, write_binary_vec
from dbf_hpc.errors import DbfError, InputError
from dbf_hpc.matrices import MatrixFiles, file_digest, load_matrix, load_node_map, load_operators
from dbf_hpc.modes import reference_modes
from dbf_hpc.scene import validate
from dbf_hpc.structure import Beam, assemble_beam

TABLE1 = dict(length=1.0, E=117e9, I=0.000878e-12, A=0.29e-6, rho=11800.0)


def to_scipy(A):
    """The whole of a distributed Mat as a scipy CSR matrix, on every rank. Collective."""
    lo, hi = A.getOwnershipRange()
    indptr, indices, values = A.getValuesCSR()
    rows = np.repeat(np.arange(lo, hi), np.diff(indptr))
    comm = MPI.COMM_WORLD if A.getComm().getSize() > 1 else MPI.COMM_SELF
    parts = comm.allgather((rows, indices, values))
    r, c, v = (np.concatenate(p) for p in zip(*parts))
    n = A.getSize()[0]
    return scipy.sparse.csr_matrix((v, (r, c)), shape=(n, n))


@pytest.fixture
def beam_files(shared_tmp_path):
    """The Table 1 beam's K and M written as PETSc binary and as Matrix Market (by scipy, an
    independent writer), and its influence vector as .npy."""
    ops = assemble_beam(Beam(**TABLE1, elements=30), base_end="left")
    K, M = to_scipy(ops.K), to_scipy(ops.M)
    r = to_numpy(ops.influence)
    paths = {name: str(shared_tmp_path / name) for name in ("K.bin", "M.bin", "K.mtx", "M.mtx", "r.npy")}
    for A, name in ((ops.K, "K.bin"), (ops.M, "M.bin")):
        viewer = PETSc.Viewer().createBinary(paths[name], mode="w", comm=ops.comm)
        A.view(viewer)
        viewer.destroy()
    if MPI.COMM_WORLD.rank == 0:
        scipy.io.mmwrite(paths["K.mtx"], K, symmetry="symmetric", precision=17)  # lower triangle
        scipy.io.mmwrite(paths["M.mtx"], M, precision=17)
        np.save(paths["r.npy"], r)
    MPI.COMM_WORLD.Barrier()
    yield ops, K, M, paths
    ops.destroy()


@pytest.mark.parametrize("fmt", ["bin", "mtx"])
def test_loaded_operators_equal_the_written_ones(beam_files, fmt):
    ops, K, M, paths = beam_files
    loaded = load_operators(MatrixFiles(paths[f"K.{fmt}"], paths[f"M.{fmt}"], influence=paths["r.npy"]))
    assert abs(to_scipy(loaded.K) - K).max() <= 1e-12 * abs(K).max()
    assert abs(to_scipy(loaded.M) - M).max() <= 1e-12 * abs(M).max()
    np.testing.assert_allclose(to_numpy(loaded.influence), to_numpy(ops.influence), rtol=0, atol=1e-15)
    loaded.destroy()


@pytest.mark.parallel
@pytest.mark.parametrize("seen,expected", [
    ("K.mtx missing", "does not exist"), ("K.bin missing", "does not exist"),
    ("K.mtx cut short", "declares"), ("r.npy missing", "does not exist")],
    ids=["mtx-missing", "binary-missing", "mtx-cut-short", "npy-missing"])
def test_a_file_that_rank_1s_node_cannot_read_is_every_ranks_one_line_error(beam_files, seen, expected):
    # Red team (collective semantics): every rank reads a Matrix Market matrix and a .npy/.txt vector
    # itself (and checks that a PETSc binary one exists); a file missing or cut short in rank 1's view
    # (a node that does not see the file system as rank 0 does, a file replaced while the ranks read
    # it) was rank 1's InputError alone, while rank 0 went on into the matrix's collective assembly:
    # the job hung. Here rank 1 is given its own path, as its node would see it.

    _, _, _, paths = beam_files
    name, what = seen.split(" ", 1)
    folder = os.path.dirname(paths["K.mtx"])
    mine = dict(paths)
    if MPI.COMM_WORLD.rank == 1:
        if what == "missing":
            mine[name] = os.path.join(folder, "unseen", name)
        else:   # the file as a copy cut short in its last line
            with open(paths[name]) as f:
                text = f.read()
            mine[name] = os.path.join(folder, "cut-" + name)
            with open(mine[name], "w") as f:
                f.write(text[:len(text) // 2].rsplit("\n", 1)[0] + "\n")
    fmt = "bin" if name == "K.bin" else "mtx"
    with ends_a_hang(), pytest.raises(InputError) as refused:
        ops = load_operators(MatrixFiles(mine[f"K.{fmt}"], mine[f"M.{fmt}"], influence=mine["r.npy"]))
        ops.destroy()
    line = str(refused.value)
    assert MPI.COMM_WORLD.allgather(line) == [line] * MPI.COMM_WORLD.size, "the ranks refused with other lines"
    assert expected in line and "\n" not in line, line


def test_an_influence_vector_in_petsc_binary_is_the_written_one(shared_tmp_path, beam_files):
    # Red team: every PETSc binary influence vector was refused with "PETSc error 56 in
    # VecScatterCreate()" (a scatter with default indices on both sides), though the docs offer it.
    ops, _, _, paths = beam_files
    path = str(shared_tmp_path / "r.bin")
    write_binary_vec(ops.influence, path)
    for stiffness, mass in ((paths["K.bin"], paths["M.bin"]), (paths["K.mtx"], paths["M.mtx"])):
        loaded = load_operators(MatrixFiles(stiffness, mass, influence=path))
        np.testing.assert_array_equal(to_numpy(loaded.influence), to_numpy(ops.influence))
        loaded.destroy()


def test_a_petsc_binary_file_cut_short_is_refused_on_every_rank_naming_its_length(shared_tmp_path, beam_files):
    # Red team (new user): K.bin cut short (a copy that ran out of space) was "(rank 0) ... is not a PETSc
    # binary matrix" after 10 s on 2 ranks (MatLoad failed on rank 0, which reads, while rank 1 waited
    # for its rows), and a K.bin that ends inside its header was an internal error. Now every rank
    # raises the same InputError at once (pytest.raises on each rank), for matrices and vectors alike.
    ops, _, _, paths = beam_files
    r_bin = str(shared_tmp_path / "r.bin")
    write_binary_vec(ops.influence, r_bin)
    cut = {name: str(shared_tmp_path / name) for name in ("K_half.bin", "K_header.bin", "r_half.bin")}
    if MPI.COMM_WORLD.rank == 0:
        k_bytes, r_bytes = open(paths["K.bin"], "rb").read(), open(r_bin, "rb").read()
        open(cut["K_half.bin"], "wb").write(k_bytes[:len(k_bytes) // 2])
        open(cut["K_header.bin"], "wb").write(k_bytes[:10])
        open(cut["r_half.bin"], "wb").write(r_bytes[:len(r_bytes) // 2])
    MPI.COMM_WORLD.Barrier()
    n, nz = ops.K.getSize()[0], int(ops.K.getInfo()["nz_used"])     # (summed over the ranks)
    with pytest.raises(InputError, match=rf"^stiffness file '.*K_half.bin' is cut short: \d+ bytes, where its PETSc "
                                         rf"binary header \({n} x {n}, {nz} entries\) needs {16 + 4 * (n + nz) + 8 * nz}"):
        load_operators(MatrixFiles(cut["K_half.bin"], paths["M.bin"]))
    with pytest.raises(InputError, match=r"^stiffness file '.*K_header.bin' is cut short: it ends inside its PETSc"):
        load_operators(MatrixFiles(cut["K_header.bin"], paths["M.bin"]))
    with pytest.raises(InputError, match=rf"^influence vector file '.*r_half.bin' is cut short: \d+ bytes, where its "
                                         rf"PETSc binary header \({n} entries\) needs {8 + 8 * n}"):
        load_operators(MatrixFiles(paths["K.bin"], paths["M.bin"], influence=cut["r_half.bin"]))


def test_loaded_operators_have_the_beams_frequencies(beam_files):
    ops, _, _, paths = beam_files
    loaded = load_operators(MatrixFiles(paths["K.mtx"], paths["M.bin"]))
    a = reference_modes(ops, count=5).omega
    b = reference_modes(loaded, count=5).omega
    assert np.allclose(a, b, rtol=1e-10)
    loaded.destroy()


def test_size_mismatch_is_an_error(shared_tmp_path, beam_files):
    _, _, _, paths = beam_files
    small = str(shared_tmp_path / "small.mtx")
    if MPI.COMM_WORLD.rank == 0:
        scipy.io.mmwrite(small, scipy.sparse.identity(7, format="csr"))
    MPI.COMM_WORLD.Barrier()
    with pytest.raises(InputError, match="mass matrix .* is 7 x 7; the stiffness is"):
        load_operators(MatrixFiles(paths["K.bin"], small))


def test_influence_vector_of_the_wrong_length_is_an_error(shared_tmp_path, beam_files):
    _, _, _, paths = beam_files
    short = str(shared_tmp_path / "short.txt")
    if MPI.COMM_WORLD.rank == 0:
        np.savetxt(short, np.ones(5))
    MPI.COMM_WORLD.Barrier()
    with pytest.raises(InputError, match="influence vector .* has 5 entries"):
        load_operators(MatrixFiles(paths["K.bin"], paths["M.bin"], influence=short))


def test_non_symmetric_stiffness_is_an_error(shared_tmp_path, beam_files):
    _, K, _, paths = beam_files
    bad = str(shared_tmp_path / "Kbad.mtx")
    if MPI.COMM_WORLD.rank == 0:
        skew = K.tolil()
        skew[0, 1] *= 1.01
        scipy.io.mmwrite(bad, skew.tocsr(), precision=17)
    MPI.COMM_WORLD.Barrier()
    with pytest.raises(InputError, match="stiffness matrix .* is not symmetric"):
        load_operators(MatrixFiles(bad, paths["M.bin"]))


def test_one_triangle_of_a_symmetric_matrix_written_as_a_whole_one_is_refused_naming_the_header_to_write(
        shared_tmp_path, beam_files):
    # Red team (new user): K's lower triangle under a "general" header (an FE code keeps one triangle)
    # was refused as "not symmetric (||A - A^T|| / ||A|| = 0.63)", with nothing on the cause or the fix.
    # The same triangle as a whole PETSc binary matrix is named too; G's gets the skew-symmetric header.
    ops, K, _, paths = beam_files
    lower = scipy.sparse.tril(K).tocsr()
    files = {name: str(shared_tmp_path / name) for name in ("Kl.mtx", "Kl.bin", "Gu.mtx")}
    if MPI.COMM_WORLD.rank == 0:
        scipy.io.mmwrite(files["Kl.mtx"], lower, precision=17)    # scipy writes a general header
        scipy.io.mmwrite(files["Gu.mtx"], scipy.sparse.triu(K, 1).tocsr(), precision=17)
        assert "general" in open(files["Kl.mtx"]).readline()
    lo, hi = ops.K.getOwnershipRange()
    indptr, cols, values = ops.K.getValuesCSR()
    rows = np.repeat(np.arange(lo, hi), np.diff(indptr))
    triangle = PETSc.Mat().createAIJ(ops.K.getSizes(), csr=(indptr, cols, np.where(cols > rows, 0.0, values)),
                                     comm=ops.comm)      # the upper triangle zeroed, the pattern kept
    viewer = PETSc.Viewer().createBinary(files["Kl.bin"], mode="w", comm=ops.comm)
    triangle.view(viewer)
    viewer.destroy(), triangle.destroy()
    MPI.COMM_WORLD.Barrier()
    with pytest.raises(InputError, match=r"^stiffness matrix '.*Kl.mtx' is not symmetric \(.*\): it holds only its "
                                         r"lower triangle, under a \"general\" header, .* write the header as "
                                         r"\"%%MatrixMarket matrix coordinate real symmetric\""):
        load_operators(MatrixFiles(files["Kl.mtx"], paths["M.bin"]))
    # the same file under another name is read as Matrix Market (its header), and gets the same advice
    upper_case = str(shared_tmp_path / "KL.MTX")
    if MPI.COMM_WORLD.rank == 0:
        shutil.copy(files["Kl.mtx"], upper_case)
    MPI.COMM_WORLD.Barrier()
    with pytest.raises(InputError, match=r"^stiffness matrix '.*KL.MTX' is not symmetric \(.*\): it holds only its "
                                         r"lower triangle, under a \"general\" header"):
        load_operators(MatrixFiles(upper_case, paths["M.bin"]))
    with pytest.raises(InputError, match=r"^stiffness matrix '.*Kl.bin' is not symmetric \(.*\): it holds only its "
                                         r"lower triangle, .* write both triangles$"):
        load_operators(MatrixFiles(files["Kl.bin"], paths["M.bin"]))
    with pytest.raises(InputError, match=r"^gyroscopic matrix '.*Gu.mtx' is not skew-symmetric \(\|\|G \+ G\^T\|\| "
                                         r"/ \|\|G\|\| = .*\): it holds only its upper triangle, .* "
                                         r"\"%%MatrixMarket matrix coordinate real skew-symmetric\""):
        load_operators(MatrixFiles(paths["K.bin"], paths["M.bin"], gyroscopic=files["Gu.mtx"]))


def test_a_stiffness_whose_size_line_exceeds_its_diagonal_is_refused_before_its_rows_are_allocated(shared_tmp_path,
                                                                                                  beam_files):
    # Red team (new user): a size line typed 8700000 for 87 allocated 8.7 million rows (0.37 GB; 870
    # million would take 37 GB) before "mass matrix is 87 x 87; the stiffness is 8700000 x 8700000".
    # A K row without a diagonal entry is a DOF nothing holds. M may have empty rows (massless DOFs).
    _, K, M, paths = beam_files
    n = K.shape[0]
    typo, massless = str(shared_tmp_path / "K_typo.mtx"), str(shared_tmp_path / "M_massless.mtx")
    if MPI.COMM_WORLD.rank == 0:
        lines = open(paths["K.mtx"]).read().splitlines(keepends=True)
        size = next(i for i, line in enumerate(lines) if not line.startswith("%"))
        lines[size] = lines[size].replace(f"{n} {n} ", f"{n}00000 {n}00000 ", 1)
        open(typo, "w").writelines(lines)
        lumped = M.tolil()
        lumped[3, :] = 0.0
        lumped[:, 3] = 0.0
        scipy.io.mmwrite(massless, lumped.tocsr(), precision=17)
    MPI.COMM_WORLD.Barrier()
    with pytest.raises(InputError, match=rf"^stiffness file '.*K_typo.mtx' declares {n}00000 rows, but only {n} of them "
                                         rf"have a non-zero diagonal entry: .* check the size line"):
        load_operators(MatrixFiles(typo, paths["M.bin"]))
    load_operators(MatrixFiles(paths["K.mtx"], massless)).destroy()


@pytest.mark.parametrize("content,message", [
    ("", "not a Matrix Market matrix"),
    ("%%MatrixMarket matrix array real general\n2 2\n1\n0\n0\n1\n", "only real coordinate"),
    ("%%MatrixMarket matrix coordinate real general\n2 2 3\n1 1 1.0\n", "declares 3 entries but holds 1"),
    ("%%MatrixMarket matrix coordinate real general\n2 3 1\n1 1 1.0\n", "not square"),
    # red team: both triangles under a symmetric header were mirrored again, doubling the off-diagonal
    ("%%MatrixMarket matrix coordinate real symmetric\n2 2 4\n1 1 2.0\n2 1 -1.0\n1 2 -1.0\n2 2 2.0\n",
     "symmetric header but entries on both sides of the diagonal"),
    # ... and a repeated entry was summed (readers disagree on both)
    ("%%MatrixMarket matrix coordinate real general\n2 2 3\n1 1 2.0\n1 1 2.0\n2 2 1.0\n",
     "lists 1 entry twice \\(e.g. row 1, column 1\\)"),
    ("%%MatrixMarket matrix coordinate real skew-symmetric\n2 2 2\n1 1 1.0\n2 1 1.0\n", "non-zero diagonal")])
def test_malformed_matrix_market_is_an_error(shared_tmp_path, content, message):
    path = shared_tmp_path / "bad.mtx"
    if MPI.COMM_WORLD.rank == 0:
        path.write_text(content)
    MPI.COMM_WORLD.Barrier()
    with pytest.raises(InputError, match=message):
        load_matrix(str(path))


def test_a_dense_matrix_market_array_is_refused_with_the_coordinate_writing_that_loads(shared_tmp_path):
    # Red team: scipy.io.mmwrite of a dense K writes "matrix array real"; the refusal named no way out.
    # The advice it gives, mmwrite of a scipy.sparse matrix, writes a file that loads with the same entries.
    K = np.array([[2.0, -1.0, 0.0], [-1.0, 2.0, -1.0], [0.0, -1.0, 2.0]])
    dense, sparse = shared_tmp_path / "K_dense.mtx", shared_tmp_path / "K_sparse.mtx"
    if MPI.COMM_WORLD.rank == 0:
        scipy.io.mmwrite(str(dense), K)
        scipy.io.mmwrite(str(sparse), scipy.sparse.coo_matrix(K))
    MPI.COMM_WORLD.Barrier()
    with pytest.raises(InputError, match=r"^stiffness file '.*K_dense.mtx' is a dense Matrix Market array .*: only "
                                         r"real coordinate Matrix Market is read for a matrix; write it with "
                                         r"scipy.io.mmwrite\(path, scipy.sparse.coo_matrix\(A\)\) .*or as PETSc "
                                         r"binary$"):
        load_matrix(str(dense), what="stiffness")
    A = load_matrix(str(sparse), what="stiffness")
    try:
        start, end = A.getOwnershipRange()
        rows = MPI.COMM_WORLD.allgather(A.getValues(range(start, end), range(3)))
        assert_all(np.array_equal(np.vstack(rows), K))
    finally:
        A.destroy()


def test_blank_lines_before_the_size_line_of_a_matrix_market_file_are_allowed(shared_tmp_path):
    # Red team: a blank line after the comments (the format allows blank lines; scipy and NIST's
    # mmio read them) was "malformed: not enough values to unpack".
    path = shared_tmp_path / "K.mtx"
    if MPI.COMM_WORLD.rank == 0:
        path.write_text("%%MatrixMarket matrix coordinate real symmetric\n% from another code\n\n  \n"
                        "2 2 3\n1 1 2.0\n2 1 -1.0\n\n2 2 3.0\n")
    MPI.COMM_WORLD.Barrier()
    mat = load_matrix(str(path))
    np.testing.assert_array_equal(to_scipy(mat).toarray(), [[2.0, -1.0], [-1.0, 3.0]])
    np.testing.assert_array_equal(scipy.io.mmread(str(path)).toarray(), [[2.0, -1.0], [-1.0, 3.0]])
    mat.destroy()


def test_one_triangle_of_a_symmetric_or_skew_symmetric_file_is_the_whole_matrix(shared_tmp_path):
    G = np.array([[0.0, 1.5, 0.0], [-1.5, 0.0, -2.0], [0.0, 2.0, 0.0]])
    K = np.array([[4.0, -1.0, 0.0], [-1.0, 4.0, -1.0], [0.0, -1.0, 4.0]])
    files = {"G.mtx": ("skew-symmetric", G, np.tril), "K.mtx": ("symmetric", K, np.tril),
             "Ku.mtx": ("symmetric", K, np.triu)}
    if MPI.COMM_WORLD.rank == 0:
        for name, (symmetry, A, triangle) in files.items():
            T = scipy.sparse.coo_matrix(triangle(A))
            lines = [f"%%MatrixMarket matrix coordinate real {symmetry}", f"3 3 {T.nnz}"]
            lines += [f"{i + 1} {j + 1} {v!r}" for i, j, v in zip(T.row, T.col, T.data)]
            (shared_tmp_path / name).write_text("\n".join(lines) + "\n")
    MPI.COMM_WORLD.Barrier()
    for name, (_, A, _) in files.items():
        mat = load_matrix(str(shared_tmp_path / name))
        np.testing.assert_array_equal(to_scipy(mat).toarray(), A)
        mat.destroy()


def test_a_node_map_that_gives_two_dofs_one_node_and_direction_is_refused(shared_tmp_path):
    # Red team: the later DOF's value was drawn at that node and the earlier one's was lost
    paths = {name: str(shared_tmp_path / name) for name in ("K.mtx", "M.mtx", "nodes.txt", "dofs.txt")}
    if MPI.COMM_WORLD.rank == 0:
        scipy.io.mmwrite(paths["K.mtx"], scipy.sparse.diags([2.0, 3.0, 4.0]).tocsr())
        scipy.io.mmwrite(paths["M.mtx"], scipy.sparse.identity(3, format="csr"))
        np.savetxt(paths["nodes.txt"], [[0.0], [1.0]])
        open(paths["dofs.txt"], "w").write("0 y\n1 y\n1 Y\n")
    MPI.COMM_WORLD.Barrier()
    with pytest.raises(InputError, match="DOF 2 \\(row 3\\) repeats node 1 y"):
        load_operators(MatrixFiles(paths["K.mtx"], paths["M.mtx"], nodes=paths["nodes.txt"], dofs=paths["dofs.txt"]))


@pytest.mark.parametrize("dofs,message", [
    ("1 y\n2 y\n3 y\n", r"DOF 2 \(row 3\) names node 3, but the nodes file '.*nodes.txt' has 3 nodes, 0 to 2; node "
                         r"numbers count from 0 \(if these count from 1, subtract 1; if not, the two files describe different "
                         r"meshes\)$"),
    ("0 y\n1 y\n7 y\n", r"DOF 2 \(row 3\) names node 7, but the nodes file '.*nodes.txt' has 3 nodes, 0 to 2: the two "
                         r"files must describe one mesh$"),
    ("0 y\n1 uy\n2 y\n", r"directions must be one of x, y, z, rx, ry, rz \(got 'uy'\)$"),
])
def test_a_dofs_file_that_names_a_node_the_nodes_file_lacks_is_refused_naming_both_files(shared_tmp_path, dofs,
                                                                                          message):
    # New-user pass: a node map counted from 1, or a nodes file of another mesh, was "nodes must be 0 to 2
    # and directions one of x, y, ...", naming neither the nodes file nor the row nor the count from 1
    nodes, dofs_path = str(shared_tmp_path / "nodes.txt"), str(shared_tmp_path / "dofs.txt")
    if MPI.COMM_WORLD.rank == 0:
        np.savetxt(nodes, [[0.0], [0.5], [1.0]])
        open(dofs_path, "w").write(dofs)
    MPI.COMM_WORLD.Barrier()
    with pytest.raises(InputError, match=r"^dofs file '.*dofs.txt': " + message):
        load_node_map(nodes, dofs_path, 3)


def test_a_node_map_file_that_does_not_parse_is_refused_naming_that_file_and_its_rows(tmp_path):
    # New-user pass: the nodes and dofs files swapped was "node map: could not convert string 'x'
    # to float64 at row 0, column 2." (neither file named). Not collective: each rank its own files.
    nodes, dofs, ragged = (str(tmp_path / name) for name in ("nodes.txt", "dofs.txt", "ragged.txt"))
    np.savetxt(nodes, [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    open(dofs, "w").write("0 y\n1 y\n")
    open(ragged, "w").write("0 y\n1 y z\n")
    assert load_node_map(nodes, dofs, 2)[0].shape == (2, 3)
    with pytest.raises(InputError, match=f"^nodes file {re.escape(repr(dofs))}: could not convert .*; it holds one "
                                         f"node a row, 1 to 3 coordinates \\(m\\)$"):
        load_node_map(dofs, nodes, 2)
    with pytest.raises(InputError, match=f"^dofs file {re.escape(repr(ragged))}: .*; it holds one DOF a row"):
        load_node_map(nodes, ragged, 2)


def test_missing_or_foreign_files_are_errors(shared_tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        load_matrix(str(shared_tmp_path / "nothing.bin"), what="stiffness")
    junk = shared_tmp_path / "junk.bin"
    if MPI.COMM_WORLD.rank == 0:
        junk.write_bytes(b"not a petsc file at all")
    MPI.COMM_WORLD.Barrier()
    with pytest.raises(InputError, match="not a PETSc binary matrix"):
        load_matrix(str(junk))
    assert_all(True)


def test_a_matrix_market_file_is_read_as_one_whatever_its_name_and_a_table_is_refused_naming_the_formats(
        shared_tmp_path, beam_files):
    # Red team (new user): the beam's K and M in Matrix Market named K.MTX and M.mm were refused as
    # "not a PETSc binary matrix"; a dense text table (numpy.savetxt) drew the same line, naming no
    # format that is read.
    _, K, M, paths = beam_files
    files = {name: str(shared_tmp_path / name) for name in ("K.MTX", "M.mm", "r.NPY", "K.txt")}
    if MPI.COMM_WORLD.rank == 0:
        for A, name in ((K, "K.MTX"), (M, "M.mm")):     # (scipy's writer appends .mtx to other names)
            scipy.io.mmwrite(str(shared_tmp_path / "written.mtx"), A, precision=17)
            os.replace(shared_tmp_path / "written.mtx", files[name])
        with open(files["r.NPY"], "wb") as f:
            np.save(f, np.load(paths["r.npy"]))
        np.savetxt(files["K.txt"], K.toarray())
    MPI.COMM_WORLD.Barrier()
    loaded = load_operators(MatrixFiles(files["K.MTX"], files["M.mm"], influence=files["r.NPY"]))
    try:
        assert abs(to_scipy(loaded.K) - K).max() <= 1e-12 * abs(K).max()
        assert abs(to_scipy(loaded.M) - M).max() <= 1e-12 * abs(M).max()
        assert np.array_equal(to_numpy(loaded.influence), np.load(paths["r.npy"]))
    finally:
        loaded.destroy()
    with pytest.raises(InputError, match=r"^stiffness file '.*K.txt' is not a PETSc binary matrix, nor Matrix Market "
                                         r"\(it does not begin with %%MatrixMarket\): a matrix is read in one of "
                                         r"those two formats"):
        load_operators(MatrixFiles(files["K.txt"], paths["M.bin"]))


def test_a_run_whose_scene_names_a_missing_matrix_file_is_one_input_error_on_every_rank(shared_tmp_path, beam_files):
    # `dbf-hpc run` hashes a scene's files (its identity) on rank 0 before it loads them: a typo in the
    # stiffness file's name was "internal error (FileNotFoundError) on rank 0", exit 70 (red team)
    from dbf_hpc.matrices import file_digest
    from dbf_hpc.run import run
    from dbf_hpc.scene import load_scene

    scene_path = shared_tmp_path / "typo.toml"
    if MPI.COMM_WORLD.rank == 0:
        scene_path.write_text(f"""[structure]
kind = "matrices"
stiffness = "{shared_tmp_path / 'Kx.mtx'}"
mass = "{beam_files[3]['M.mtx']}"
[excitation]
kind = "force"
dof = 0
amplitude = 1.0
frequency_hz = 5.0
[[constraint]]
dof = 2
law = "deadband"
clearance = 1e-3
k = 1e3
""")
    MPI.COMM_WORLD.Barrier()
    with pytest.raises(InputError, match=r"^stiffness file '.*Kx\.mtx' does not exist$"):
        run(load_scene(str(scene_path)), str(shared_tmp_path / "typo.h5"), progress=False)
    with pytest.raises(InputError, match=r"^mass file '.*' is a directory$"):
        file_digest(str(shared_tmp_path), PETSc.COMM_WORLD, "mass")
    MPI.COMM_WORLD.Barrier()
    assert_all(not any(p.name.startswith("typo.h5") for p in shared_tmp_path.iterdir()), "no output, no lock")


def test_a_matrix_file_the_run_cannot_hash_is_an_input_error_on_every_rank(shared_tmp_path, beam_files):
    # A run hashes its matrix files (rank 0) before it loads them. Red team: a missing K.bin (the solid
    # cantilever's before scripts/solid3d.py wrote it), or stiffness = "." (a directory), was an internal
    # FileNotFoundError / IsADirectoryError on rank 0 instead of one line naming the file.
    missing = str(shared_tmp_path / "nothing.bin")
    with pytest.raises(InputError, match=rf"^stiffness file '{missing}' does not exist$"):
        file_digest(missing, PETSc.COMM_WORLD, "stiffness")
    with pytest.raises(InputError, match=r"^mass file .* is a directory$"):
        MatrixFiles(beam_files[3]["K.bin"], str(shared_tmp_path)).fingerprint(PETSc.COMM_WORLD)
    # red team: a named pipe (and a device) "does not exist"
    with pytest.raises(InputError, match=r"^stiffness file '/dev/null' is a character device$"):
        file_digest("/dev/null", PETSc.COMM_WORLD, "stiffness")
    scene = validate({"structure": {"kind": "matrices", "stiffness": missing, "mass": beam_files[3]["M.bin"]}})
    with pytest.raises(InputError, match=rf"^stiffness file '{missing}' does not exist$"):
        scene.file_digests(PETSc.COMM_WORLD)
    digest = file_digest(beam_files[3]["K.bin"], PETSc.COMM_WORLD)   # the bytes' sha256, the same on every rank
    assert_all(len(digest) == 64 and len(set(MPI.COMM_WORLD.allgather(digest))) == 1)


@pytest.mark.parametrize("which,message", [("K", "stiffness matrix is not positive semi-definite"),
                                           ("M", r"mass matrix '.*Mbad.mtx' has a negative diagonal entry")])
def test_indefinite_operators_are_an_error(shared_tmp_path, beam_files, which, message):
    _, K, M, paths = beam_files
    bad = str(shared_tmp_path / f"{which}bad.mtx")
    if MPI.COMM_WORLD.rank == 0:
        A = (K if which == "K" else M).tolil()
        A[5, 5] = -abs(A[5, 5]) * 10      # one negative diagonal entry: symmetric but indefinite
        scipy.io.mmwrite(bad, A.tocsr(), precision=17)
    MPI.COMM_WORLD.Barrier()
    files = MatrixFiles(bad if which == "K" else paths["K.bin"], bad if which == "M" else paths["M.bin"])
    if which == "M":     # refused as it is read (test_an_indefinite_mass_matrix_is_refused_as_it_is_read)
        with pytest.raises(InputError, match=message):
            load_operators(files)
        return
    loaded = load_operators(files)
    with pytest.raises(DbfError, match=message):
        reference_modes(loaded, count=4)
    loaded.destroy()


@pytest.mark.parametrize("name,content,message", [
    ("r.txt", "", "is empty"),
    ("r.npy", b"", "is empty"),
    ("r.npy", "complex", "must hold real numbers"),
    ("r.npy", "nan", "NaN or Inf"),
    ("r.mtx", "%%MatrixMarket matrix array real general\n", "malformed"),
])
def test_a_bad_influence_vector_is_one_line_naming_the_file(shared_tmp_path, beam_files, name, content, message):
    # Red team: an empty file was an IndexError, a complex .npy lost its imaginary part, and a NaN
    # surfaced only at integration as "reduce dt or rtol".
    _, K, _, paths = beam_files
    path = shared_tmp_path / name
    if MPI.COMM_WORLD.rank == 0:
        if content in ("complex", "nan"):
            n = K.shape[0]
            values = np.ones(n) * (1 + 1j) if content == "complex" else np.full(n, np.nan)
            np.save(str(path), values)
        elif isinstance(content, bytes):
            path.write_bytes(content)
        else:
            path.write_text(content)
    MPI.COMM_WORLD.Barrier()
    with pytest.raises(InputError, match=message):
        load_operators(MatrixFiles(paths["K.bin"], paths["M.bin"], influence=str(path)))


@pytest.mark.parametrize("content,message", [
    ("%%MatrixMarket matrix coordinate real general\n3000000000 3000000000 1\n1 1 1.0\n", "32-bit indices"),
    ("%%MatrixMarket matrix coordinate real general\n2 2 1\n1.5 1 1.0\n", "index that is not an integer"),
    ("%%MatrixMarket matrix coordinate real general\n2 2 2\n1 1 nan\n2 2 1.0\n", "NaN or Inf"),
])
def test_matrix_market_beyond_petsc_or_with_bad_entries_is_refused(shared_tmp_path, content, message):
    path = shared_tmp_path / "bad.mtx"
    if MPI.COMM_WORLD.rank == 0:
        path.write_text(content)
    MPI.COMM_WORLD.Barrier()
    with pytest.raises(InputError, match=message):
        load_operators(MatrixFiles(str(path), str(path)))


def test_a_free_floating_matrix_model_is_said_to_have_rigid_body_modes(shared_tmp_path):
    # Red team: K of a free-free beam given as matrices was called "not positive semi-definite".
    ops = assemble_beam(Beam(**TABLE1, elements=20, left="free", right="free"))
    K, M = to_scipy(ops.K), to_scipy(ops.M)
    ops.destroy()
    if MPI.COMM_WORLD.rank == 0:
        scipy.io.mmwrite(str(shared_tmp_path / "K.mtx"), K, precision=17)
        scipy.io.mmwrite(str(shared_tmp_path / "M.mtx"), M, precision=17)
    MPI.COMM_WORLD.Barrier()
    loaded = load_operators(MatrixFiles(str(shared_tmp_path / "K.mtx"), str(shared_tmp_path / "M.mtx")))
    with pytest.raises(InputError, match="K is singular: .* rigid-body modes"):
        reference_modes(loaded, count=4)
    loaded.destroy()


def test_a_free_floating_matrix_model_is_refused_naming_a_singular_k(shared_tmp_path):
    # Red team: a spring chain without supports drew only "check the -modes_st_ solver options"
    n = 20
    K = scipy.sparse.diags([-np.ones(n - 1), 2 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1]).tolil()
    K[0, 0] = K[n - 1, n - 1] = 1.0                    # K 1 = 0: the chain translates freely
    paths = [str(shared_tmp_path / name) for name in ("K.mtx", "M.mtx")]
    if MPI.COMM_WORLD.rank == 0:
        scipy.io.mmwrite(paths[0], 1e5 * K.tocsr(), precision=17)
        scipy.io.mmwrite(paths[1], scipy.sparse.identity(n, format="csr"))
    MPI.COMM_WORLD.Barrier()
    ops = load_operators(MatrixFiles(*paths))
    try:
        with pytest.raises(DbfError, match="K is singular"):
            reference_modes(ops, count=4)
    finally:
        ops.destroy()


def test_a_damping_matrix_that_adds_energy_or_a_directory_given_as_a_file_is_refused(shared_tmp_path):
    # Red team: C = -I was accepted (rayleigh_alpha < 0 is refused); a directory "did not exist"
    paths = {name: str(shared_tmp_path / name) for name in ("K.mtx", "M.mtx", "C.mtx")}
    if MPI.COMM_WORLD.rank == 0:
        scipy.io.mmwrite(paths["K.mtx"], scipy.sparse.diags([2.0, 3.0, 4.0]).tocsr())
        scipy.io.mmwrite(paths["M.mtx"], scipy.sparse.identity(3, format="csr"))
        scipy.io.mmwrite(paths["C.mtx"], scipy.sparse.diags([0.1, -0.2, 0.1]).tocsr())
    MPI.COMM_WORLD.Barrier()
    with pytest.raises(InputError, match="negative diagonal entry \\(-0.2 in row 1\\)"):
        load_operators(MatrixFiles(paths["K.mtx"], paths["M.mtx"], damping=paths["C.mtx"]))
    with pytest.raises(InputError, match="stiffness file .* is a directory"):
        load_operators(MatrixFiles(str(shared_tmp_path), paths["M.mtx"]))


def test_a_damping_matrix_beside_modal_damping_is_refused_by_the_full_order_model(shared_tmp_path):
    # Red team: the reduced model projected C and ignored Damping(zeta=...) given with it.
    from dbf_hpc.damping import Damping
    from dbf_hpc.fom import FullOrderModel

    paths = {name: str(shared_tmp_path / name) for name in ("K.mtx", "M.mtx", "C.mtx")}
    if MPI.COMM_WORLD.rank == 0:
        scipy.io.mmwrite(paths["K.mtx"], scipy.sparse.diags([2.0, 3.0, 4.0]).tocsr())
        scipy.io.mmwrite(paths["M.mtx"], scipy.sparse.identity(3, format="csr"))
        scipy.io.mmwrite(paths["C.mtx"], scipy.sparse.diags([0.1, 0.2, 0.1]).tocsr())
    MPI.COMM_WORLD.Barrier()
    files = MatrixFiles(paths["K.mtx"], paths["M.mtx"], damping=paths["C.mtx"])
    with pytest.raises(InputError, match="only the matrix would act"):
        FullOrderModel.build(files, damping=Damping(zeta=0.02))
    with FullOrderModel.build(files) as fom:     # the matrix alone is the damping
        assert to_scipy(fom.damping_matrix()).diagonal().tolist() == [0.1, 0.2, 0.1]


def test_a_damping_matrix_with_a_negative_eigenvalue_and_a_positive_diagonal_is_refused(shared_tmp_path):
    # Red team: only C's diagonal was checked, so a C with eigenvalue -4.9 (C[5, 6] = 5 between
    # diagonal entries of 0.1, the two rows on different ranks with 2) fed energy in without a word.
    # A dashpot between two DOFs, c [[1, -1], [-1, 1]], is semi-definite at equality and stays accepted.
    n = 12
    K = scipy.sparse.diags([-np.ones(n - 1), 2 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1]).tocsr() * 1e5
    dashpot = scipy.sparse.lil_matrix((n, n))
    dashpot[5, 5] = dashpot[6, 6] = 3.0
    dashpot[5, 6] = dashpot[6, 5] = -3.0
    bad = scipy.sparse.identity(n, format="lil") * 0.1
    bad[5, 6] = bad[6, 5] = 5.0
    assert np.linalg.eigvalsh(bad.toarray()).min() < -4 and np.linalg.eigvalsh(dashpot.toarray()).min() > -1e-12
    paths = {name: str(shared_tmp_path / name) for name in ("K.mtx", "M.mtx", "C.mtx", "D.mtx", "R.mtx")}
    if MPI.COMM_WORLD.rank == 0:
        scipy.io.mmwrite(paths["K.mtx"], K, precision=17)
        scipy.io.mmwrite(paths["M.mtx"], scipy.sparse.identity(n, format="csr"))
        scipy.io.mmwrite(paths["C.mtx"], bad.tocsr(), precision=17)
        scipy.io.mmwrite(paths["D.mtx"], dashpot.tocsr(), precision=17)
        scipy.io.mmwrite(paths["R.mtx"], 1e-4 * K, precision=17)
    MPI.COMM_WORLD.Barrier()
    with pytest.raises(InputError, match=r"\|C\[5, 6\]\| = 5 above sqrt\(C\[5, 5\] C\[6, 6\]\) = 0.1: "
                                         r"C is indefinite"):
        load_operators(MatrixFiles(paths["K.mtx"], paths["M.mtx"], damping=paths["C.mtx"]))
    for name in ("D.mtx", "R.mtx"):
        load_operators(MatrixFiles(paths["K.mtx"], paths["M.mtx"], damping=paths[name])).destroy()


def test_an_indefinite_mass_matrix_is_refused_as_it_is_read_and_a_massless_dof_is_not(shared_tmp_path, beam_files):
    # Red team (new user): the beam's M with one diagonal entry negated (a sign slip in an export) ran
    # the reduced model with no word: its negative eigenvalue lies far from 0, beyond the lowest modes
    # the eigensolver finds; the full-order model grew until "the state is not finite". An M with a
    # positive diagonal and a 2 x 2 minor below 0 is indefinite as well. A lumped M without rotary
    # inertia (zero rows) and a point mass on an offset (a rank-one block, m [[1, e], [e, e^2]]) written
    # with 6 digits are positive semi-definite and stay accepted.
    _, K, M, paths = beam_files
    negated = M.tolil()
    negated[7, 7] = -negated[7, 7]
    n = 12
    chain = scipy.sparse.diags([-np.ones(n - 1), 2 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1]).tocsr() * 1e5
    minor = scipy.sparse.identity(n, format="lil")
    minor[4, 5] = minor[5, 4] = 1.5
    offset = scipy.sparse.diags(np.where(np.arange(n) % 2, 0.0, 2.0)).tolil()   # odd rows massless
    offset[8, 8], offset[8, 9], offset[9, 8], offset[9, 9] = 1 / 3, 0.1, 0.1, 0.03   # e = 0.3, m = 1/3
    assert np.linalg.eigvalsh(negated.toarray()).min() < 0 and np.linalg.eigvalsh(minor.toarray()).min() < 0
    names = ("negated.mtx", "minor.mtx", "offset.mtx", "chain.mtx")
    files = {name: str(shared_tmp_path / name) for name in names}
    if MPI.COMM_WORLD.rank == 0:
        scipy.io.mmwrite(files["negated.mtx"], negated.tocsr(), precision=17)
        scipy.io.mmwrite(files["minor.mtx"], minor.tocsr(), precision=17)
        scipy.io.mmwrite(files["offset.mtx"], offset.tocsr(), precision=6)
        scipy.io.mmwrite(files["chain.mtx"], chain, precision=17)
    MPI.COMM_WORLD.Barrier()
    with pytest.raises(InputError, match=r"^mass matrix '.*negated.mtx' has a negative diagonal entry \(-[0-9.e-]+ "
                                         r"in row 7\): a mass matrix is positive semi-definite"):
        load_operators(MatrixFiles(paths["K.bin"], files["negated.mtx"]))
    with pytest.raises(InputError, match=r"^mass matrix '.*minor.mtx' has \|M\[4, 5\]\| = 1.5 above "
                                         r"sqrt\(M\[4, 4\] M\[5, 5\]\) = 1: M is indefinite"):
        load_operators(MatrixFiles(files["chain.mtx"], files["minor.mtx"]))
    load_operators(MatrixFiles(files["chain.mtx"], files["offset.mtx"])).destroy()


def test_a_mass_matrix_of_another_dof_numbering_draws_a_warning(shared_tmp_path, beam_files, capfd):
    # Red team: a K and an M of the same size from two different meshes ran with no word (the first mode
    # 8 % off). An element's mass couples no DOFs its stiffness does not, so M's entries outside K's
    # pattern mean the files do not describe one model; the beam's own pair draws no warning.
    _, _, M, paths = beam_files
    perm = np.random.default_rng(0).permutation(M.shape[0])
    other = str(shared_tmp_path / "M_other_numbering.mtx")
    if MPI.COMM_WORLD.rank == 0:
        scipy.io.mmwrite(other, scipy.sparse.csr_matrix(M[perm][:, perm]), precision=17)
    MPI.COMM_WORLD.Barrier()
    capfd.readouterr()
    load_operators(MatrixFiles(paths["K.mtx"], paths["M.bin"])).destroy()
    assert "non-zero entries where the stiffness" not in capfd.readouterr().err
    load_operators(MatrixFiles(paths["K.mtx"], other)).destroy()
    err = capfd.readouterr().err
    if MPI.COMM_WORLD.rank == 0:
        assert re.search(r"mass matrix .*M_other_numbering.mtx' has \d+ non-zero entries where the stiffness", err), err



def test_a_nodes_file_with_a_node_number_column_draws_a_warning_or_names_it_in_its_refusal(shared_tmp_path, capfd):
    # Red team (new user): "id x y" rows (a node-number column first, as many FE codes export them)
    # were read as x = id, y = x, z = y with no word, so every displacement was drawn elsewhere; "id x
    # y z" was refused as "must hold 1 to 3 finite coordinates a row" without the reason. A frame's
    # "x y" rows and a chain of nodes 1 m apart along x (x = 0, 1, 2 and y = 0) draw no warning.
    n = 4
    paths = {name: str(shared_tmp_path / name) for name in ("K.mtx", "M.mtx", "dofs.txt")}
    tables = {"ids.txt": [[i, 0.1 * i, 0.5] for i in range(n)], "ids1.txt": [[i + 1, 0.1 * i, 0.5] for i in range(n)],
              "xy.txt": [[0.1 * i, 0.5] for i in range(n)], "chain.txt": [[float(i), 0.0] for i in range(n)],
              "ids3d.txt": [[i, 0.1 * i, 0.5, 0.0] for i in range(n)]}
    for name in tables:
        paths[name] = str(shared_tmp_path / name)
    if MPI.COMM_WORLD.rank == 0:
        scipy.io.mmwrite(paths["K.mtx"], scipy.sparse.diags([2.0, 3.0, 4.0, 5.0]).tocsr())
        scipy.io.mmwrite(paths["M.mtx"], scipy.sparse.identity(n, format="csr"))
        open(paths["dofs.txt"], "w").write("".join(f"{i} y\n" for i in range(n)))
        for name, rows in tables.items():
            np.savetxt(paths[name], rows)
    MPI.COMM_WORLD.Barrier()

    def warning(nodes):
        capfd.readouterr()
        load_operators(MatrixFiles(paths["K.mtx"], paths["M.mtx"], nodes=paths[nodes], dofs=paths["dofs.txt"])).destroy()
        return capfd.readouterr().err

    for nodes, numbers in (("ids.txt", "0, 1, ..., 3"), ("ids1.txt", "1, 2, ..., 4")):
        err = warning(nodes)
        if MPI.COMM_WORLD.rank == 0:
            assert re.search(rf"warning: the first column of the nodes file '.*{nodes}' is {re.escape(numbers)}, as node "
                             rf"numbers are: .* remove it", err), err
    for nodes in ("xy.txt", "chain.txt"):
        assert "first column" not in warning(nodes)
    with pytest.raises(InputError, match=r"must hold 1 to 3 finite coordinates a row \(m\); its first column is "
                                         r"0, 1, \.\.\., 3, as node numbers are: remove it"):
        load_operators(MatrixFiles(paths["K.mtx"], paths["M.mtx"], nodes=paths["ids3d.txt"], dofs=paths["dofs.txt"]))


def test_dofs_a_coupled_model_does_not_couple_draw_a_warning_naming_them_and_their_frequency(shared_tmp_path, capfd):
    # Red team (new user): a frame exported with its supports kept as zeroed rows and columns with 1 on
    # the diagonal of K and M had its 6 reference modes all at 1 rad/s (0.159 Hz), the isolated DOFs;
    # the run then failed on a DBF's stiffness, naming neither. A diagonal model (all DOFs decoupled)
    # and the chain without those rows draw no warning.
    n = 12
    chain = scipy.sparse.diags([-np.ones(n - 1), 2 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1]).toarray() * 1e5
    mass = np.eye(n)
    kept_k, kept_m = chain.copy(), mass.copy()
    for i in (0, n - 1):                     # a boundary condition kept in the matrices
        kept_k[i, :] = kept_k[:, i] = kept_m[i, :] = kept_m[:, i] = 0.0
        kept_k[i, i] = kept_m[i, i] = 1.0
    matrices = {"K.mtx": chain, "M.mtx": mass, "Kbc.mtx": kept_k, "Mbc.mtx": kept_m, "D.mtx": np.diag([2.0, 3.0, 4.0]),
                "I.mtx": np.eye(3)}
    paths = {name: str(shared_tmp_path / name) for name in matrices}
    if MPI.COMM_WORLD.rank == 0:
        for name, A in matrices.items():
            scipy.io.mmwrite(paths[name], scipy.sparse.csr_matrix(A), precision=17)
    MPI.COMM_WORLD.Barrier()

    def warnings_of(K, M):
        capfd.readouterr()
        load_operators(MatrixFiles(paths[K], paths[M])).destroy()
        return capfd.readouterr().err

    err = warnings_of("Kbc.mtx", "Mbc.mtx")
    if MPI.COMM_WORLD.rank == 0:
        assert re.search(r"warning: 2 DOF\(s\) of '.*Kbc.mtx' and '.*Mbc.mtx' are coupled to no other DOF: "
                         r"0 \(0.1592 Hz\), 11 \(0.1592 Hz\); .* remove fixed DOFs", err), err
    for K, M in (("K.mtx", "M.mtx"), ("D.mtx", "I.mtx")):
        assert "coupled to no other DOF" not in warnings_of(K, M)


@pytest.mark.parametrize("args,message", [((None, None), "MatrixFiles stiffness: give the path of a file"),
                                          (("K.mtx", 2), "MatrixFiles mass: give the path of a file .* got 2"),
                                          (("K.mtx", ""), "MatrixFiles mass: give the path of a file .* got ''"),
                                          (("K.mtx", b"M.mtx"), "MatrixFiles mass: give the path of a file")])
def test_matrix_files_refuse_what_is_not_a_path_where_they_are_given(args, message):
    # Red team: MatrixFiles(None, None) and MatrixFiles(1, 2) were taken, and FullOrderModel.build
    # failed in os.stat with a bare TypeError
    with pytest.raises(InputError, match=message):
        MatrixFiles(*args)


def test_matrix_files_take_a_pathlib_path_as_its_str(tmp_path):
    files = MatrixFiles(tmp_path / "K.mtx", tmp_path / "M.mtx", influence=tmp_path / "r.npy")
    assert (files.stiffness, files.mass, files.influence) == tuple(str(tmp_path / n) for n in ("K.mtx", "M.mtx", "r.npy"))


CUBE = np.array([(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1)], float)


def cube_files(folder):
    """A unit cube's 8 nodes with x, y, z DOFs each (24), K = 2 I and M = I: the paths of a model that
    takes a cells file."""
    paths = {name: str(folder / name) for name in ("K.mtx", "M.mtx", "nodes.txt", "dofs.txt")}
    if MPI.COMM_WORLD.rank == 0:
        scipy.io.mmwrite(paths["K.mtx"], 2.0 * scipy.sparse.identity(24, format="csr"))
        scipy.io.mmwrite(paths["M.mtx"], scipy.sparse.identity(24, format="csr"))
        np.savetxt(paths["nodes.txt"], CUBE)
        open(paths["dofs.txt"], "w").writelines(f"{i // 3} {'xyz'[i % 3]}\n" for i in range(24))
    return paths


def cube_operators(paths, cells=None, nodes=True):
    return load_operators(MatrixFiles(paths["K.mtx"], paths["M.mtx"], nodes=paths["nodes.txt"] if nodes else None,
                                      dofs=paths["dofs.txt"] if nodes else None, cells=cells))


def test_a_cells_file_gives_the_field_its_cells_and_changes_no_fingerprint(shared_tmp_path, capsys):
    paths = cube_files(shared_tmp_path)
    hexahedron, mirrored, tetrahedron = (str(shared_tmp_path / name) for name in ("hex.txt", "mirror.npy", "tet.txt"))
    if MPI.COMM_WORLD.rank == 0:
        open(hexahedron, "w").write("0 1 2 3 4 5 6 7\n")
        np.save(mirrored, np.array([[4, 5, 6, 7, 0, 1, 2, 3]], dtype=np.int32))   # upside down: drawn all the same
        open(tetrahedron, "w").write("0 1 3 4\n")
    MPI.COMM_WORLD.Barrier()
    for path, cells in ((hexahedron, [[0, 1, 2, 3, 4, 5, 6, 7]]), (mirrored, [[4, 5, 6, 7, 0, 1, 2, 3]]),
                        (tetrahedron, [[0, 1, 3, 4]])):
        ops = cube_operators(paths, path)
        field = ops.field
        ops.destroy()
        assert field.cells.dtype == np.int64
        np.testing.assert_array_equal(field.cells, cells)
        assert field.geometry()[4] is field.cells and len(field.cells_sha256) == 64
    # the tetrahedron leaves 4 of the cube's nodes out: their displacement would not be drawn
    assert_all(MPI.COMM_WORLD.rank > 0 or "4 nodes with a displacement DOF are in no cell of" in
               capsys.readouterr().err)
    plain = MatrixFiles(paths["K.mtx"], paths["M.mtx"], nodes=paths["nodes.txt"], dofs=paths["dofs.txt"])
    drawn = MatrixFiles(paths["K.mtx"], paths["M.mtx"], nodes=paths["nodes.txt"], dofs=paths["dofs.txt"],
                        cells=hexahedron)
    assert drawn.fingerprint(PETSc.COMM_WORLD) == plain.fingerprint(PETSc.COMM_WORLD)   # the basis cache's key


@pytest.mark.parametrize("name, content, message", [
    ("out.txt", "0 1 2 3 4 5 6 8\n", "cell 0 \\(row 1\\) names node 8; the nodes file has 8 nodes \\(0 to 7\\)"),
    ("negative.txt", "0 1 3 4\n0 1 3 -1\n", "cell 1 \\(row 2\\) names node -1; the nodes file has 8 nodes"),
    ("ragged.txt", "0 1 3 4\n0 1 3\n", "is malformed .*every row the same number of node indices"),
    ("seven.txt", "0 1 2 3 4 5 6\n", "rows of 7 nodes are no cell type dbf-hpc writes; give 2 \\(Polyline\\).* 8 "
                                     "\\(Hexahedron\\)"),
    ("half.txt", "0 1 3 4.5\n", "node indices must be integers"),
    ("twice.txt", "0 1 2 2 4 5 6 7\n", "cell 0 \\(row 1\\) lists node 2 twice"),
    ("lexicographic.txt", "0 1 3 2 4 5 7 6\n", "hexahedron 0 \\(row 1, nodes 0 1 3 2 4 5 7 6\\) is not in XDMF's "
                                               "node order"),
    ("flat.txt", "0 1 2 3\n", "tetrahedron 0 \\(row 1, nodes 0 1 2 3\\) has no volume: its corners must be apart "
                              "in 3-D .*; for quadrilaterals give \\[structure\\] cell_type = \"Quadrilateral\""),
    ("empty.txt", "", "cells file .*empty.txt' is empty"),
    ("words.npy", np.array([["a", "b", "c", "d"]]), "node indices must be integers"),
    ("objects.npy", np.array([[0, 1, 3, None]], dtype=object), "is malformed"),
    ("scalar.npy", np.array(3), "holds no table of cells"),
])
def test_a_cells_file_that_is_not_a_mesh_of_the_nodes_is_refused_in_one_line(shared_tmp_path, name, content,
                                                                              message):
    # A cell drawn between wrong or missing nodes, or a hexahedron in the lexicographic corner order of
    # many generators (drawn twisted), would be a wrong picture without a word
    paths = cube_files(shared_tmp_path)
    path = str(shared_tmp_path / name)
    if MPI.COMM_WORLD.rank == 0:
        if name.endswith(".npy"):
            np.save(path, content, allow_pickle=True)
        else:
            open(path, "w").write(content)
    MPI.COMM_WORLD.Barrier()
    with pytest.raises(InputError, match=message) as error:
        cube_operators(paths, path)
    assert "\n" not in str(error.value)


def test_a_cell_type_draws_four_nodes_as_a_quadrilateral_and_must_fit_the_rows(shared_tmp_path):
    # 4 nodes a row are tetrahedra by default; a shell's quadrilaterals say so with cell_type
    paths = cube_files(shared_tmp_path)
    faces, bow_tie = str(shared_tmp_path / "faces.txt"), str(shared_tmp_path / "bow_tie.txt")
    if MPI.COMM_WORLD.rank == 0:
        open(faces, "w").write("0 1 2 3\n4 5 6 7\n0 1 5 4\n")      # bottom, top, front
        open(bow_tie, "w").write("0 1 3 2\n")
    MPI.COMM_WORLD.Barrier()
    ops = load_operators(MatrixFiles(paths["K.mtx"], paths["M.mtx"], nodes=paths["nodes.txt"], dofs=paths["dofs.txt"],
                                     cells=faces, cell_type="Quadrilateral"))
    field = ops.field
    ops.destroy()
    assert field.cell_type == "Quadrilateral" and field.geometry()[5] == "Quadrilateral" and field.cells.shape == (3, 4)
    for cells, cell_type, message in (
            (bow_tie, "Quadrilateral", "quadrilateral 0 \\(row 1, nodes 0 1 3 2\\) has no area or its corners do "
                                       "not go round it"),
            (faces, "Hexahedron", "has 4 nodes a row, but a Hexahedron \\(cell_type\\) has 8")):
        with pytest.raises(InputError, match=message):
            load_operators(MatrixFiles(paths["K.mtx"], paths["M.mtx"], nodes=paths["nodes.txt"],
                                       dofs=paths["dofs.txt"], cells=cells, cell_type=cell_type))
    with pytest.raises(InputError, match="cell_type 'Quad' is no XDMF cell type dbf-hpc writes; give one of "
                                         "Polyline, "):
        MatrixFiles(paths["K.mtx"], paths["M.mtx"], cells=faces, cell_type="Quad")
    with pytest.raises(InputError, match="give that file as well"):
        MatrixFiles(paths["K.mtx"], paths["M.mtx"], cell_type="Quadrilateral")


def test_cells_without_a_node_map_are_refused_before_the_matrices_are_read(shared_tmp_path):
    paths = cube_files(shared_tmp_path)
    with pytest.raises(InputError, match="cells are drawn between the nodes of a node map: give \\[structure\\] "
                                         "nodes and dofs as well"):
        load_operators(MatrixFiles(str(shared_tmp_path / "missing.mtx"), paths["M.mtx"], cells=paths["K.mtx"]))


def test_a_node_map_and_a_cells_file_are_read_on_rank_0_and_every_rank_follows_them(shared_tmp_path, monkeypatch):
    # Each rank read the node map and the cells file itself: a rank that could not (a node without
    # the file) raised alone and left the others waiting. Here another rank that tried would fail.
    from dbf_hpc import matrices

    paths = cube_files(shared_tmp_path)
    hexahedron = str(shared_tmp_path / "hex.txt")
    if MPI.COMM_WORLD.rank == 0:
        open(hexahedron, "w").write("0 1 2 3 4 5 6 7\n")
    else:
        monkeypatch.setattr(matrices, "load_cells", lambda *args: pytest.fail("a rank other than 0 read the cells"))
        monkeypatch.setattr(matrices, "load_node_map", lambda *args: pytest.fail("a rank other than 0 read the node map"))
    MPI.COMM_WORLD.Barrier()
    ops = cube_operators(paths, hexahedron)
    field = ops.field
    ops.destroy()
    np.testing.assert_array_equal(field.cells, [[0, 1, 2, 3, 4, 5, 6, 7]])
    assert field.cell_type == "Hexahedron"


def test_loading_a_petsc_binary_matrix_leaves_the_options_so_a_second_run_in_one_process_asks_the_same_question(
        shared_tmp_path):
    # PETSc reads a binary file's .info beside it into the options database (-matload_block_size 1);
    # the options are part of every run identity, so a study script's second run of one scene did
    # not recognise the output its first run had finished (`resume` computed it again)
    import os

    from dbf_hpc.run import run
    from dbf_hpc.scene import load_scene
    from test_xdmf import solid

    scene = load_scene(solid(shared_tmp_path))
    assert "matload_block_size" in (shared_tmp_path / "K.bin.info").read_text()   # the generator's files carry it
    before = PETSc.Options().getAll()
    load_matrix(str(shared_tmp_path / "K.bin")).destroy()
    assert PETSc.Options().getAll() == before
    out = shared_tmp_path / "bar.h5"
    run(scene, str(out), progress=False)
    written = os.stat(out).st_mtime_ns if MPI.COMM_WORLD.rank == 0 else None
    run(scene, str(out), progress=False, resume=True)
    if MPI.COMM_WORLD.rank == 0:
        assert os.stat(out).st_mtime_ns == written                # kept, not computed and renamed again
