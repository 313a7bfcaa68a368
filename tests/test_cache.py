"""Basis cache: a hit performs no eigen-solve, whatever determines the basis rebuilds it, and a stale
or corrupt file is detected and never used (paper, conclusion 2). Each kind of enrichment (DBFs,
static modes, modes alone) is cached apart and round-trips with its own column count."""
import glob
import os

import h5py
import numpy as np
import pytest
from mpi4py import MPI

from conftest import assert_all, ends_a_hang, fifo_at, two_ranks_of
from dbf_hpc.cache import seal
from dbf_hpc.modes import counters
from dbf_hpc.reductor import Reductor
from dbf_hpc.scene import validate

STRUCTURE = {"kind": "beam", "length": 1.0, "E": 117e9, "I": 8.78e-16, "A": 2.9e-7, "rho": 11800.0,
             "elements": 40}


def scene(law="deadband", x=(0.25,), modes=6, basis=None, elements=40, **excitation):
    constraints = [{"x": v, "law": law, "k": 1e6, **({"clearance": 2.5e-3} if law == "deadband" else {})}
                   for v in x]
    return validate({"structure": {**STRUCTURE, "elements": elements}, "constraint": constraints,
                     "basis": {"modes": modes, **(basis or {})},
                     "excitation": excitation or {"kind": "none"}}, "cache-test.toml")


def summary(s, cache_dir):
    """What a basis from the cache holds: (size, K_r, B, dbf_omega, dbf_k, eigen-solves on the busiest
    rank, cache state)."""
    with s.full_order_model() as fom, Reductor(fom, s.basis_settings(), str(cache_dir)) as reductor:
        before = counters["eigen_solves"]
        basis = reductor.basis()
        solves = MPI.COMM_WORLD.allreduce(counters["eigen_solves"] - before, op=MPI.MAX)
        return (basis.size, basis.project(fom.operators.K), basis.rows(basis.constraint_rows),
                basis.enrichment_omega.copy(), basis.dbf_k.copy(), solves, basis.stats.get("cache"))


def obtain(s, cache_dir):
    """(K_r, eigen-solves it took on the busiest rank, cache state)."""
    _, Kr, _, _, _, solves, state = summary(s, cache_dir)
    return Kr, solves, state


def stored_under_key(path, other) -> None:
    """Rank 0 moves the cache file `path` onto `other`, with other's key and a valid seal: a whole file of
    another question stored under this one's key (a stale entry its checksum cannot see). Collective."""
    if MPI.COMM_WORLD.rank == 0:
        with h5py.File(other, "r") as f:
            key = f.attrs["key"]
        os.replace(path, other)
        with h5py.File(other, "r+") as f:
            f.attrs["key"] = key
        seal(other)
    MPI.COMM_WORLD.Barrier()


def test_a_cache_hit_performs_no_eigen_solve(shared_tmp_path):
    first, solves, state = obtain(scene(), shared_tmp_path)
    assert solves > 0 and state == "stored"
    second, solves, state = obtain(scene(), shared_tmp_path)
    assert solves == 0 and state == "hit"
    assert np.allclose(first, second, rtol=1e-13, atol=0)


def test_changing_the_law_or_the_excitation_reuses_the_basis(shared_tmp_path):
    obtain(scene(), shared_tmp_path)
    _, solves, state = obtain(scene(law="linear"), shared_tmp_path)
    assert solves == 0 and state == "hit"
    _, solves, state = obtain(scene(kind="base", amplitude=1e-3, frequency_hz=3.0), shared_tmp_path)
    assert solves == 0 and state == "hit"


@pytest.mark.parametrize("change", [dict(x=(0.3,)), dict(modes=5), dict(x=(0.25, 0.6))])
def test_changing_what_determines_the_basis_rebuilds_it(shared_tmp_path, change):
    obtain(scene(), shared_tmp_path)
    _, solves, state = obtain(scene(**change), shared_tmp_path)
    assert solves > 0 and state == "stored"


def test_a_basis_another_dbf_hpc_version_wrote_is_not_reused(shared_tmp_path, monkeypatch):
    # Red team: the version was in no key; a release that builds the basis otherwise (without a new
    # ALGORITHM) would have read the old files.
    import dbf_hpc.cache

    obtain(scene(), shared_tmp_path)
    monkeypatch.setattr(dbf_hpc.cache, "__version__", "9.9.9")
    _, solves, state = obtain(scene(), shared_tmp_path)
    assert solves > 0 and state == "stored"


def _cache_file(directory):
    files = MPI.COMM_WORLD.bcast(sorted(glob.glob(str(directory / "basis-*.h5"))), root=0)
    assert len(files) == 1
    return files[0]


def test_a_corrupt_basis_is_detected_and_rebuilt(shared_tmp_path):
    reference, _, _ = obtain(scene(), shared_tmp_path)
    path = _cache_file(shared_tmp_path)
    if MPI.COMM_WORLD.rank == 0:
        with h5py.File(path, "r+") as f:
            f["V"][5, 2] *= 1.001     # one flipped value: V^T M V is no longer I
        seal(path)                    # sealed again: the check of V itself is what this is about
    MPI.COMM_WORLD.Barrier()
    rebuilt, solves, state = obtain(scene(), shared_tmp_path)
    assert solves > 0 and state == "stored"
    assert np.allclose(rebuilt, reference, rtol=1e-10)


def test_an_unreadable_cache_file_is_rebuilt(shared_tmp_path):
    obtain(scene(), shared_tmp_path)
    path = _cache_file(shared_tmp_path)
    if MPI.COMM_WORLD.rank == 0:
        with open(path, "wb") as f:
            f.write(b"\x89HDF\r\n truncated")
    MPI.COMM_WORLD.Barrier()
    _, solves, state = obtain(scene(), shared_tmp_path)
    assert solves > 0 and state == "stored"
    assert_all(True)



def test_a_named_pipe_at_the_cache_file_is_rebuilt_over_not_waited_on(shared_tmp_path):
    # Red team: a FIFO at a basis cache entry hung the run before its basis (rank 0's check of the
    # file's seal opened it, and the open waited for a writer for ever; the other ranks waited for rank
    # 0). It cannot be read: rebuilt, and the basis stored in its place, on every rank alike.
    import stat

    first, _, _ = obtain(scene(), shared_tmp_path)
    path = _cache_file(shared_tmp_path)
    fifo_at(path)
    with ends_a_hang():
        Kr, solves, state = obtain(scene(), shared_tmp_path)
    assert solves > 0 and state == "stored"
    np.testing.assert_allclose(Kr, first, rtol=1e-10, atol=1e-10 * np.abs(first).max())
    assert_all(stat.S_ISREG(os.stat(path).st_mode))


@pytest.mark.parametrize("enrichment,columns", [("dbf", 8), ("static", 8), ("none", 6)])
def test_every_enrichment_round_trips_through_the_cache_with_its_column_count(shared_tmp_path, enrichment,
                                                                              columns):
    # Two constraints: 6 modes + 2 columns, or the 6 modes alone; the loaded basis passes the checks
    # of cache.load (V^T M V = I, the modes' and the enrichment columns' frequencies) and is the one stored.
    s = scene(x=(0.25, 0.6), basis={"enrichment": enrichment})
    size, Kr, B, dbf_omega, dbf_k, solves, state = summary(s, shared_tmp_path)
    assert size == columns and state == "stored" and solves > 0
    assert B.shape == (2, columns) and dbf_omega.size == columns - 6 and dbf_k.size == columns - 6
    size2, Kr2, B2, dbf_omega2, dbf_k2, solves, state = summary(s, shared_tmp_path)
    assert size2 == columns and state == "hit" and solves == 0
    assert np.array_equal(Kr, Kr2) and np.array_equal(B, B2)
    assert np.array_equal(dbf_omega, dbf_omega2) and np.array_equal(dbf_k, dbf_k2)


def test_the_kinds_of_enrichment_are_cached_apart(shared_tmp_path):
    sizes = {}
    for enrichment in ("dbf", "static", "none"):
        size, _, _, _, _, solves, state = summary(scene(basis={"enrichment": enrichment}), shared_tmp_path)
        assert state == "stored" and solves > 0, f"{enrichment} must not reuse another kind's basis"
        sizes[enrichment] = size
    assert sizes == {"dbf": 7, "static": 7, "none": 6}
    files = MPI.COMM_WORLD.bcast(sorted(glob.glob(str(shared_tmp_path / "basis-*.h5"))), root=0)
    assert len(files) == 3


@pytest.mark.parametrize("enrichment", ["static", "none"])
def test_dbf_settings_do_not_split_the_cache_of_the_other_kinds(shared_tmp_path, enrichment):
    # The DBF stiffness and derivative do not enter a static or modal basis: equal bases, one entry.
    summary(scene(basis={"enrichment": enrichment}), shared_tmp_path)
    *_, solves, state = summary(scene(basis={"enrichment": enrichment, "dbf_stiffness": 0.1,
                                             "dbf_derivative": "central"}), shared_tmp_path)
    assert solves == 0 and state == "hit"
    *_, solves, state = summary(scene(basis={"dbf_stiffness": 0.1}), shared_tmp_path)
    assert solves > 0 and state == "stored", "for DBFs the stiffness does matter"


# Offsets from the HDF5 signature where one flipped bit crashed HDF5 1.10.8 (a segmentation fault)
# reading this scene's basis file
CRASHED_HDF5 = (920, 1504)


def test_a_damaged_cache_file_is_rebuilt_without_hdf5_parsing_it(shared_tmp_path):
    # Red team: one flipped bit in a cache file's HDF5 metadata crashed the process (segmentation
    # fault inside HDF5, not an error): that run, every run of the scene after it, and `cache list` and
    # `cache clear`, so the file could not even be removed. The file's seal (a sha256 of everything
    # after HDF5's user block) is checked before HDF5 opens it.
    from dbf_hpc import cache

    reference, _, _ = obtain(scene(), shared_tmp_path)
    path = _cache_file(shared_tmp_path)
    missed = []
    if MPI.COMM_WORLD.rank == 0:
        with open(path, "rb") as f:
            original = f.read()
        start = original.find(b"\x89HDF\r\n\x1a\n")
        for offset in range(0, len(original), 61):    # the user block, HDF5's metadata, V
            damaged = bytearray(original)
            damaged[offset] ^= 1 << (offset % 8)
            with open(path, "wb") as f:
                f.write(damaged)
            if cache.seal_problem(path) is None:
                missed.append(offset)
        damaged = bytearray(original)
        for offset in CRASHED_HDF5:
            damaged[start + offset] ^= 1
        with open(path, "wb") as f:
            f.write(damaged)
        problems = [e.get("problem") for e in cache.entries(str(shared_tmp_path))]
    else:
        problems = None
    assert MPI.COMM_WORLD.bcast((missed, problems), root=0) == ([], ["unreadable (damaged)"])
    rebuilt, solves, state = obtain(scene(), shared_tmp_path)
    assert solves > 0 and state == "stored"
    assert np.allclose(rebuilt, reference, rtol=1e-10)
    assert obtain(scene(), shared_tmp_path)[2] == "hit"    # the rebuilt file is sealed again
    cleared = None
    if MPI.COMM_WORLD.rank == 0:    # a truncated file: listed as damaged, and cleared
        with open(path, "r+b") as f:
            f.truncate(len(original) - 8)
        cleared = cache.clear(str(shared_tmp_path)) == (1, len(original) - 8) and not os.path.exists(path)
    assert MPI.COMM_WORLD.bcast(cleared, root=0)


def test_a_basis_of_many_modes_less_orthonormal_than_the_check_is_reused_and_still_checked(shared_tmp_path):
    # Red team: 150 modes of a 100-element beam are M-orthonormal to ~1e-7 only (SLEPc's tolerance,
    # amplified in the DBF by Gram-Schmidt), past the 1e-8 a cached V^T M V had to meet: every run
    # stored the basis and the next said "does not match the operators (corrupt or stale)" and built it
    # again. The check now allows the basis's own defect, stored with it, plus VERIFY_TOL.
    from dbf_hpc.cache import VERIFY_TOL

    many = scene(modes=150, elements=100)
    with many.full_order_model() as fom, Reductor(fom, many.basis_settings(), str(shared_tmp_path)) as reductor:
        basis = reductor.basis()
        defect = np.abs(basis.project(fom.operators.M) - np.eye(basis.size)).max()
    assert defect > 10 * VERIFY_TOL and basis.stats["cache"] == "stored"
    reference, solves, state = obtain(many, shared_tmp_path)
    assert solves == 0 and state == "hit"
    path = _cache_file(shared_tmp_path)
    if MPI.COMM_WORLD.rank == 0:
        with h5py.File(path, "r+") as f:
            f["V"][5, 2] *= 1.001     # V^T M V departs from I by far more than the stored defect
        seal(path)
    MPI.COMM_WORLD.Barrier()
    rebuilt, solves, state = obtain(many, shared_tmp_path)
    assert solves > 0 and state == "stored"
    assert np.allclose(rebuilt, reference, rtol=1e-8)


def test_stored_constraint_rows_that_differ_from_the_scene_are_detected_and_rebuilt(shared_tmp_path):
    # Red team: one flipped bit in the stored rows moved the contact to the next node while the output
    # said x = 0.25. Everything a cached basis carries is checked against what the scene asks for.
    reference, _, _ = obtain(scene(), shared_tmp_path)
    path = _cache_file(shared_tmp_path)
    if MPI.COMM_WORLD.rank == 0:
        with h5py.File(path, "r+") as f:
            f["constraint_rows"][0] += 2          # the next node's w
        seal(path)                                # a whole file: the rows' own check must see it
    MPI.COMM_WORLD.Barrier()
    rebuilt, solves, state = obtain(scene(), shared_tmp_path)
    assert solves > 0 and state == "stored"
    assert np.allclose(rebuilt, reference, rtol=1e-10)


@pytest.mark.parametrize("name", ["dbf_k", "dbf_k_auto", "dbf_branch", "flexibility_exact", "enrichment_omega"])
def test_a_stored_value_the_operators_cannot_check_is_covered_by_a_checksum(shared_tmp_path, name):
    # Red team: k_j scaled by 10 (or f_exact by 2) in a cache file was a hit, and the output reported
    # the wrong k_j (and a false flexibility warning): V^T M V and the frequencies do not see them.
    reference = summary(scene(), shared_tmp_path)
    path = _cache_file(shared_tmp_path)
    if MPI.COMM_WORLD.rank == 0:
        with h5py.File(path, "r+") as f:
            f[name][...] = f[name][...] * 2
        seal(path)                                # a whole file: the arrays' checksum must see it
    MPI.COMM_WORLD.Barrier()
    size, Kr, B, omega, k, solves, state = summary(scene(), shared_tmp_path)
    assert solves > 0 and state == "stored"
    assert np.allclose(k, reference[4], rtol=1e-10) and np.allclose(omega, reference[3], rtol=1e-10)
    assert summary(scene(), shared_tmp_path)[6] == "hit"    # the rebuilt file is whole again


@pytest.mark.parametrize("blocker", ["file", "read-only"])
def test_a_cache_directory_that_cannot_be_made_is_a_warning_on_every_rank_not_a_hang(shared_tmp_path, blocker):
    cache = shared_tmp_path / "cache"
    if MPI.COMM_WORLD.rank == 0:
        if blocker == "file":
            cache.write_text("in the way")
        else:
            cache.mkdir(mode=0o555)
    MPI.COMM_WORLD.Barrier()
    target = cache / "sub" if blocker == "read-only" else cache
    if blocker == "read-only" and os.geteuid() == 0:
        pytest.skip("root may write anywhere")
    _, solves, state = obtain(scene(), target)
    assert solves > 0 and state == "unwritable"


def gyroscopic_basis(cache_dir, speed=30.0, form="second_order", tension=2000.0):
    """(V gathered, eigen-solves on the busiest rank, cache state, the file's path) of a moving band's basis."""
    from dbf_hpc import Beam, Constraint, FullOrderModel, law
    from dbf_hpc.basis import BasisSettings
    from test_gyroscopic import BAND

    beam = Beam(elements=40, axial_speed=speed, **{**BAND, "tension": tension})
    stops = [Constraint(law("deadband", clearance=5e-4, k=1e5), x=x) for x in (0.3, 0.75)]
    with FullOrderModel.build(beam, stops) as fom, Reductor(fom, BasisSettings(modes=4, gyroscopic_form=form),
                                                             str(cache_dir)) as reductor:
        before = counters["eigen_solves"]
        basis = reductor.basis()
        solves = MPI.COMM_WORLD.allreduce(counters["eigen_solves"] - before, op=MPI.MAX)
        if form == "state_space":
            return None, solves, basis.stats.get("cache"), None
        dense = basis.vectors.getMat()
        V = np.vstack(MPI.COMM_WORLD.allgather(dense.getDenseArray().copy()))
        basis.vectors.restoreMat(dense)
        assert basis.complex_modes == 4 and len(basis.stats["constraint_columns"]) == 2
        # each complex mode's frequency, stored and read back with the basis (`dbf-hpc basis` prints it)
        assert np.array_equal(np.unique(basis.stats["complex_omega"]), np.unique(basis.omega))
        return V, solves, basis.stats.get("cache"), basis.stats.get("cache_file")


def test_a_gyroscopic_basis_is_cached_and_its_speed_is_part_of_the_key(shared_tmp_path):
    V, solves, state, path = gyroscopic_basis(shared_tmp_path)
    assert solves > 0 and state == "stored"
    again, solves, state, _ = gyroscopic_basis(shared_tmp_path)
    assert solves == 0 and state == "hit" and np.array_equal(V, again)
    # U enters the key through the beam's fingerprint: another speed is another basis
    _, solves, state, other = gyroscopic_basis(shared_tmp_path, speed=31.0)
    assert solves > 0 and state == "stored" and other != path
    # the paper's state-space form is cached apart: another basis of the same settings and operators
    _, solves, state, _ = gyroscopic_basis(shared_tmp_path, form="state_space")
    assert solves > 0 and state == "stored"


def test_a_gyroscopic_basis_of_another_speed_under_this_key_is_detected_and_rebuilt(shared_tmp_path):
    # 20 m/s under 1883 N has the 30 m/s band's K (T - m_t U^2 the same, m_t = rho A = 0.234 kg/m) and M:
    # only G = 2 m_t U differs, so V^T M V = I and the flexibility still hold for the other file's V, but
    # its reduced model no longer has the stored complex frequencies
    _, _, _, path = gyroscopic_basis(shared_tmp_path, speed=30.0)
    slow = dict(speed=20.0, tension=2000.0 - 7800.0 * 3e-5 * (30.0**2 - 20.0**2))
    reference, _, _, other = gyroscopic_basis(shared_tmp_path / "b", **slow)
    stored_under_key(path, other)            # a whole file: the complex frequencies must see it
    rebuilt, solves, state, _ = gyroscopic_basis(shared_tmp_path / "b", **slow)
    assert solves > 0 and state == "stored"
    assert np.abs(rebuilt - reference).max() < 1e-10 * np.abs(reference).max()


def state_space_basis(cache_dir, speed=30.0, tension=2000.0, enrichment="dbf"):
    """What a moving band's state-space basis gives, gathered on every rank: its reduced model's A_r, B_r
    and constraint rows (g^T Psi_w, g^T Psi_v), its raw DBFs (d_R, d_I) and varpi (what the error
    estimate's richer basis reuses), hat-omega; the eigen-solves on the busiest rank, the cache state,
    the file."""
    from dbf_hpc import Beam, Constraint, FullOrderModel, law
    from dbf_hpc.basis import BasisSettings
    from test_gyroscopic import BAND

    def gathered(vecs):
        local = np.column_stack([v.getArray(readonly=True) for v in vecs]) if vecs else np.zeros((0, 0))
        return np.vstack([b for b in MPI.COMM_WORLD.allgather(local) if b.size] or [np.zeros((0, 0))])

    beam = Beam(elements=40, axial_speed=speed, **{**BAND, "tension": tension})
    stops = [Constraint(law("deadband", clearance=5e-4, k=1e5), x=x) for x in (0.3, 0.75)]
    settings = BasisSettings(modes=4, gyroscopic_form="state_space", enrichment=enrichment)
    with FullOrderModel.build(beam, stops) as fom, Reductor(fom, settings, str(cache_dir)) as reductor:
        before = counters["eigen_solves"]
        basis = reductor.basis()
        solves = MPI.COMM_WORLD.allreduce(counters["eigen_solves"] - before, op=MPI.MAX)
        model = reductor.reduce()
        assert basis.form == "state_space" and basis.complex_modes == 4
        return {"A": model.A, "B_state": model.B_state, "B": model.B, "B_velocity": model.B_velocity,
                "raw_real": gathered([d[0] for d in basis.raw]), "raw_imag": gathered([d[1] for d in basis.raw]),
                "varpi": np.array([d[2] for d in basis.raw]), "hat_omega": basis.enrichment_omega.copy(),
                "flexibility": basis.flexibility_captured.copy(), "solves": solves,
                "cache": basis.stats.get("cache"), "path": basis.stats.get("cache_file"),
                "complex_omega": basis.stats["complex_omega"], "columns": basis.stats["constraint_columns"]}


@pytest.mark.parametrize("enrichment", ["dbf", "none"])
def test_a_state_space_basis_is_cached_and_a_hit_gives_the_same_reduced_model_bit_for_bit(shared_tmp_path,
                                                                                       enrichment):
    # A state-space run rebuilt its basis at every invocation (it was not cached); two builds of it on a
    # CI machine differed at 4e-8, and a --resume there found its checkpoint's coordinates changed. A hit
    # solves nothing and gives the very numbers stored: the reduced model and the raw DBFs the error
    # estimate's richer basis reuses.
    first = state_space_basis(shared_tmp_path, enrichment=enrichment)
    assert first["solves"] > 0 and first["cache"] == "stored"
    again = state_space_basis(shared_tmp_path, enrichment=enrichment)
    assert again["solves"] == 0 and again["cache"] == "hit" and again["path"] == first["path"]
    for name in ("A", "B_state", "B", "B_velocity", "raw_real", "raw_imag", "varpi", "hat_omega", "flexibility"):
        assert np.array_equal(first[name], again[name]), name
    assert again["complex_omega"] == first["complex_omega"] and again["columns"] == first["columns"]
    assert first["raw_real"].shape[1] == first["varpi"].size == (2 if enrichment == "dbf" else 0)
    if enrichment == "dbf":   # the second-order basis of the same settings is another entry, not this one
        _, solves, state, other = gyroscopic_basis(shared_tmp_path)
        assert solves > 0 and state == "stored" and other != first["path"]


def _replace_in_state_space_file(path, change):
    """Rank 0 changes the cache file (change(h5py.File)) and seals it again: what is checked is the
    basis itself, not the seal."""
    if MPI.COMM_WORLD.rank == 0:
        with h5py.File(path, "r+") as f:
            change(f)
        seal(path)
    MPI.COMM_WORLD.Barrier()


def _scale_column(name, j, factor):
    def change(f):
        f[name][:, j] *= factor
    return change


# each damage and the cause the line names
STATE_SPACE_DAMAGE = {"flipped byte": "fails its file checksum", "truncated": "fails its file checksum",
                      "velocity column": "Psi^T A Psi is not I", "displacement column": "Psi^T A Psi is not I",
                      "raw DBF": "a DBF it reuses is not in its span", "hat-omega": "fails its checksum (corrupt",
                      "DBF columns swapped": "its DBF columns do not have the stored hat-omega"}


@pytest.mark.parametrize("damage", list(STATE_SPACE_DAMAGE))
def test_a_damaged_state_space_cache_file_is_refused_and_rebuilt(shared_tmp_path, damage, capfd):
    # Every damage a cache file can have is a line naming the file and its cause and a rebuild, never a
    # basis used: bytes flipped or cut (the seal), a column of either part scaled (Psi^T A Psi = I), a raw
    # DBF the richer basis would reuse (in span Psi), a hat-omega (its checksum), the two constraints' DBF
    # columns swapped (an A-orthonormal basis of the same span: only their hat-omega on these operators
    # tells).
    reference = state_space_basis(shared_tmp_path)
    path = reference["path"]
    assert reference["A"].shape == (12, 12)   # 4 complex modes and 2 DBFs, Re and Im of each
    if damage == "flipped byte" and MPI.COMM_WORLD.rank == 0:
        with open(path, "r+b") as f:
            f.seek(os.path.getsize(path) // 2)
            byte = f.read(1)
            f.seek(-1, os.SEEK_CUR)
            f.write(bytes([byte[0] ^ 0x10]))
    elif damage == "truncated" and MPI.COMM_WORLD.rank == 0:
        os.truncate(path, os.path.getsize(path) // 2)
    elif damage == "velocity column":
        _replace_in_state_space_file(path, _scale_column("velocity", 1, 1.001))
    elif damage == "displacement column":
        _replace_in_state_space_file(path, _scale_column("displacement", 8, 1 + 1e-6))
    elif damage == "raw DBF":   # another direction: V^T A V and the frequencies cannot see it
        def change(f):
            f["dbf_raw_real"][:, 0] += f["dbf_raw_real"][:, 0][::-1]
        _replace_in_state_space_file(path, change)
    elif damage == "DBF columns swapped":
        def change(f):
            for name in ("velocity", "displacement"):
                V = f[name][...]
                f[name][...] = V[:, [0, 1, 2, 3, 4, 5, 6, 7, 10, 11, 8, 9]]
        _replace_in_state_space_file(path, change)
    elif damage == "hat-omega":
        def change(f):
            f["enrichment_omega"][0] *= 1.01
        _replace_in_state_space_file(path, change)
    MPI.COMM_WORLD.Barrier()
    capfd.readouterr()
    rebuilt = state_space_basis(shared_tmp_path)
    out = capfd.readouterr().out
    assert rebuilt["solves"] > 0 and rebuilt["cache"] == "stored"
    if MPI.COMM_WORLD.rank == 0:
        assert f"basis cache {path}" in out and STATE_SPACE_DAMAGE[damage] in out and "rebuilding it" in out, out
    scale = np.abs(reference["B_state"]).max()
    assert np.abs(rebuilt["B_state"] - reference["B_state"]).max() < 1e-8 * scale
    assert state_space_basis(shared_tmp_path)["cache"] == "hit"   # the rebuilt file serves


def test_a_state_space_basis_of_another_speed_under_this_key_is_refused_and_rebuilt(shared_tmp_path, capfd):
    # 20 m/s under 1883 N has the 30 m/s band's K and M (test_a_gyroscopic_basis_of_another_speed_...):
    # Psi^T A Psi = I and the flexibility hold for the other file's Psi, but its reduced model no longer
    # has the stored complex frequencies
    path = state_space_basis(shared_tmp_path)["path"]
    slow = dict(speed=20.0, tension=2000.0 - 7800.0 * 3e-5 * (30.0**2 - 20.0**2))
    reference = state_space_basis(shared_tmp_path / "b", **slow)
    other = reference["path"]
    stored_under_key(path, other)
    capfd.readouterr()
    rebuilt = state_space_basis(shared_tmp_path / "b", **slow)
    out = capfd.readouterr().out
    assert rebuilt["solves"] > 0 and rebuilt["cache"] == "stored"
    if MPI.COMM_WORLD.rank == 0:
        assert "does not match the operators (its reduced model lacks the stored complex frequencies" in out, out
    assert np.abs(rebuilt["B_state"] - reference["B_state"]).max() < 1e-8 * np.abs(reference["B_state"]).max()


def test_cache_list_shows_a_state_space_entry_and_clear_removes_it(shared_tmp_path):
    # A state-space file holds its two parts, not V: `cache list` would call it a foreign file, and
    # `cache clear` never remove it. Not collective (rank 0 lists and clears).
    from dbf_hpc import cache

    first = state_space_basis(shared_tmp_path)
    if MPI.COMM_WORLD.rank == 0:
        (entry,) = cache.entries(str(shared_tmp_path))
        assert "problem" not in entry and entry["form"] == "state_space", entry
        assert entry["shape"] == (first["raw_real"].shape[0], 12) and entry["path"] == first["path"]
        assert cache.clear(str(shared_tmp_path))[0] == 1 and not os.path.exists(first["path"])
    MPI.COMM_WORLD.Barrier()


def test_clear_on_a_read_only_cache_is_one_error_saying_what_it_could_not_remove(tmp_path):
    # Red team: `dbf-hpc cache clear` on a read-only file system ended in "internal error (OSError)"
    # at the first file. Not collective: each rank clears a cache of its own.
    import subprocess

    from conftest import tmpfs_disk
    from dbf_hpc import cache
    from dbf_hpc.errors import InputError

    with tmpfs_disk(tmp_path, "1m") as disk:
        damaged = disk / "basis-0123456789abcdef0123.h5"
        damaged.write_bytes(b"\x89HDF\r\n\x1a\n damaged")
        assert [e.get("problem") for e in cache.entries(str(disk))] == ["unreadable (damaged)"]
        subprocess.run(["mount", "-o", "remount,ro", str(disk)], check=True)
        with pytest.raises(InputError, match=r"cannot remove 1 file\(s\) of the basis cache .*Read-only file "
                                             r"system; removed 0 file\(s\)"):
            cache.clear(str(disk))
        assert damaged.exists()


def test_a_cache_file_stored_again_between_the_check_and_the_read_is_rebuilt_not_mixed(shared_tmp_path, monkeypatch):
    # M-helper's red team: rank 0 checked the seal, then every rank opened the path itself; another job
    # storing the entry again in between (a repeated mode turned on another rank count) gave the ranks
    # rows of two bases. What rank 0 checked is now compared with what each rank holds open.
    from dbf_hpc import sealed

    reference, _, _ = obtain(scene(), shared_tmp_path)
    check = sealed.check
    # as if rank 0 had checked another file than the one the ranks then open
    monkeypatch.setattr(sealed, "check", lambda *a: (check(*a)[0], b"another file's user block"))
    rebuilt, solves, state = obtain(scene(), shared_tmp_path)
    assert solves > 0 and state == "stored"
    assert np.allclose(rebuilt, reference, rtol=1e-10)
    monkeypatch.undo()
    _, solves, state = obtain(scene(), shared_tmp_path)      # the file read back as checked: a hit
    assert solves == 0 and state == "hit"


def test_an_option_that_only_shows_a_solve_is_no_part_of_the_basis_key(shared_tmp_path):
    # helper L's red team: -modes_eps_view made every run build the basis again; a tolerance still counts
    from petsc4py import PETSc

    from dbf_hpc.cache import basis_key

    s = scene()
    settings, options = s.basis_settings(), PETSc.Options()
    plain = basis_key({"K": "k"}, [3], settings)
    for name, value in (("modes_eps_view", ""), ("modes_st_ksp_monitor", ""), ("dbf_eps_converged_reason", ""),
                        ("modes_eps_view_values", "")):
        options.setValue(name, value)
        try:
            assert basis_key({"K": "k"}, [3], settings) == plain, name
        finally:
            options.delValue(name)
    options.setValue("modes_eps_tol", "1e-12")
    try:
        assert basis_key({"K": "k"}, [3], settings) != plain
    finally:
        options.delValue("modes_eps_tol")


def test_a_static_option_the_exact_flexibility_was_computed_under_is_part_of_every_basis_key(shared_tmp_path):
    # red team: f_exact = g^T K^-1 g, stored with every basis (the captured-flexibility indicator), is
    # solved with the static_ prefix; a DBF basis built under a static_ solve that fails stored NaN, and a
    # run without the option hit the cache and reported no indicator
    from conftest import petsc_options

    def flexibility(cache_dir):
        s = scene()
        with s.full_order_model() as fom, Reductor(fom, s.basis_settings(), str(cache_dir)) as reductor:
            basis = reductor.basis()
            return basis.flexibility_exact.copy(), basis.stats.get("cache")

    with petsc_options(static_ksp_type="cg", static_pc_type="none", static_ksp_max_it="1"):
        failed, state = flexibility(shared_tmp_path)
    assert state == "stored" and np.all(np.isnan(failed))
    exact, state = flexibility(shared_tmp_path)
    assert state == "stored", "a basis stored under other static_ options was reused"
    assert np.all(np.isfinite(exact) & (exact > 0))   # the pinned-pinned beam's K is regular


def test_a_free_free_beams_basis_with_rigid_body_modes_is_reused_from_the_cache(shared_tmp_path):
    """A free-free beam has two rigid-body modes, omega^2 at round-off (1e-7 rad^2/s^2 against the
    largest 1e6): reloading its basis recomputes diag(V^T K V) with another round-off, which a
    purely relative check took for a stale file (red team: every run said "corrupt or stale" and
    rebuilt). The frequencies are checked to round-off of the largest one kept."""
    free = {"structure": {"kind": "beam", "length": 1.0, "E": 7e10, "I": 1e-10, "A": 1e-4, "rho": 2700.0,
                          "elements": 40, "left": "free", "right": "free"}}   # an aluminium bar
    s = validate({**free, "constraint": [{"x": v, "law": "linear", "k": 2e3} for v in (0.0, 1.0)]
                  + [{"x": 0.5, "law": "deadband", "clearance": 1e-3, "k": 1e5}],
                  "basis": {"modes": 6}, "excitation": {"kind": "none"}}, "cache-test.toml")
    first, solves, state = obtain(s, shared_tmp_path)
    assert solves > 0 and state == "stored"
    second, solves, state = obtain(s, shared_tmp_path)
    assert solves == 0 and state == "hit"
    assert np.allclose(first, second, rtol=1e-13, atol=0)


def richer(s, cache_dir, first_only=False):
    """The estimate's richer models of scene s's basis (accuracy.richer_models, or richer_model alone)
    with the cache in cache_dir (or none): ((M, K, C, B) of each model, eigen-solves on the busiest rank)."""
    from dbf_hpc import accuracy

    with s.full_order_model() as fom, Reductor(fom, s.basis_settings(), None) as reductor:
        basis = reductor.basis()
        before = counters["eigen_solves"]
        cache = None if cache_dir is None else str(cache_dir)
        models = ((accuracy.richer_model(fom, basis, cache),) if first_only
                  else accuracy.richer_models(fom, basis, cache))
        solves = MPI.COMM_WORLD.allreduce(counters["eigen_solves"] - before, op=MPI.MAX)
    return [(m.M, m.K, m.C, m.B) for m in models], solves


def test_the_estimates_richer_modes_are_cached_and_give_its_models_bit_for_bit(shared_tmp_path, capfd):
    # The estimate's richer bases (1.5 to 3 times the run's modes) were solved again at every run, also
    # where the run's own basis came from the cache: the 2-D tube's 96 modes, 0.45 s a run
    s = scene(modes=6)
    solved, solves = richer(s, None)
    assert solves == 1 and len(solved) == 2, "one eigensolve for both richer models"
    stored, solves = richer(s, shared_tmp_path)
    assert solves == 1
    hit, solves = richer(s, shared_tmp_path)
    assert solves == 0, "the second run's richer modes come from the cache"
    for models in (stored, hit):    # the same numbers as the solve: the same estimate
        assert all(np.array_equal(a, b) for m, n in zip(solved, models) for a, b in zip(m, n))
    # the count is part of the key: the first richer model alone (12 modes, not 18) is solved anew
    alone, solves = richer(s, shared_tmp_path, first_only=True)
    assert solves == 1 and alone[0][1].shape == (13, 13) and solved[0][1].shape == (13, 13)
    # and its own entry serves it next time, bit for bit like a solve of 12 modes
    again, solves = richer(s, shared_tmp_path, first_only=True)
    fresh, _ = richer(s, None, first_only=True)
    assert solves == 0 and all(np.array_equal(a, b) for a, b in zip(again[0], fresh[0]))
    # a cache that cannot be written keeps nothing, gives the same models, and adds no warning to the run
    # basis's own
    blocked = shared_tmp_path / "in-the-way"
    if MPI.COMM_WORLD.rank == 0:
        blocked.write_text("a file, not a directory")
    MPI.COMM_WORLD.Barrier()
    capfd.readouterr()
    unwritable, solves = richer(s, blocked)
    assert solves == 1 and "warning" not in capfd.readouterr().err
    assert all(np.array_equal(a, b) for m, n in zip(solved, unwritable) for a, b in zip(m, n))



def test_an_odd_count_of_richer_modes_on_a_beam_of_two_planes_is_its_whole_pairs_stored_once(shared_tmp_path):
    # An odd count on a beam of two planes keeps one of a y-z pair in a direction set by round-off
    # (basis.check_pairs refuses such a basis), so cache.obtain_modes takes the whole pair, as the
    # solve does: 9 richer modes are 10, stored once and read back, and the 10 asked next are the same
    from dbf_hpc import BaseMotion, Beam, Constraint, FullOrderModel, law
    from dbf_hpc.cache import obtain_modes

    tube = Beam(length=1.0, E=117e9, I=8.78e-16, A=2.9e-7, rho=11800.0, elements=20, planes=2)
    holes = [Constraint(law("circular", clearance=2.5e-3, k=1e6), x=x) for x in (0.25, 0.6)]
    with FullOrderModel.build(tube, holes, BaseMotion(5e-3, 1.0)) as fom:
        # (count, solved, cache files after): 9 solved as 10 and stored, then read, and 10 read too
        for count, solved in ((9, True), (9, False), (10, False)):
            before = counters["eigen_solves"]
            modes = obtain_modes(fom.operators, count, fom.fingerprint, str(shared_tmp_path))
            solves = MPI.COMM_WORLD.allreduce(counters["eigen_solves"] - before, op=MPI.MAX)
            omega = modes.omega.copy()
            modes.destroy()
            files = MPI.COMM_WORLD.bcast(sorted(glob.glob(str(shared_tmp_path / "basis-*.h5"))), root=0)
            assert (omega.size, solves > 0, len(files)) == (10, solved, 1)
            np.testing.assert_allclose(omega[0::2], omega[1::2], rtol=1e-9)


def test_the_estimates_richer_modes_of_a_symmetric_structure_take_a_repeated_frequency_whole_from_the_cache(
        shared_tmp_path):
    # Two identical chains (every frequency twice): 5 richer modes (2 modes and 3 stops) end inside the
    # 3rd pair. Stored through the basis build, that count was refused as a user's [basis] modes
    # would be, and a cached run of such a structure had no richer model: its estimate was lost. The
    # pair is taken whole (6 modes, as reference_modes gives such counts) and served by the cache.
    import scipy.linalg

    from conftest import twin_chains
    from dbf_hpc.cache import obtain_modes

    ops, K, M = twin_chains(shared_tmp_path)
    chain = np.sqrt(np.sort(scipy.linalg.eigh(K, M, eigvals_only=True))) / (2 * np.pi)
    try:
        for stored in (False, True):   # solved and stored, then read back
            before = counters["eigen_solves"]
            modes = obtain_modes(ops, 5, {"structure": "twin chains"}, str(shared_tmp_path / "cache"))
            try:
                assert modes.count == 6
                np.testing.assert_allclose(modes.omega / (2 * np.pi), np.repeat(chain[:3], 2), rtol=1e-9)
            finally:
                modes.destroy()
            assert (counters["eigen_solves"] == before) == stored
    finally:
        ops.destroy()


def test_the_estimates_whole_pair_in_the_cache_does_not_serve_a_run_asking_a_count_that_cuts_it(shared_tmp_path):
    # The estimate's richer modes take a repeated frequency whole (5 asked, 6 stored) in an entry of modes
    # alone without constraint rows: the key of a run of the same structure asking 5 modes alone. That run
    # read the 6 modes from the cache, where without it 5 is refused (a pair cut: a direction set by
    # round-off). The estimate's entry has its own key; a run's count must be the count an entry holds.
    from dbf_hpc.basis import BasisSettings
    from dbf_hpc.cache import cache_path, basis_key, obtain_basis, obtain_modes
    from dbf_hpc.errors import InputError
    from conftest import twin_chains

    ops, _, _ = twin_chains(shared_tmp_path)
    fingerprint, cache = {"structure": "twin chains"}, str(shared_tmp_path / "cache")
    none, five = np.zeros(0, dtype=np.int64), BasisSettings(modes=5, enrichment="none")

    def refused():
        try:
            obtain_basis(ops, none, five, fingerprint, cache).destroy()
        except InputError as e:
            return "keeps 1 of the 2 modes" in str(e)
        return False

    try:
        obtain_modes(ops, 5, fingerprint, cache).destroy()
        assert refused(), "with the estimate's entry in the cache, as without a cache"
        # an entry stored under the run's own key (by 0.2.3, which keyed both alike) is not used either
        moved = False
        if MPI.COMM_WORLD.rank == 0:
            stored = glob.glob(os.path.join(cache, "basis-*.h5"))
            if len(stored) == 1:
                os.rename(stored[0], cache_path(cache, basis_key(fingerprint, none, five)))
                moved = True
        assert MPI.COMM_WORLD.bcast(moved, root=0), "one entry, the estimate's"
        assert refused()
    finally:
        ops.destroy()


# Rank 0 of a 2-rank job meets an exception no write foresaw (a ValueError from h5py's create_dataset or
# os.replace) as it writes the basis cache (cache.save), through the Python API; every rank says what it
# raised, then the files
_UNEXPECTED_AS_RANK_0_SAVES = """
import os, sys
import h5py
from mpi4py import MPI
from dbf_hpc import BasisSettings, Beam, Constraint, FullOrderModel, Reductor, law

folder, where, rank = sys.argv[1], sys.argv[2], MPI.COMM_WORLD.rank
def refuse(*args, **kwargs):
    raise ValueError(f"rank 0's {where} refused")
if rank == 0 and where == "create_dataset":   # as it opens the file
    h5py.Group.create_dataset = refuse
if rank == 0 and where == "os.replace":       # as it moves the finished file into place
    os.replace = refuse
beam = Beam(length=1.0, E=117e9, I=8.78e-16, A=2.9e-7, rho=11800.0, elements=20)
def act():
    with FullOrderModel.build(beam, [Constraint(law("deadband", clearance=2.5e-3, k=1e6), x=0.25)]) as fom:
        with Reductor(fom, BasisSettings(modes=4), folder) as reductor:
            reductor.basis()


every_rank_says(act, folder)
"""


@pytest.mark.launcher
@pytest.mark.parametrize("where", ["create_dataset", "os.replace"])
def test_an_unexpected_error_while_rank_0_writes_the_cache_is_raised_on_every_rank_and_leaves_no_file(tmp_path,
                                                                                                      where):
    # Red team: save() passed on a write error (OSError, RuntimeError) or a full disk, nothing else; any
    # other exception on rank 0 (a bug, an h5py ValueError) left rank 0 alone with it and rank 1 waiting
    # in the broadcast for ever (the Python API does not abort as `python -m mpi4py` does), and its
    # temporary file behind. Now every rank raises it (rank 0 its own, rank 1 a copy naming rank 0).
    out = two_ranks_of(_UNEXPECTED_AS_RANK_0_SAVES, tmp_path, where)
    assert out.returncode == 0, f"exit {out.returncode} (124: a rank waited for ever)\n{out.stdout}{out.stderr}"
    assert out.stdout.splitlines() == [f"rank 0: ValueError: rank 0's {where} refused (origin None)",
                                       f"rank 1: ValueError: rank 0's {where} refused (origin 0)",
                                       "files []"], out.stdout + out.stderr
