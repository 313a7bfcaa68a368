/* The reduced model's TS callbacks in C (dbf_hpc issue 15; docs/design.md "The reduced integrator's
 * fast path"). The equations are rom_integrator.py's, with M_r^-1 applied once in Python:
 *
 *   y = [q, p] (2r),  F(t, y, y') = [q' - p ; p' + D p + K q - Bt^T N(z, v)],  G(t, y) = [0 ; f(t)]
 *   z = B q + r_c Omega(t),  v = B p + r_c Omega'(t),  f(t) = force_shape F(t) - base_load Omega''(t)
 *
 * B and Bt are N_L d x r, row-major: B's rows are the basis at the constraints' components, Bt's
 * rows those of M_r^-1 B^T (the same array when M_r = I). K and D are r x r row-major (M_r^-1 applied).
 * Constraints of d = 2 directions (laws.PlanarLaws: circular, flat_bar) have d x d Jacobian blocks,
 * stored row-major per constraint (Nz[j d^2 + a d + b]); nl counts the components (N_L d).
 * f(t) is force_shape F(t) for one load shape, or force_shape X(t) for a load matrix (turbulence:
 * force_shape r x m row-major, X_m(t) = sum_k amp_mk cos(omega_mk t + phase_mk), excitation.CorrelatedProcess).
 */
#ifndef DBF_ROM_CORE_H
#define DBF_ROM_CORE_H
#include <petscts.h>

enum { LAW_TWO_SIDED = 0, LAW_POLY = 1, LAW_TABLE = 2, LAW_FRICTION = 3 };

typedef struct {
  PetscInt r, nl, nprobe;
  PetscInt dim, ncon;                      /* d (1 or 2) and N_L = nl / d */
  PetscReal *K, *D, *B, *Bt, *BT;         /* r*r, r*r, nl*r, nl*r, r*nl (B^T row-major) */
  PetscReal *BvT;                         /* r*nl: the rows giving v (B^T, the same array, in the second-order form) */
  /* first = 1: the state-space form of a gyroscopic structure (state_space.py): y = eta (r states),
     F = eta' + K eta - Bt^T N(z, v), z = B eta + r_c Omega, v = Bv eta + r_c Omega', G = f(t); K = A_r^-1 B_r,
     Bt = (A_r^-1 B_v^T)^T, D unused. The stage Jacobian shift I + K - Bt^T (N_z B + N_v Bv) is formed
     densely (Jd, row-major) and factored by LU (Jlu, jpiv) at an IJacobian whose shift or law
     linearization (N_z, N_v blocks) differs from the last factored one (fact_shift, jNz, jNv; jlu_ok). */
  int first, jlu_ok; PetscReal *Bv, *Jd, *Jlu, *jNz, *jNv; PetscInt *jpiv;
  PetscReal *KT, *DT;                     /* K^T, D^T row-major (column access for the matrix-vector products) */
  /* the stage solve works on the model's own M_r, D = C_r + G_r, K_r (symmetric for a symmetric structure) */
  PetscReal *Mo, *Do, *Ko, *MoT, *DoT;     /* r*r each; MoT, DoT transposed (column access) */
  PetscReal *Ms, *Ds, *Ks; int sym_ok, m_identity; /* their symmetric parts; sym_ok: symmetric to round-off (Cholesky); M_r = I exactly */
  PetscReal *rc, *base_load, *force_shape; /* nl, r, r */
  PetscReal *probe_B, *probe_r;            /* nprobe*r, nprobe */
  int d_zero;                              /* D == 0 exactly */
  int d_diag, do_diag;                     /* D, resp. the model's own D (Do), diagonal exactly (modal damping) */
  /* excitation: Omega = sup_a sin(sup_w t + sup_ph); F = force_a sin(force_w t + force_ph), or the random sum */
  PetscReal sup_a, sup_w, sup_ph, force_a, force_w, force_ph;
  PetscInt nrand; PetscReal *rand_amp, *rand_omega, *rand_phase;
  PetscInt nhist, nterm; PetscReal *hist_amp, *hist_omega, *hist_phase, *X;  /* load matrix: m histories of nterm cosines */
  /* equally spaced frequencies omega_mk = w0_m + k dw (excitation.CorrelatedProcess): X_m = Re(e^{i w0_m t} sum_k A_mk e^{i k dw t}),
     A_mk = amp_mk e^{i phase_mk}, the sum by Horner's rule in e^{i dw t} (one complex multiply-add a term, not a cosine) */
  int hist_horner; PetscReal hist_dw, *hist_w0, *hist_re, *hist_im, *hist_sr, *hist_si;  /* re, im: K x m (k-major) */
  /* laws (laws.py's families, the same evaluation order) */
  int implicit_contact, damped, hunt_crossley, poly_cubic, two_linear, pwlinear;
  int *kind;
  PetscReal *em, *ep, *km, *kp, *pm1, *pp1, *km_pm, *kp_pp, *k3, *c, *alpha;
  PetscInt *tab_off, *tab_n; PetscReal *tab_z, *tab_f, *tab_slope;
  int friction, has_nv; PetscReal *slip, *fvreg;   /* law = "friction": slip = mu F_n; has_nv: some dN/dv != 0 */
  /* 2-D laws (laws.PlanarLaws), per constraint: gap, k, mu, v_reg, c, alpha, the flats' normal e (2 each), flat or round */
  PetscReal *pl_gap, *pl_k, *pl_mu, *pl_vreg, *pl_c, *pl_alpha, *pl_e; int *pl_flat;
  /* work */
  PetscReal *z, *v, *N, *Nz, *Nv, *BtN, *tmp, *tmp2;
  /* linearization at the last IJacobian: W = Nz + shift Nv, Nv, Nz, the side of each constraint */
  PetscReal shift, lin_t, *W, *NzJ, *NvJ; signed char *sides;
  /* the exact structured solve: A(shift) = shift^2 I + shift D + K factored once per shift */
  PetscReal fact_shift, *L, *U, *AinvB, *Cap, *Mcap; PetscInt *piv, *lpiv, *act, nact; int chol_ok;
  long fact_id, *col_id, *cap_id;
  /* the arrow structure (reductor._clean_projection): the leading am x am blocks of K, D (and of M_r,
     K_r, C_r) are diagonal, so A(shift) is a diagonal mode block bordered by l = r - am enrichment
     columns; factored as ad (am) and the Cholesky of the l x l Schur complement (SL, SU), A12 the
     border (am x l, row-major). am = 0: dense. arrow_ok: the current factor is the arrow one. */
  PetscInt am; PetscReal *ad, *A12, *SL, *SU; int arrow_ok;
  int linear_shortcut;
  Vec snes_dy;
  /* counters */
  long n_snes, n_newton, n_ifun, n_ijac, n_rhs, n_apply, n_fact, n_mult, n_shortcut;
  /* the recorder's state, in place in its numpy arrays (recorder.py, stats.ImpactAccumulator) */
  PetscReal *peak;                                        /* nl: signed largest |N| since the last sample */
  PetscReal *acc_impacts, *acc_contact_time, *acc_run, *acc_duration_max, *acc_f2, *acc_z2, *acc_power,
            *acc_force_peak, *acc_displacement_peak, *acc_prev;  /* nl each; prev 4*nl */
  PetscReal acc_t0, acc_t_prev; int acc_started;
  PetscReal *acc_work, *acc_work_prev;                    /* N_L each, d = 2: the work-rate integral and its last point */
  PetscReal *alpha_speed;                                 /* N_L (supports): the largest alpha |v| (|v.n|) in contact, or NULL */
  /* samples: times, the next one, rows [t, q, p, z, v, N, peak, probe] buffered for Python */
  PetscReal *sample_t, sample_tol; PetscInt nsample, next_sample; int dense_output;
  PetscReal *rows; PetscInt row_len, row_cap, nrows;
  Vec work;
} RomCtx;

PetscErrorCode RomIFunction(TS, PetscReal, Vec, Vec, Vec, void *);
PetscErrorCode RomIJacobianDense(TS, PetscReal, Vec, Vec, PetscReal, Mat, Mat, void *);
PetscErrorCode RomIJacobianShell(TS, PetscReal, Vec, Vec, PetscReal, Mat, Mat, void *);
PetscErrorCode RomRHSFunction(TS, PetscReal, Vec, Vec, void *);

void RomLaws(RomCtx *, const PetscReal *z, const PetscReal *v, PetscReal *N, PetscReal *Nz, PetscReal *Nv, int want_jac);
PetscErrorCode RomApplyInverse(RomCtx *, Vec X, Vec Y);

/* monitor pieces (the Cython monitor calls them; Python only for what Python must do) */
int RomFinite(RomCtx *, const PetscReal *u);
PetscErrorCode RomTakeSamples(RomCtx *, TS, PetscReal t, Vec U, PetscInt *taken);
void RomStepStatistics(RomCtx *, PetscReal t, const PetscReal *u);
void RomForcing(RomCtx *, PetscReal t, PetscReal *g);
void RomRate(RomCtx *, PetscReal t, const PetscReal *q, PetscReal *z, PetscReal *v, PetscReal *N, PetscReal *out);

/* wiring */
PetscErrorCode RomAttach(RomCtx *, TS, Vec F, Vec G, Mat J, int shell);
PetscErrorCode RomCreateShellMat(RomCtx *, Mat *);
PetscErrorCode RomSetPCShell(RomCtx *, PC);
PetscErrorCode RomSetSNESShell(RomCtx *, SNES);
PetscErrorCode RomDestroy(RomCtx *);
#endif
