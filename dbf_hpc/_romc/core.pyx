# cython: language_level=3, boundscheck=False, wraparound=False
"""Cython glue of the reduced model's C callbacks (rom_core.c): a ReducedModel's arrays into a C
context, the callbacks onto a petsc4py TS (as petsc4py's wrap-cython demo does), and the TS monitor:
samples and per-step statistics in C, Python only for what must be Python (writing the samples in
blocks, the per-step hook when it is due, signals)."""
import numpy as np
from petsc4py import PETSc
from petsc4py.PETSc cimport TS, Vec, Mat, PC, SNES, PetscTS, PetscVec, PetscMat, PetscPC, PetscSNES
from cpython.exc cimport PyErr_CheckSignals
from libc.string cimport memset

cdef extern from "petsc.h":
    ctypedef long PetscInt
    ctypedef int PetscErrorCode
    ctypedef double PetscReal
    PetscErrorCode TSMonitorSet(PetscTS, PetscErrorCode (*)(PetscTS, PetscInt, PetscReal, PetscVec, void*), void*, void*)
    PetscErrorCode TSSetMaxTime(PetscTS, PetscReal)
    PetscErrorCode VecGetArrayRead(PetscVec, const PetscReal **)
    PetscErrorCode VecRestoreArrayRead(PetscVec, const PetscReal **)

cdef extern from "petscviewer.h":
    PetscErrorCode PetscOptionsPushGetViewerOff(int)
    PetscErrorCode PetscOptionsPopGetViewerOff()

cdef extern from "rom_core.h":
    ctypedef struct RomCtx:
        PetscInt r, nl, nprobe
        PetscInt dim, ncon
        PetscReal *K
        PetscReal *D
        PetscReal *B
        PetscReal *Bt
        PetscReal *BT
        PetscReal *BvT
        int first, jlu_ok
        PetscReal *jNz
        PetscReal *jNv
        PetscReal *Bv
        PetscReal *Jd
        PetscReal *Jlu
        PetscInt *jpiv
        PetscReal *KT
        PetscReal *DT
        PetscReal *Mo
        PetscReal *Do
        PetscReal *Ko
        PetscReal *MoT
        PetscReal *DoT
        PetscReal *Ms
        PetscReal *Ds
        PetscReal *Ks
        int sym_ok, m_identity
        PetscInt am
        PetscReal *ad
        PetscReal *A12
        PetscReal *SL
        PetscReal *SU
        int arrow_ok
        PetscReal *rc
        PetscReal *base_load
        PetscReal *force_shape
        PetscReal *probe_B
        PetscReal *probe_r
        int d_zero
        int d_diag, do_diag
        PetscReal sup_a, sup_w, sup_ph, force_a, force_w, force_ph
        PetscInt nrand
        PetscReal *rand_amp
        PetscReal *rand_omega
        PetscReal *rand_phase
        PetscInt nhist, nterm
        PetscReal *hist_amp
        PetscReal *hist_omega
        PetscReal *hist_phase
        PetscReal *X
        int hist_horner
        PetscReal hist_dw
        PetscReal *hist_w0
        PetscReal *hist_re
        PetscReal *hist_im
        PetscReal *hist_sr
        PetscReal *hist_si
        int friction, has_nv
        PetscReal *slip
        PetscReal *fvreg
        PetscReal *pl_gap
        PetscReal *pl_k
        PetscReal *pl_mu
        PetscReal *pl_vreg
        PetscReal *pl_c
        PetscReal *pl_alpha
        PetscReal *pl_e
        int *pl_flat
        int implicit_contact, damped, hunt_crossley, poly_cubic, two_linear, pwlinear
        int *kind
        PetscReal *em
        PetscReal *ep
        PetscReal *km
        PetscReal *kp
        PetscReal *pm1
        PetscReal *pp1
        PetscReal *km_pm
        PetscReal *kp_pp
        PetscReal *k3
        PetscReal *c
        PetscReal *alpha
        PetscInt *tab_off
        PetscInt *tab_n
        PetscReal *tab_z
        PetscReal *tab_f
        PetscReal *tab_slope
        PetscReal *z
        PetscReal *v
        PetscReal *N
        PetscReal *Nz
        PetscReal *Nv
        PetscReal *BtN
        PetscReal *tmp
        PetscReal *tmp2
        PetscReal *W
        PetscReal *NzJ
        PetscReal *NvJ
        signed char *sides
        PetscReal fact_shift
        PetscReal *L
        PetscReal *U
        PetscReal *AinvB
        PetscReal *Cap
        PetscReal *Mcap
        PetscInt *piv
        PetscInt *lpiv
        PetscInt *act
        long fact_id
        long *col_id
        long *cap_id
        int linear_shortcut
        long n_snes, n_newton, n_ifun, n_ijac, n_rhs, n_apply, n_fact, n_mult, n_shortcut
        PetscReal *peak
        PetscReal *acc_impacts
        PetscReal *acc_contact_time
        PetscReal *acc_run
        PetscReal *acc_duration_max
        PetscReal *acc_f2
        PetscReal *acc_z2
        PetscReal *acc_power
        PetscReal *acc_force_peak
        PetscReal *acc_displacement_peak
        PetscReal *acc_prev
        PetscReal acc_t0, acc_t_prev
        int acc_started
        PetscReal *acc_work
        PetscReal *acc_work_prev
        PetscReal *alpha_speed
        PetscReal *sample_t
        PetscReal sample_tol
        PetscInt nsample, next_sample
        int dense_output
        PetscReal *rows
        PetscInt row_len, row_cap, nrows
        PetscVec work
    void RomLaws(RomCtx *, const PetscReal *, const PetscReal *, PetscReal *, PetscReal *, PetscReal *, int)
    int RomFinite(RomCtx *, const PetscReal *)
    void RomRate(RomCtx *, PetscReal, const PetscReal *, PetscReal *, PetscReal *, PetscReal *, PetscReal *)
    PetscErrorCode RomTakeSamples(RomCtx *, PetscTS, PetscReal, PetscVec, PetscInt *)
    void RomStepStatistics(RomCtx *, PetscReal, const PetscReal *)
    PetscErrorCode RomAttach(RomCtx *, PetscTS, PetscVec, PetscVec, PetscMat, int)
    PetscErrorCode RomCreateShellMat(RomCtx *, PetscMat *)
    PetscErrorCode RomSetPCShell(RomCtx *, PetscPC)
    PetscErrorCode RomSetSNESShell(RomCtx *, PetscSNES)
    PetscErrorCode RomDestroy(RomCtx *)

LAW_CODE = {"deadband": 0, "power": 0, "hertz": 0, "linear": 1, "cubic": 1, "table": 2, "friction": 3}
ACCUMULATED = ("impacts", "contact_time", "run", "duration_max", "f2", "z2", "power", "force_peak",
               "displacement_peak")
ARROW_MIN = 4   # the fewest diagonal leading rows worth the arrow factor


def arrow_size(*matrices) -> int:
    """The largest m such that every matrix's leading m x m block is diagonal (exact zeros off the
    diagonal: reductor._clean_projection makes them so on the reference modes), 0 below ARROW_MIN."""
    m = matrices[0].shape[0]
    for A in matrices:
        off = np.asarray(A)[:m, :m] != 0
        np.fill_diagonal(off, False)
        coupled = (np.tril(off) | np.triu(off).T).any(axis=1)   # row i coupled to a row j < i
        if coupled.any():
            m = int(np.argmax(coupled))
    return m if m >= ARROW_MIN else 0


SYMMETRY_TOL = 1e-10   # relative asymmetry of K, D up to which the symmetric part is factored (Cholesky)
USER_ERROR = 83   # PETSC_ERR_USER: a Python exception in the monitor, re-raised after TSSolve


cdef inline int CHK(PetscErrorCode ierr) except -1:
    if ierr != 0:
        raise PETSc.Error(ierr)
    return 0


def viewers_off():
    """PetscOptionsPushGetViewerOff(TRUE): the *ViewFromOptions queries inside every stage solve return
    at once (pop with viewers_pop)."""
    CHK(PetscOptionsPushGetViewerOff(1))


def viewers_pop():
    CHK(PetscOptionsPopGetViewerOff())


cdef PetscErrorCode _monitor(PetscTS ts, PetscInt step, PetscReal t, PetscVec u, void *ctx) with gil:
    cdef Problem self = <Problem>ctx
    try:
        return self.monitor(ts, step, t, u)
    except BaseException as e:   # KeyboardInterrupt from a signal, an OSError writing the output, ...
        self.error = e
        return USER_ERROR


cdef class Problem:
    """The C callbacks of one reduced model. `operators` is rom_integrator.ReducedProblem (the model's
    matrices with M_r^-1 applied), or for the first-order form of a gyroscopic structure (model.form
    "state_space") state_space.StateSpaceProblem (B_r, the contact's A_r^-1 B_v^T and the loads with
    A_r^-1 applied; the state is eta, r = model.size values); the arrays are kept alive here as long
    as the Problem lives, which must be as long as the TS it is attached to."""
    cdef RomCtx c
    cdef list keep
    cdef object rows_arr, prev_arr, work_prev_arr
    # the monitor's Python side
    cdef public object error, record, recorder, on_step, due, steps, commit, stop_message, ts
    cdef public object nonfinite
    cdef bint resumed_first
    cdef long since_report
    cdef PetscInt arrow_found

    def __cinit__(self):
        memset(&self.c, 0, sizeof(RomCtx))
        self.keep = []

    cdef PetscReal *dptr(self, a) except NULL:
        a = np.ascontiguousarray(a, dtype=np.float64)
        if a.size == 0:
            a = np.zeros(1)
        self.keep.append(a)
        return <PetscReal *><size_t>a.ctypes.data

    cdef PetscInt *iptr(self, a) except NULL:
        a = np.ascontiguousarray(a, dtype=PETSc.IntType)
        if a.size == 0:
            a = np.zeros(1, dtype=PETSc.IntType)
        self.keep.append(a)
        return <PetscInt *><size_t>a.ctypes.data

    def __init__(self, model, operators, bint implicit_contact=True):
        from dbf_hpc.excitation import CorrelatedProcess, Harmonic, RandomProcess
        if np.dtype(PETSc.ScalarType) != np.float64 or np.dtype(PETSc.IntType).itemsize != sizeof(PetscInt):
            raise ImportError("the C callbacks need a real double-precision PETSc")
        cdef RomCtx *c = &self.c
        r, nl = model.size, model.B.shape[0]
        d = model.constraints.dimension
        if d not in (1, 2):
            raise TypeError(f"constraints of {d} directions have no C implementation")
        c.r, c.nl, c.dim, c.ncon = r, nl, d, nl // d
        first = getattr(model, "form", "") == "state_space"
        c.first = int(first)
        if first:   # F = eta' + K eta - Bt^T N: K = A_r^-1 B_r, no D; the stage solve is a dense LU (Jd, Jlu)
            K, D = np.asarray(operators.Bs, float), np.zeros((r, r))
        else:
            K, D = np.asarray(operators.K, float), np.asarray(operators.D, float)
        c.K, c.D = self.dptr(K), self.dptr(D)
        c.KT, c.DT = self.dptr(K.T), self.dptr(D.T)
        # the stage solve factors A(s) = s^2 M + s D + K of the model's own matrices, symmetric to the
        # projection's round-off for a symmetric structure: then the Cholesky of their symmetric part,
        # within SYMMETRY_TOL of the exact one (Newton's residual removes the difference)
        Mo, Do, Ko = ((np.eye(r), np.zeros((r, r)), K) if first else
                      (np.asarray(a, float) for a in (model.M, model.damping, model.K)))
        c.Mo, c.Do, c.Ko, c.MoT, c.DoT = self.dptr(Mo), self.dptr(Do), self.dptr(Ko), self.dptr(Mo.T), self.dptr(Do.T)
        c.Ms, c.Ds, c.Ks = self.dptr(0.5 * (Mo + Mo.T)), self.dptr(0.5 * (Do + Do.T)), self.dptr(0.5 * (Ko + Ko.T))
        asym = lambda A: np.abs(A - A.T).max(initial=0.0) <= SYMMETRY_TOL * max(np.abs(A).max(initial=0.0), 1e-300)
        c.sym_ok = int(asym(Mo) and asym(Do) and asym(Ko))
        c.m_identity = int(np.array_equal(Mo, np.eye(r)))
        B = np.asarray(model.B, float).reshape(nl, r)
        Bt = np.ascontiguousarray(np.asarray(operators.Bvt if first else operators.Bt, float).reshape(r, nl).T)
        c.B, c.BT = self.dptr(B), self.dptr(B.T)
        if first:   # v from the velocity part's rows
            Bv = np.asarray(model.B_velocity, float).reshape(nl, r)
            c.Bv, c.BvT = self.dptr(Bv), self.dptr(Bv.T)
            c.Jd, c.Jlu, c.jpiv = self.dptr(np.zeros(r * r)), self.dptr(np.zeros(r * r)), self.iptr(np.zeros(r))
            c.jNz, c.jNv, c.jlu_ok = self.dptr(np.zeros(nl * d)), self.dptr(np.zeros(nl * d)), 0
        else:
            c.Bv, c.BvT = c.B, c.BT
        c.Bt = c.B if np.array_equal(B, Bt) else self.dptr(Bt)
        c.rc = self.dptr(model.r_c)
        c.base_load, c.force_shape = self.dptr(operators.base_load), self.dptr(operators.force_shape)  # (r,) or (r, m)
        c.nprobe = model.probe_B.shape[0]
        c.probe_B, c.probe_r = self.dptr(model.probe_B), self.dptr(model.probe_r)
        c.d_zero = int(not np.any(D))
        diagonal = lambda A: not np.any(A - np.diag(np.diag(A)))
        c.d_diag, c.do_diag = int(diagonal(D)), int(diagonal(Do))
        two_pi = 2 * np.pi
        s = model.support
        c.sup_a, c.sup_w, c.sup_ph = s.amplitude, two_pi * s.frequency_hz, s.phase
        f = model.force
        if isinstance(f, CorrelatedProcess) != (np.ndim(operators.force_shape) == 2):
            raise TypeError("a load matrix goes with a CorrelatedProcess's histories, one load shape with one history")
        if isinstance(f, CorrelatedProcess):
            c.nhist, c.nterm = f.count, f.omega.shape[1]
            c.hist_amp, c.hist_omega, c.hist_phase = self.dptr(f.amplitude), self.dptr(f.omega), self.dptr(f.phase)
            c.X = self.dptr(np.zeros(f.count))
            # equally spaced in k (Deodatis' frequencies): Horner's rule instead of a cosine per term, the
            # same sum to round-off (the phase error of w0 + k dw against omega_mk is ~1e-16 omega_mk t)
            nk = f.omega.shape[1]
            dw = (f.omega[0, -1] - f.omega[0, 0]) / (nk - 1) if nk > 1 else 0.0
            if nk > 1 and np.allclose(f.omega, f.omega[:, :1] + dw * np.arange(nk), rtol=1e-13, atol=0.0):
                c.hist_horner, c.hist_dw = 1, dw
                A = f.amplitude * np.exp(1j * f.phase)
                c.hist_w0, c.hist_re, c.hist_im = self.dptr(f.omega[:, 0]), self.dptr(A.real.T), self.dptr(A.imag.T)
                c.hist_sr, c.hist_si = self.dptr(np.zeros(f.count)), self.dptr(np.zeros(f.count))
        elif isinstance(f, RandomProcess):
            c.nrand = f.omega.size
            c.rand_amp, c.rand_omega, c.rand_phase = self.dptr(f.amplitude), self.dptr(f.omega), self.dptr(f.phase)
        elif isinstance(f, Harmonic):
            c.force_a, c.force_w, c.force_ph = f.amplitude, two_pi * f.frequency_hz, f.phase
        else:
            raise TypeError(f"a force history {type(f).__name__} has no C implementation")
        laws = model.constraints.laws.laws
        c.implicit_contact = int(implicit_contact and nl > 0)
        if d == 2:
            self.planar(laws)
        else:
            self.scalar(laws)
        n = max(nl, 1)
        c.z, c.v, c.N = self.dptr(np.zeros(n)), self.dptr(np.zeros(n)), self.dptr(np.zeros(n))
        c.Nz, c.Nv, c.tmp = self.dptr(np.zeros(n * d)), self.dptr(np.zeros(n * d)), self.dptr(np.zeros(n))
        c.BtN, c.tmp2 = self.dptr(np.zeros(r)), self.dptr(np.zeros(r))
        c.W, c.NzJ, c.NvJ = self.dptr(np.zeros(n * d)), self.dptr(np.zeros(n * d)), self.dptr(np.zeros(n * d))
        c.L, c.U, c.AinvB = self.dptr(np.zeros(r * r)), self.dptr(np.zeros(r * r)), self.dptr(np.zeros(r * n))
        c.Cap, c.Mcap = self.dptr(np.zeros(n * n)), self.dptr(np.zeros(n * n))
        c.piv, c.lpiv, c.act = self.iptr(np.zeros(n)), self.iptr(np.zeros(r)), self.iptr(np.zeros(n))
        c.am = self.arrow_found = 0 if first else arrow_size(K, D, Mo, Do, Ko)
        c.ad, c.A12 = self.dptr(np.zeros(r)), self.dptr(np.zeros(r * r))
        c.SL, c.SU = self.dptr(np.zeros(r * r)), self.dptr(np.zeros(r * r))
        c.arrow_ok = 0
        ids = np.full(n * n + n, -1, dtype=np.int_)
        self.keep.append(ids)
        c.col_id = <long *><size_t>ids.ctypes.data
        c.cap_id = <long *><size_t>(ids.ctypes.data + n * ids.itemsize)
        sides = np.zeros(n, dtype=np.int8)
        self.keep.append(sides)
        c.sides = <signed char *><size_t>sides.ctypes.data
        c.fact_shift = -1.0
        c.linear_shortcut = 1
        self.prev_arr = np.zeros((4, n))
        c.acc_prev = <PetscReal *><size_t>self.prev_arr.ctypes.data
        self.work_prev_arr = np.zeros(n)
        c.acc_work_prev = <PetscReal *><size_t>self.work_prev_arr.ctypes.data
        self.on_step = self.due = self.recorder = self.record = self.steps = self.commit = None

    def planar(self, laws):
        """The 2-D laws (laws.CircularLaw: circular, flat_bar) as per-support arrays."""
        cdef RomCtx *c = &self.c
        g = lambda name: np.array([float(getattr(l, name)) for l in laws], dtype=float)
        c.pl_gap, c.pl_k = self.dptr(g("clearance")), self.dptr(g("k"))
        c.pl_mu, c.pl_vreg = self.dptr(g("mu")), self.dptr(g("v_reg"))
        c.pl_c, c.pl_alpha = self.dptr(g("c")), self.dptr(g("alpha"))
        angle = np.radians(g("angle"))
        c.pl_e = self.dptr(np.column_stack((np.cos(angle), np.sin(angle))))   # as laws.PlanarLaws
        flat = np.array([l.kind == "flat_bar" for l in laws], dtype=np.intc)
        self.keep.append(flat)
        c.pl_flat = <int *><size_t>flat.ctypes.data if flat.size else NULL
        c.damped = int(any(l.c > 0 or l.alpha > 0 for l in laws))
        c.has_nv = int(c.damped or any(l.mu > 0 for l in laws))
        c.pwlinear = 0

    def scalar(self, laws):
        """The 1-D laws (laws.Law) as per-constraint arrays, by family as laws.ConstraintLaws."""
        cdef RomCtx *c = &self.c
        kinds = np.array([LAW_CODE[l.kind] for l in laws], dtype=np.intc)
        self.keep.append(kinds)
        c.kind = <int *><size_t>kinds.ctypes.data if kinds.size else NULL
        g = lambda name: np.array([float(getattr(l, name)) for l in laws], dtype=float)
        pm, pp, km, kp = g("exponent_minus"), g("exponent_plus"), g("k_minus"), g("k_plus")
        c.em, c.ep, c.km, c.kp = self.dptr(-g("clearance_minus")), self.dptr(g("clearance_plus")), self.dptr(km), self.dptr(kp)
        c.pm1, c.pp1, c.km_pm, c.kp_pp = self.dptr(pm - 1.0), self.dptr(pp - 1.0), self.dptr(km * pm), self.dptr(kp * pp)
        c.k3, c.c, c.alpha = self.dptr(g("k3")), self.dptr(g("c")), self.dptr(g("alpha"))
        two = [l for l in laws if LAW_CODE[l.kind] == 0]
        c.two_linear = int(all(l.exponent_minus == 1 and l.exponent_plus == 1 for l in two))
        c.poly_cubic = int(any(l.k3 != 0 for l in laws if LAW_CODE[l.kind] == 1))
        c.damped = int(any(l.c > 0 or l.alpha > 0 for l in laws))
        c.hunt_crossley = int(any(l.alpha > 0 for l in laws))
        # affine on each side (the linear shortcut): deadband-like with p = 1, linear; no or linear damping
        c.pwlinear = int(all((LAW_CODE[l.kind] == 0 and l.exponent_minus == 1 and l.exponent_plus == 1)
                             or l.kind == "linear" for l in laws) and not c.hunt_crossley)
        # tables: the slopes of laws._Table (np.diff ratios, the last one repeated)
        offs, ns, tz, tf, tsl = [], [], [], [], []
        for l in laws:
            offs.append(len(tz))
            if l.kind == "table":
                pts = np.array(l.table, dtype=float)
                m = len(pts)
                sl = np.empty(m)
                sl[:m - 1] = np.diff(pts[:, 1]) / np.diff(pts[:, 0])
                sl[m - 1] = sl[m - 2]
                tz += list(pts[:, 0]); tf += list(pts[:, 1]); tsl += list(sl); ns.append(len(pts))
            else:
                ns.append(0)
        c.tab_off, c.tab_n = self.iptr(offs), self.iptr(ns)
        c.tab_z, c.tab_f, c.tab_slope = self.dptr(tz), self.dptr(tf), self.dptr(tsl)
        # law = "friction": N = -mu F_n tanh(v / v_reg) (laws.ConstraintLaws._friction)
        c.slip = self.dptr(g("mu") * g("normal_force"))
        c.fvreg = self.dptr(np.array([l.v_reg if l.kind == "friction" else 1.0 for l in laws], dtype=float))
        c.friction = int(any(l.kind == "friction" for l in laws))
        c.has_nv = int(c.damped or c.friction)

    def __dealloc__(self):
        RomDestroy(&self.c)

    # ------------------------------------------------------------ wiring
    def attach(self, TS ts not None, Vec F not None, Vec G not None, Mat J not None, bint shell):
        """IFunction, IJacobian (into the MatShell of shell_matrix(), or a dense matrix), RHSFunction."""
        CHK(RomAttach(&self.c, ts.ts, F.vec, G.vec, J.mat, shell))

    def shell_matrix(self):
        """The Jacobian as a MatShell: MatMult in C, the linearization for the exact solve."""
        cdef Mat A = Mat()
        CHK(RomCreateShellMat(&self.c, &A.mat))
        return A

    def set_pcshell(self, PC pc not None):
        """The exact structured solve as the PC (with KSP preonly: PETSc's Newton with an exact solve)."""
        CHK(RomSetPCShell(&self.c, pc.pc))

    def set_snes_shell(self, SNES snes not None):
        """Newton in C (SNESSHELL) with the exact structured solve."""
        CHK(RomSetSNESShell(&self.c, snes.snes))

    property linear_shortcut:
        def __get__(self):
            return bool(self.c.linear_shortcut)
        def __set__(self, value):
            self.c.linear_shortcut = int(bool(value))

    property next_sample:
        def __get__(self):
            return self.c.next_sample

    property cholesky:
        def __get__(self):
            return bool(self.c.sym_ok)

    property arrow_modes:
        """The diagonal leading rows the stage solve's arrow factor uses (0: the dense factor). Set
        it to False to force the dense factor, to True for the arrow one where the model has it."""
        def __get__(self):
            return int(self.c.am) if self.c.sym_ok else 0
        def __set__(self, value):
            self.c.am = self.arrow_found if value else 0
            self.c.fact_shift = -1.0

    @property
    def counters(self):
        c = self.c
        return dict(snes_solves=c.n_snes, newton=c.n_newton, ifunction=c.n_ifun, ijacobian=c.n_ijac,
                    rhsfunction=c.n_rhs, exact_solves=c.n_apply, factorizations=c.n_fact, matmult=c.n_mult,
                    linear_shortcuts=c.n_shortcut)

    def laws(self, z, v):
        """(N, dN/dz, dN/dv) of the C laws at z, v (to test them against laws.py): flat (N_L d,) values,
        the Jacobians (N_L,) diagonals for d = 1 and (N_L, 2, 2) blocks for d = 2."""
        z = np.ascontiguousarray(z, dtype=float)
        v = np.ascontiguousarray(v, dtype=float)
        if z.shape != (self.c.nl,) or v.shape != (self.c.nl,):
            raise ValueError(f"expected {self.c.nl} values")
        d = self.c.dim
        N = np.zeros(self.c.nl)
        Nz, Nv = (np.zeros(self.c.nl) if d == 1 else np.zeros((self.c.ncon, d, d)) for _ in range(2))
        RomLaws(&self.c, <PetscReal *><size_t>z.ctypes.data, <PetscReal *><size_t>v.ctypes.data,
                <PetscReal *><size_t>N.ctypes.data, <PetscReal *><size_t>Nz.ctypes.data,
                <PetscReal *><size_t>Nv.ctypes.data, 1)
        return N, Nz, Nv

    # ------------------------------------------------------------ the monitor
    def set_monitor(self, TS ts not None, Vec work not None, steps, times, bint dense, record, recorder=None,
                    on_step=None, due=None, commit=None, bint resumed=False, int block=256):
        """Samples at `times` from steps.next on (dense output, or the steps that land on them) and the
        per-step work. With `recorder` (recorder.ReducedRecorder), the samples go to it in blocks of
        `block` rows (recorder.record_rows) and the impact statistics and the peak force accumulate in
        C in its own arrays; without, record(t, q, p) is called at each sample. on_step(ts, t, q, p)
        (it may return a message to stop) is called after every step, or with `due` (a function
        giving the simulated time from which on is it due) only once t >= due(). commit(t, q, p):
        the laws' state, after every step. steps: timestepping.StepMonitor (progress lines, the
        outcome)."""
        cdef RomCtx *c = &self.c
        times = np.ascontiguousarray(times, dtype=float)
        c.sample_t, c.nsample, c.next_sample = self.dptr(times), times.size, steps.next
        c.sample_tol = steps.tol
        c.dense_output = dense
        c.work = work.vec
        self.keep.append(work)
        r, nl = c.r, c.nl
        c.row_len = 1 + 2 * r + 4 * nl + c.nprobe
        c.row_cap = block if recorder is not None else 1
        self.rows_arr = np.zeros((c.row_cap, c.row_len))
        c.rows, c.nrows = <PetscReal *><size_t>self.rows_arr.ctypes.data, 0
        self.record, self.recorder, self.on_step, self.due, self.steps, self.commit = record, recorder, on_step, due, steps, commit
        self.ts = ts
        self.resumed_first = resumed
        self.error = self.stop_message = self.nonfinite = None
        if recorder is not None:
            self.bind_recorder()
        else:   # the samples' peak column, unused
            c.peak = self.dptr(np.zeros(max(nl, 1)))
        CHK(TSMonitorSet(ts.ts, _monitor, <void *>self, NULL))

    cdef bind_recorder(self):
        cdef RomCtx *c = &self.c
        rec = self.recorder
        acc = rec.impacts
        planar = c.dim == 2
        if planar != bool(getattr(acc, "with_work", False)):
            raise TypeError("the recorder's statistics do not match the constraints' dimension")
        arrays = [rec.peak] + [getattr(acc, name) for name in ACCUMULATED]
        for i, a in enumerate(arrays):   # the peak per component, the statistics per support
            if not (isinstance(a, np.ndarray) and a.dtype == np.float64 and a.flags.c_contiguous
                    and a.size == (c.nl if i == 0 else c.ncon)):
                raise TypeError("the recorder's arrays must be float64, contiguous, one value per constraint")
        if planar:
            work = acc.work
            if not (isinstance(work, np.ndarray) and work.dtype == np.float64 and work.flags.c_contiguous
                    and work.size == c.ncon):
                raise TypeError("the recorder's work integral must be float64, contiguous, one value per support")
            self.keep.append(work)
            c.acc_work = <PetscReal *><size_t>work.ctypes.data if work.size else self.dptr(np.zeros(1))
            if acc.work_prev is not None:
                self.work_prev_arr[:c.ncon] = acc.work_prev
        cdef size_t[10] ptrs
        for i, a in enumerate(arrays):
            ptrs[i] = <size_t>a.ctypes.data if a.size else <size_t>self.dptr(np.zeros(1))
        self.keep.append(arrays)
        c.peak = <PetscReal *>ptrs[0]
        c.acc_impacts, c.acc_contact_time, c.acc_run = <PetscReal *>ptrs[1], <PetscReal *>ptrs[2], <PetscReal *>ptrs[3]
        c.acc_duration_max, c.acc_f2, c.acc_z2 = <PetscReal *>ptrs[4], <PetscReal *>ptrs[5], <PetscReal *>ptrs[6]
        c.acc_power, c.acc_force_peak, c.acc_displacement_peak = <PetscReal *>ptrs[7], <PetscReal *>ptrs[8], <PetscReal *>ptrs[9]
        speed = rec.alpha_speed   # Hunt-Crossley's alpha |v| in contact: tracked only where some alpha > 0
        if not (isinstance(speed, np.ndarray) and speed.dtype == np.float64 and speed.flags.c_contiguous
                and speed.size == c.ncon):
            raise TypeError("the recorder's alpha_speed must be float64, contiguous, one value per constraint")
        self.keep.append(speed)
        c.alpha_speed = <PetscReal *><size_t>speed.ctypes.data if (rec.hunt_crossley and speed.size) else NULL
        c.acc_started = acc.prev is not None
        if c.acc_started:
            c.acc_t0, c.acc_t_prev = acc.t0, acc.t_prev
            self.prev_arr[:, :c.ncon] = np.array(acc.prev).reshape(4, c.ncon)

    def sync(self):
        """Hand the samples taken so far and the accumulator's scalars to the Python objects."""
        cdef RomCtx *c = &self.c
        if c.nrows:   # the buffer itself is handed over (the writer keeps views of it): a new one for C
            rows = self.rows_arr[:c.nrows]
            self.rows_arr = np.empty_like(self.rows_arr)
            c.rows, c.nrows = <PetscReal *><size_t>self.rows_arr.ctypes.data, 0
            if self.recorder is not None:
                self.recorder.record_rows(rows)
            else:
                r = c.r
                for row in rows:
                    self.record(float(row[0]), row[1:1 + r].copy(), row[1 + r:1 + 2 * r].copy())
        if self.recorder is not None and c.acc_started:
            acc = self.recorder.impacts
            acc.t0, acc.t_prev = c.acc_t0, c.acc_t_prev
            acc.prev = tuple(self.prev_arr[i, :c.ncon].copy() for i in range(4))
            if c.dim == 2:
                acc.work_prev = self.work_prev_arr[:c.ncon].copy()

    cdef int monitor(self, PetscTS ts, PetscInt step, PetscReal t, PetscVec u) except -1:
        cdef RomCtx *c = &self.c
        cdef const PetscReal *a
        cdef PetscInt taken
        if self.stop_message is not None or self.nonfinite is not None:
            return 0
        CHK(VecGetArrayRead(u, &a))
        try:
            if not RomFinite(c, a):
                self.nonfinite = (step, t)
                TSSetMaxTime(ts, t)
                return 0
            while True:
                CHK(RomTakeSamples(c, ts, t, u, &taken))
                if c.nrows < c.row_cap:
                    break
                self.sync()
            if self.resumed_first:   # the checkpointed step itself: not a new step
                self.resumed_first = False
                return 0
            if self.recorder is not None:
                RomStepStatistics(c, t, a)
            PyErr_CheckSignals()    # Python's signal handlers run here (SIGTERM asks for a checkpoint)
            hook = self.on_step is not None and (self.due is None or t >= self.due())
            if self.commit is not None or hook:   # the state as numpy arrays only when Python needs it
                if c.first:   # (eta, eta'), eta' from the equation (StateSpaceProblem.coordinates)
                    q = np.asarray(<PetscReal[:c.r]>(<PetscReal *>a)).copy()
                    p = np.zeros(c.r)
                    RomRate(c, t, a, c.z, c.v, c.N, <PetscReal *><size_t>p.ctypes.data)
                else:
                    state = np.asarray(<PetscReal[:2 * c.r]>(<PetscReal *>a))
                    q, p = state[:c.r].copy(), state[c.r:].copy()
                if self.commit is not None:
                    self.commit(t, q, p)
                if hook:
                    self.sync()
                    message = self.on_step(self.ts, t, q, p)
                    if message:
                        self.stop_message = message
                        TSSetMaxTime(ts, t)
            self.since_report += 1
            if self.since_report >= 64:
                self.since_report = 0
                self.steps.report(step, t)
        finally:
            VecRestoreArrayRead(u, &a)
        return 0



# --- the Rayleigh-Ritz DBF path's column kernels (ritz_kernels.c; dbf_ritz.RitzSpace.sources) ---

cdef extern from "ritz_kernels.h":
    void ritz_dots(long nloc, long ncol, long n, const double *Phi, long p, const double **V, const long *pos,
                   const double *a, double *c) nogil
    void ritz_subtract(long nloc, long ncol, long n, const double *Phi, long p, const double **V,
                       const long *pos, const double *c, double *a) nogil
    void ritz_combine(long nloc, long ncol, long n, const double *Phi, long p, const double **V,
                      const long *pos, const double *y, long width, double *out) nogil
    void ritz_check_sums(long nloc, long ncol, const double *X, const double *D, const double *MX,
                         const double *MD, const double *KX, const double *KD, const double *lam,
                         const double *k, const double *gx, const double *gd, const long *grow,
                         const double *ramp, double *sums) nogil

from libc.stdlib cimport malloc, free


cdef class _Columns:
    """The modes (n x n_local, row-major), the Krylov steps' blocks (n_local x columns, column-major)
    as C pointers, and pos (steps x ncol): column j's position in each step's block (-1: none)."""
    cdef const double **blocks
    cdef const double *phi
    cdef const long *pos
    cdef long n, nloc, p, ncol
    cdef list keep

    def __cinit__(self, Phi, list blocks, pos, long nloc, long ncol):
        Phi = np.ascontiguousarray(Phi, dtype=np.float64)
        pos = np.ascontiguousarray(pos, dtype=np.int_).reshape(len(blocks), ncol)
        self.keep = [Phi, pos]
        self.n, self.nloc, self.p, self.ncol = Phi.shape[0], nloc, len(blocks), ncol
        if Phi.shape[1] != nloc:
            raise ValueError("the modes' local rows differ from the columns'")
        self.blocks = <const double **> malloc((self.p + 1) * sizeof(double *))
        cdef double[:, ::1] phi = Phi
        cdef long[:, ::1] ps = pos
        self.phi = &phi[0, 0] if Phi.size else NULL
        self.pos = &ps[0, 0] if pos.size else NULL
        cdef double[::1, :] b
        for i, block in enumerate(blocks):
            if not block.flags.f_contiguous or block.dtype != np.float64 or block.shape[0] != nloc:
                raise ValueError("a Krylov block is not n_local x columns, column-major, float64")
            b = block
            self.keep.append(block)
            self.blocks[i] = &b[0, 0] if block.size else NULL

    def __dealloc__(self):
        free(self.blocks)


cdef double *_fortran(a, long nloc, long ncol) except NULL:
    if a.shape != (nloc, ncol) or not a.flags.f_contiguous or a.dtype != np.float64:
        raise ValueError("expected an n_local x columns column-major float64 block")
    cdef double[::1, :] v = a
    return &v[0, 0]


def ritz_columns_dots(Phi, list blocks, pos, a):
    """c = [Phi a_j; V_k(j) . a_j] per column j of a (ritz_kernels.h: ritz_dots); local sums."""
    cdef long nloc = a.shape[0], ncol = a.shape[1]
    cdef _Columns cols = _Columns(Phi, blocks, pos, nloc, ncol)
    c = np.zeros((cols.n + cols.p, ncol))
    if nloc == 0 or ncol == 0:
        return c
    cdef double[:, ::1] cv = c
    cdef double *ap = _fortran(a, nloc, ncol)
    with nogil:
        ritz_dots(nloc, ncol, cols.n, cols.phi, cols.p, cols.blocks, cols.pos, ap, &cv[0, 0])
    return c


def ritz_columns_subtract(Phi, list blocks, pos, c, a):
    """a_j -= Phi^T c[:n, j] + sum_k V_k(j) c[n + k, j] in place (ritz_kernels.h: ritz_subtract)."""
    cdef long nloc = a.shape[0], ncol = a.shape[1]
    cdef _Columns cols = _Columns(Phi, blocks, pos, nloc, ncol)
    if nloc == 0 or ncol == 0:
        return
    c = np.ascontiguousarray(c, dtype=np.float64)
    if c.shape != (cols.n + cols.p, ncol):
        raise ValueError("the coefficients are not (modes + steps) x columns")
    cdef double[:, ::1] cv = c
    cdef double *ap = _fortran(a, nloc, ncol)
    with nogil:
        ritz_subtract(nloc, ncol, cols.n, cols.phi, cols.p, cols.blocks, cols.pos, &cv[0, 0], ap)


def ritz_columns_combine(Phi, list blocks, pos, y):
    """out_j = Phi^T y[j, :n] + sum_k V_k(j) y[j, n + k]: n_local x rows(y), column-major
    (ritz_kernels.h: ritz_combine)."""
    cdef long nloc = Phi.shape[1], ncol = y.shape[0]
    cdef _Columns cols = _Columns(Phi, blocks, pos, nloc, ncol)
    out = np.zeros((nloc, ncol), order="F")
    if nloc == 0 or ncol == 0:
        return out
    y = np.ascontiguousarray(y, dtype=np.float64)
    if y.shape[1] < cols.n + cols.p:
        raise ValueError("y has fewer columns than modes + steps")
    cdef double[:, ::1] yv = y
    cdef double *op = _fortran(out, nloc, ncol)
    with nogil:
        ritz_combine(nloc, ncol, cols.n, cols.phi, cols.p, cols.blocks, cols.pos, &yv[0, 0], yv.shape[1], op)
    return out


def ritz_columns_check_sums(X, D, MX, MD, KX, KD, lam, k, gx, gd, grow, ramp):
    """The 7 x columns local sums of RitzSpace.sources' checks (ritz_kernels.h: ritz_check_sums)."""
    cdef long nloc = X.shape[0], ncol = X.shape[1]
    sums = np.zeros((7, ncol))
    if nloc == 0 or ncol == 0:
        return sums
    cdef double *xp = _fortran(X, nloc, ncol)
    cdef double *dp = _fortran(D, nloc, ncol)
    cdef double *mxp = _fortran(MX, nloc, ncol)
    cdef double *mdp = _fortran(MD, nloc, ncol)
    cdef double *kxp = _fortran(KX, nloc, ncol)
    cdef double *kdp = _fortran(KD, nloc, ncol)
    cdef double[::1] lv = np.ascontiguousarray(lam, dtype=np.float64)
    cdef double[::1] kv = np.ascontiguousarray(k, dtype=np.float64)
    cdef double[::1] gxv = np.ascontiguousarray(gx, dtype=np.float64)
    cdef double[::1] gdv = np.ascontiguousarray(gd, dtype=np.float64)
    cdef long[::1] gr = np.ascontiguousarray(grow, dtype=np.int_)
    cdef double[::1] rp = np.ascontiguousarray(ramp, dtype=np.float64)
    if lv.shape[0] != ncol or kv.shape[0] != ncol or gxv.shape[0] != ncol or gdv.shape[0] != ncol \
            or gr.shape[0] != ncol or rp.shape[0] != nloc:
        raise ValueError("lam, k, gx, gd, grow need one entry per column, ramp one per local row")
    cdef double[:, ::1] sv = sums
    with nogil:
        ritz_check_sums(nloc, ncol, xp, dp, mxp, mdp, kxp, kdp, &lv[0], &kv[0], &gxv[0], &gdv[0], &gr[0],
                        &rp[0], &sv[0, 0])
    return sums
