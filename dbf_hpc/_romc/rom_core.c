/* The reduced model's TS callbacks in C: see rom_core.h, and rom_integrator.py for the readable
 * reference (Python) implementation of the same equations. The laws follow laws.py operation by
 * operation, so that they give the same bits. */
#include <math.h>
#include <string.h>
#include "rom_core.h"

/* ---------------------------------------------------------------- excitation (excitation.Harmonic, RandomProcess) */
static inline PetscReal omega_(const RomCtx *c, PetscReal t) { return c->sup_a * sin(c->sup_w * t + c->sup_ph); }
static inline PetscReal omega_rate(const RomCtx *c, PetscReal t) { return c->sup_a * c->sup_w * cos(c->sup_w * t + c->sup_ph); }
static inline PetscReal omega_acc(const RomCtx *c, PetscReal t)
{
  const PetscReal w = c->sup_w;
  return -c->sup_a * w * w * sin(w * t + c->sup_ph);
}
static inline PetscReal force_value(const RomCtx *c, PetscReal t)
{
  if (c->nrand) {
    PetscReal s = 0.0;
    for (PetscInt i = 0; i < c->nrand; i++) s += cos(t * c->rand_omega[i] + c->rand_phase[i]) * c->rand_amp[i];
    return s;
  }
  return c->force_a * sin(c->force_w * t + c->force_ph);
}

/* g = f(t) (r values): force_shape F(t) - base_load Omega''(t), or with a load matrix force_shape X(t)
   - base_load Omega''(t), X(t) as excitation.CorrelatedProcess.value (each term cos(omega t + phase) amp) */
void RomForcing(RomCtx *c, PetscReal t, PetscReal *g)
{
  const PetscInt r = c->r;
  const PetscReal acc = omega_acc(c, t);
  if (c->nhist && c->hist_horner) {
    const PetscInt m = c->nhist, K = c->nterm;
    const PetscReal zr = cos(c->hist_dw * t), zi = sin(c->hist_dw * t);
    PetscReal *sr = c->hist_sr, *si = c->hist_si;
    /* the histories side by side (A stored k-major): independent Horner chains, vectorized over h */
    for (PetscInt h = 0; h < m; h++) { sr[h] = c->hist_re[(K - 1) * m + h]; si[h] = c->hist_im[(K - 1) * m + h]; }
    for (PetscInt k = K - 2; k >= 0; k--) {
      const PetscReal *ar = c->hist_re + k * m, *ai = c->hist_im + k * m;
      for (PetscInt h = 0; h < m; h++) {
        const PetscReal tr = sr[h] * zr - si[h] * zi + ar[h];
        si[h] = sr[h] * zi + si[h] * zr + ai[h];
        sr[h] = tr;
      }
    }
    for (PetscInt h = 0; h < m; h++) {
      const PetscReal wt = c->hist_w0[h] * t;
      c->X[h] = cos(wt) * sr[h] - sin(wt) * si[h];
    }
  } else if (c->nhist) {
    const PetscInt m = c->nhist, K = c->nterm;
    for (PetscInt h = 0; h < m; h++) {
      const PetscReal *a = c->hist_amp + h * K, *w = c->hist_omega + h * K, *ph = c->hist_phase + h * K;
      PetscReal x = 0.0;
      for (PetscInt k = 0; k < K; k++) x += a[k] * cos(w[k] * t + ph[k]);
      c->X[h] = x;
    }
  }
  if (c->nhist) {
    const PetscInt m = c->nhist;
    for (PetscInt i = 0; i < r; i++) {
      const PetscReal *row = c->force_shape + i * m;
      PetscReal s = 0.0;
      for (PetscInt h = 0; h < m; h++) s += row[h] * c->X[h];
      g[i] = s - c->base_load[i] * acc;
    }
    return;
  }
  const PetscReal F = force_value(c, t);
  for (PetscInt i = 0; i < r; i++) g[i] = c->force_shape[i] * F - c->base_load[i] * acc;
}

/* ---------------------------------------------------------------- 2-D laws (laws.PlanarLaws.force_and_jacobian) */
/* The gap coordinate of support j at u: r = |u|, n = u / |u| in a round hole (n = (1, 0) at u = 0), r = |u.e|,
   n = sign(u.e) e between flat bars; *curved = 1 (dn/du = t t^T / r) or 0 (flat) */
static inline void gap_coordinate(const RomCtx *c, PetscInt j, const PetscReal *u, PetscReal *r, PetscReal *n, PetscReal *curved)
{
  if (c->pl_flat[j]) {
    const PetscReal *e = c->pl_e + 2 * j, along = u[0] * e[0] + u[1] * e[1], side = along < 0 ? -1.0 : 1.0;
    *r = fabs(along); n[0] = side * e[0]; n[1] = side * e[1]; *curved = 0.0;
  } else {
    const PetscReal rr = hypot(u[0], u[1]);
    *r = rr; *curved = 1.0;
    if (rr > 0) { n[0] = u[0] / rr; n[1] = u[1] / rr; } else { n[0] = 1.0; n[1] = 0.0; }
  }
}

/* F = -(k delta + (c + alpha k delta) v_n) n - mu k delta tanh(v_t / v_reg) t in contact (delta = r - gap > 0),
   with its exact 2 x 2 derivatives dF/du, dF/dv (row-major blocks) */
static void planar_laws(RomCtx *c, const PetscReal *z, const PetscReal *v, PetscReal *N, PetscReal *Nz, PetscReal *Nv, int want_jac)
{
  for (PetscInt j = 0; j < c->ncon; j++) {
    const PetscReal *u = z + 2 * j, *w = v + 2 * j;
    PetscReal r, n[2], curved;
    gap_coordinate(c, j, u, &r, n, &curved);
    const int contact = r > c->pl_gap[j];
    const PetscReal t0 = -n[1], t1 = n[0];
    const PetscReal vn = w[0] * n[0] + w[1] * n[1], vt = w[0] * t0 + w[1] * t1;
    const PetscReal delta = contact ? r - c->pl_gap[j] : 0.0, on = contact ? 1.0 : 0.0;
    const PetscReal k = c->pl_k[j], inv_r = on * (curved / (r > 0 ? r : 1.0));
    const PetscReal cd = on * (c->pl_c[j] + c->pl_alpha[j] * k * delta);
    const PetscReal tau = tanh(vt / c->pl_vreg[j]), mk = c->pl_mu[j] * k;
    const PetscReal normal = k * delta + cd * vn, tangent = mk * delta * tau;
    N[2 * j] = -(normal * n[0]) - tangent * t0;
    N[2 * j + 1] = -(normal * n[1]) - tangent * t1;
    if (!want_jac) continue;
    const PetscReal dtau = (1.0 - tau * tau) / c->pl_vreg[j];
    /* coefficients of n n^T, t t^T, n t^T, t n^T in dF/du and dF/dv */
    const PetscReal znn = -k * on - on * c->pl_alpha[j] * k * vn;
    const PetscReal ztt = -(k * delta * inv_r) - cd * vn * inv_r + mk * delta * dtau * vn * inv_r;
    const PetscReal znt = -(cd * vt * inv_r) + mk * delta * tau * inv_r;
    const PetscReal ztn = -(mk * on * tau);
    const PetscReal vnn = -cd, vtt = -(mk * delta * dtau);
    const PetscReal nv[2] = {n[0], n[1]}, tv[2] = {t0, t1};
    PetscReal *bz = Nz + 4 * j, *bv = Nv + 4 * j;
    for (int a = 0; a < 2; a++)
      for (int b = 0; b < 2; b++) {
        bz[2 * a + b] = znn * nv[a] * nv[b] + ztt * tv[a] * tv[b] + znt * nv[a] * tv[b] + ztn * tv[a] * nv[b];
        bv[2 * a + b] = vnn * nv[a] * nv[b] + vtt * tv[a] * tv[b];
      }
  }
}

/* ---------------------------------------------------------------- laws (laws.ConstraintLaws.force_and_jacobian) */
void RomLaws(RomCtx *c, const PetscReal *z, const PetscReal *v, PetscReal *N, PetscReal *Nz, PetscReal *Nv, int want_jac)
{
  if (c->dim == 2) { planar_laws(c, z, v, N, Nz, Nv, want_jac); return; }
  for (PetscInt j = 0; j < c->nl; j++) {
    PetscReal force, dz, mag = 0, dmag = 0;
    int contact = 0;
    const PetscReal zj = z[j];
    switch (c->kind[j]) {
    case LAW_TWO_SIDED: {
      PetscReal xm = c->em[j] - zj, xp = zj - c->ep[j];
      if (!(xm > 0.0)) xm = 0.0;
      if (!(xp > 0.0)) xp = 0.0;
      const double on_m = xm > 0.0, on_p = xp > 0.0;
      PetscReal fm, fp, gm, gp;
      if (c->two_linear) {
        fm = c->km[j] * xm; fp = c->kp[j] * xp; gm = c->km[j] * on_m; gp = c->kp[j] * on_p;
      } else {
        const PetscReal tm = pow(xm, c->pm1[j]), tp = pow(xp, c->pp1[j]);
        fm = c->km[j] * xm * tm; fp = c->kp[j] * xp * tp;
        gm = c->km_pm[j] * tm * on_m; gp = c->kp_pp[j] * tp * on_p;
      }
      force = fm - fp; dz = -(gm + gp); mag = fm + fp; dmag = gp - gm;
      contact = (on_m && c->km[j] > 0) || (on_p && c->kp[j] > 0);
    } break;
    case LAW_POLY: {
      PetscReal stiff, slope;
      if (c->poly_cubic) {
        const PetscReal z2 = zj * zj;
        stiff = c->kp[j] + c->k3[j] * z2; slope = c->kp[j] + 3.0 * c->k3[j] * z2;
      } else stiff = slope = c->kp[j];
      force = -stiff * zj; dz = -slope; mag = fabs(force);
      dmag = (zj > 0 ? 1.0 : (zj < 0 ? -1.0 : 0.0)) * slope; contact = 1;
    } break;
    default: { /* LAW_TABLE */
      const PetscReal *tz = c->tab_z + c->tab_off[j], *tf = c->tab_f + c->tab_off[j], *tsl = c->tab_slope + c->tab_off[j];
      const PetscInt n = c->tab_n[j];
      PetscInt count = 0;
      for (PetscInt i = 0; i < n; i++) count += tz[i] <= zj;
      PetscInt s = count - 1;
      if (s < 0) s = 0;
      if (s > n - 2) s = n - 2;
      dz = tsl[s]; force = tf[s] + dz * (zj - tz[s]);
      mag = fabs(force); dmag = (force > 0 ? 1.0 : (force < 0 ? -1.0 : 0.0)) * dz; contact = force != 0;
    } break;
    case LAW_FRICTION: /* no force from z: ConstraintLaws adds -mu F_n tanh(v / v_reg) below */
      force = 0.0; dz = 0.0; contact = 1;
      break;
    }
    if (!c->damped) {
      N[j] = force;
      if (want_jac) { Nz[j] = dz; Nv[j] = 0.0; }
      if (c->kind[j] == LAW_FRICTION) goto friction;
      continue;
    }
    PetscReal dv = -c->c[j] * (double)contact;
    if (c->hunt_crossley) {
      const PetscReal a = c->alpha[j] * (double)contact;
      dv -= a * mag;
      dz = dz - a * dmag * v[j];
    }
    N[j] = force + dv * v[j];
    if (want_jac) { Nz[j] = dz; Nv[j] = dv; }
    if (c->kind[j] != LAW_FRICTION) continue;
  friction: {
      const PetscReal th = tanh(v[j] / c->fvreg[j]);
      N[j] += -c->slip[j] * th;
      if (want_jac) Nv[j] += -(c->slip[j] / c->fvreg[j]) * (1.0 - th * th);
    }
  }
}

/* z = B q + r_c Omega, v = B p + r_c Omega' (by columns of B: BT is B^T row-major, vectorized over
   the constraints); the first-order form: q = p = eta, v from its own rows (BvT) */
static inline void constraint_state(const RomCtx *c, PetscReal t, const PetscReal *q, const PetscReal *p, PetscReal *z, PetscReal *v)
{
  const PetscInt r = c->r, nl = c->nl;
  const PetscReal om = omega_(c, t), omd = omega_rate(c, t);
  for (PetscInt j = 0; j < nl; j++) { z[j] = 0.0; v[j] = 0.0; }
  for (PetscInt i = 0; i < r; i++) {
    const PetscReal *b = c->BT + i * nl, *bv = c->BvT + i * nl, qi = q[i], pi = p[i];
    for (PetscInt j = 0; j < nl; j++) { z[j] += b[j] * qi; v[j] += bv[j] * pi; }
  }
  for (PetscInt j = 0; j < nl; j++) { z[j] += c->rc[j] * om; v[j] += c->rc[j] * omd; }
}

/* the velocity part of a state u: p (second-order form, u = [q, p]) or eta itself (first-order form) */
static inline const PetscReal *pstate(const RomCtx *c, const PetscReal *u) { return c->first ? u : u + c->r; }

/* y += A x with A given by its transpose AT (row-major), i.e. column by column: the inner loop is an
   axpy over contiguous memory, which the compiler vectorizes without reordering any sum */
static inline void matvec_add(const PetscReal *AT, PetscInt r, const PetscReal *x, PetscReal *y)
{
  for (PetscInt j = 0; j < r; j++) {
    const PetscReal *col = AT + j * r, xj = x[j];
    for (PetscInt i = 0; i < r; i++) y[i] += col[i] * xj;
  }
}

/* y += A x for an arrow A (c->am > 0: its leading am x am block diagonal), given by AT as above:
   the same sums in the same order as matvec_add without the block's zeros */
static inline void arrow_matvec_add(const PetscReal *AT, PetscInt r, PetscInt am, const PetscReal *x, PetscReal *y)
{
  for (PetscInt j = 0; j < am; j++) {
    const PetscReal *col = AT + j * r, xj = x[j];
    y[j] += col[j] * xj;
    for (PetscInt i = am; i < r; i++) y[i] += col[i] * xj;
  }
  for (PetscInt j = am; j < r; j++) {
    const PetscReal *col = AT + j * r, xj = x[j];
    for (PetscInt i = 0; i < r; i++) y[i] += col[i] * xj;
  }
}
/* y += A x for a diagonal A (given by AT as above): the same sums without the zeros */
static inline void diag_add(const PetscReal *AT, PetscInt r, const PetscReal *x, PetscReal *y)
{
  for (PetscInt i = 0; i < r; i++) y[i] += AT[i * r + i] * x[i];
}
static inline void mv_add(const RomCtx *c, const PetscReal *AT, const PetscReal *x, PetscReal *y)
{
  if (c->am) arrow_matvec_add(AT, c->r, c->am, x, y);
  else matvec_add(AT, c->r, x, y);
}

/* out += sign * Bt^T N */
static inline void add_BtN(const RomCtx *c, const PetscReal *N, PetscReal sign, PetscReal *out)
{
  for (PetscInt j = 0; j < c->nl; j++) {
    const PetscReal *b = c->Bt + j * c->r, nj = sign * N[j];
    for (PetscInt i = 0; i < c->r; i++) out[i] += b[i] * nj;
  }
}

/* the first-order form's rate eta' = -K eta + f(t) + Bt^T N(z, v) at eta = q (state_space.StateSpaceProblem.rate),
   with z, v, N (nl each) at q as by-products */
void RomRate(RomCtx *c, PetscReal t, const PetscReal *q, PetscReal *z, PetscReal *v, PetscReal *N, PetscReal *out)
{
  const PetscInt r = c->r;
  PetscReal *kq = c->tmp2;
  RomForcing(c, t, out);
  for (PetscInt i = 0; i < r; i++) kq[i] = 0.0;
  matvec_add(c->KT, r, q, kq);
  for (PetscInt i = 0; i < r; i++) out[i] = -kq[i] + out[i];
  constraint_state(c, t, q, q, z, v);
  RomLaws(c, z, v, N, NULL, NULL, 0);
  for (PetscInt j = 0; j < c->nl; j++) {
    const PetscReal *b = c->Bt + j * r, nj = N[j];
    for (PetscInt i = 0; i < r; i++) out[i] += b[i] * nj;
  }
}

/* ---------------------------------------------------------------- TS callbacks */
PetscErrorCode RomIFunction(TS ts, PetscReal t, Vec U, Vec Udot, Vec F, void *ctx)
{
  RomCtx *c = (RomCtx *)ctx;
  const PetscReal *u, *ud;
  PetscReal *f;
  const PetscInt r = c->r;
  PetscFunctionBeginUser;
  c->n_ifun++;
  PetscCall(VecGetArrayRead(U, &u));
  PetscCall(VecGetArrayRead(Udot, &ud));
  PetscCall(VecGetArrayWrite(F, &f));
  if (c->first) {   /* F = eta' + K eta - Bt^T N(z, v) */
    for (PetscInt i = 0; i < r; i++) f[i] = ud[i];
    matvec_add(c->KT, r, u, f);
    if (c->implicit_contact) {
      constraint_state(c, t, u, u, c->z, c->v);
      RomLaws(c, c->z, c->v, c->N, NULL, NULL, 0);
      add_BtN(c, c->N, -1.0, f);
    }
    PetscCall(VecRestoreArrayRead(U, &u));
    PetscCall(VecRestoreArrayRead(Udot, &ud));
    PetscCall(VecRestoreArrayWrite(F, &f));
    PetscFunctionReturn(0);
  }
  const PetscReal *q = u, *p = u + r, *qd = ud, *pd = ud + r;
  PetscReal *fq = f, *fp = f + r;
  for (PetscInt i = 0; i < r; i++) { fq[i] = qd[i] - p[i]; fp[i] = pd[i]; }
  if (c->d_diag) { if (!c->d_zero) diag_add(c->DT, r, p, fp); }
  else mv_add(c, c->DT, p, fp);
  mv_add(c, c->KT, q, fp);
  if (c->implicit_contact) {
    constraint_state(c, t, q, p, c->z, c->v);
    RomLaws(c, c->z, c->v, c->N, NULL, NULL, 0);
    add_BtN(c, c->N, -1.0, fp);
  }
  PetscCall(VecRestoreArrayRead(U, &u));
  PetscCall(VecRestoreArrayRead(Udot, &ud));
  PetscCall(VecRestoreArrayWrite(F, &f));
  PetscFunctionReturn(0);
}

PetscErrorCode RomRHSFunction(TS ts, PetscReal t, Vec U, Vec G, void *ctx)
{
  RomCtx *c = (RomCtx *)ctx;
  PetscReal *g;
  const PetscInt r = c->r;
  PetscFunctionBeginUser;
  c->n_rhs++;
  PetscCall(VecGetArrayWrite(G, &g));
  PetscReal *gp = c->first ? g : g + r;   /* the first-order form: G = f(t) on all of eta */
  if (!c->first) for (PetscInt i = 0; i < r; i++) g[i] = 0.0;
  RomForcing(c, t, gp);
  if (!c->implicit_contact && c->nl) {
    const PetscReal *u;
    PetscCall(VecGetArrayRead(U, &u));
    constraint_state(c, t, u, pstate(c, u), c->z, c->v);
    RomLaws(c, c->z, c->v, c->N, NULL, NULL, 0);
    add_BtN(c, c->N, 1.0, gp);
    PetscCall(VecRestoreArrayRead(U, &u));
  }
  PetscCall(VecRestoreArrayWrite(G, &g));
  PetscFunctionReturn(0);
}

/* the side of each two-sided constraint: -1 below, 0 inside, +1 above (the laws' strict inequalities) */
static inline signed char side_of(const RomCtx *c, PetscInt j, PetscReal z)
{
  if (c->kind[j] != LAW_TWO_SIDED) return 0;
  return (c->em[j] - z > 0.0) ? -1 : ((z - c->ep[j] > 0.0) ? 1 : 0);
}

/* the linearization of the laws at (t, U): Nz, Nv, W = Nz + shift Nv, sides */
static PetscErrorCode linearize(RomCtx *c, PetscReal t, Vec U, PetscReal shift)
{
  const PetscReal *u;
  const PetscInt nl = c->nl, nb = c->ncon * c->dim * c->dim;
  PetscFunctionBeginUser;
  c->shift = shift; c->lin_t = t;
  if (!c->implicit_contact) {
    for (PetscInt j = 0; j < nb; j++) c->W[j] = c->NzJ[j] = c->NvJ[j] = 0.0;
    PetscFunctionReturn(0);
  }
  PetscCall(VecGetArrayRead(U, &u));
  constraint_state(c, t, u, pstate(c, u), c->z, c->v);
  PetscCall(VecRestoreArrayRead(U, &u));
  RomLaws(c, c->z, c->v, c->N, c->NzJ, c->NvJ, 1);
  for (PetscInt j = 0; j < nb; j++) c->W[j] = c->NzJ[j] + shift * c->NvJ[j];
  if (c->dim == 1)
    for (PetscInt j = 0; j < nl; j++) c->sides[j] = side_of(c, j, c->z[j]);
  PetscFunctionReturn(0);
}

/* the first-order form's stage Jacobian Jd = shift I + K - Bt^T (N_z B + N_v Bv) (row-major r x r) at the
   last linearization (state_space.StateSpaceProblem.ijacobian) */
static void first_jacobian(RomCtx *c, PetscReal shift)
{
  const PetscInt r = c->r, d = c->dim;
  for (PetscInt i = 0; i < r; i++)
    for (PetscInt j = 0; j < r; j++) {
      PetscReal s = c->K[i * r + j] + (i == j ? shift : 0.0);
      if (c->implicit_contact)
        for (PetscInt l = 0; l < c->ncon; l++)
          for (PetscInt a = 0; a < d; a++) {
            const PetscReal bt = c->Bt[(l * d + a) * r + i];
            if (bt == 0.0) continue;
            PetscReal g = 0.0;
            for (PetscInt b = 0; b < d; b++)
              g += c->NzJ[(l * d + a) * d + b] * c->B[(l * d + b) * r + j] + c->NvJ[(l * d + a) * d + b] * c->Bv[(l * d + b) * r + j];
            s -= bt * g;
          }
      c->Jd[i * r + j] = s;
    }
}

/* the dense 2r x 2r Jacobian, for PETSc's own solvers (callbacks = "c" with a dense matrix) */
PetscErrorCode RomIJacobianDense(TS ts, PetscReal t, Vec U, Vec Udot, PetscReal shift, Mat A, Mat P, void *ctx)
{
  RomCtx *c = (RomCtx *)ctx;
  PetscScalar *a;
  PetscInt lda;
  const PetscInt r = c->r, d = c->dim, n = 2 * r;
  PetscFunctionBeginUser;
  c->n_ijac++;
  PetscCall(linearize(c, t, U, shift));
  PetscCall(MatDenseGetLDA(P, &lda));
  PetscCall(MatDenseGetArrayWrite(P, &a));
  if (c->first) {   /* r x r, column-major */
    first_jacobian(c, shift);
    c->jlu_ok = 0;   /* Jd is no longer the factored matrix */
    for (PetscInt j = 0; j < r; j++)
      for (PetscInt i = 0; i < r; i++) a[i + j * lda] = c->Jd[i * r + j];
  } else {
  for (PetscInt j = 0; j < n; j++) memset(a + j * lda, 0, sizeof(PetscScalar) * n);
  for (PetscInt i = 0; i < r; i++) { a[i + i * lda] = shift; a[i + (r + i) * lda] = -1.0; }
  for (PetscInt j = 0; j < r; j++)
    for (PetscInt i = 0; i < r; i++) {
      PetscReal kz = c->K[i * r + j], dv = c->D[i * r + j] + (i == j ? shift : 0.0);
      for (PetscInt l = 0; l < c->ncon; l++)   /* - Bt^T blockdiag(N_z) B, the d x d block of each constraint */
        for (PetscInt a = 0; a < d; a++)
          for (PetscInt b = 0; b < d; b++) {
            const PetscReal bb = c->Bt[(l * d + a) * r + i] * c->B[(l * d + b) * r + j];
            kz -= bb * c->NzJ[(l * d + a) * d + b];
            dv -= bb * c->NvJ[(l * d + a) * d + b];
          }
      a[(r + i) + j * lda] = kz;
      a[(r + i) + (r + j) * lda] = dv;
    }
  }
  PetscCall(MatDenseRestoreArrayWrite(P, &a));
  PetscCall(MatAssemblyBegin(P, MAT_FINAL_ASSEMBLY));
  PetscCall(MatAssemblyEnd(P, MAT_FINAL_ASSEMBLY));
  if (A != P) {
    PetscCall(MatAssemblyBegin(A, MAT_FINAL_ASSEMBLY));
    PetscCall(MatAssemblyEnd(A, MAT_FINAL_ASSEMBLY));
  }
  PetscFunctionReturn(0);
}

/* ---------------------------------------------------------------- the exact structured solve */
/* Cholesky A = L L^T (right-looking; a holds the lower triangle of A, row-major, and gets L), U = L^T
   row-major; col: work of n. Every inner loop runs over contiguous memory (vectorized axpys). */
static int cholesky(PetscReal *a, PetscReal *U, PetscReal *col, PetscInt n)
{
  for (PetscInt j = 0; j < n; j++) {
    const PetscReal d = a[j * n + j];
    if (!(d > 0)) return 1;
    const PetscReal ljj = sqrt(d), inv = 1.0 / ljj;
    a[j * n + j] = ljj; U[j * n + j] = ljj;
    for (PetscInt i = j + 1; i < n; i++) { const PetscReal l = a[i * n + j] * inv; a[i * n + j] = l; U[j * n + i] = l; }
    for (PetscInt i = j + 1; i < n; i++) col[i] = U[j * n + i];
    for (PetscInt i = j + 1; i < n; i++) {   /* trailing update of row i, columns j+1..i */
      const PetscReal lij = col[i];
      PetscReal *ai = a + i * n;
      for (PetscInt k = j + 1; k <= i; k++) ai[k] -= lij * col[k];
    }
  }
  return 0;
}
/* L L^T x = b in place: forward by columns of L (rows of U), backward by columns of U (rows of L) */
static void chol_solve(const PetscReal *L, const PetscReal *U, PetscInt n, PetscReal *x)
{
  for (PetscInt k = 0; k < n; k++) {
    const PetscReal *uk = U + k * n;
    const PetscReal xk = x[k] / uk[k];
    x[k] = xk;
    for (PetscInt i = k + 1; i < n; i++) x[i] -= uk[i] * xk;
  }
  for (PetscInt k = n - 1; k >= 0; k--) {
    const PetscReal *lk = L + k * n;
    const PetscReal xk = x[k] / lk[k];
    x[k] = xk;
    for (PetscInt i = 0; i < k; i++) x[i] -= lk[i] * xk;
  }
}
static int lu(PetscReal *a, PetscInt n, PetscInt *piv)
{
  for (PetscInt j = 0; j < n; j++) {
    PetscInt p = j;
    PetscReal m = fabs(a[j * n + j]);
    for (PetscInt i = j + 1; i < n; i++) if (fabs(a[i * n + j]) > m) { m = fabs(a[i * n + j]); p = i; }
    piv[j] = p;
    if (m == 0.0) return 1;
    if (p != j) for (PetscInt k = 0; k < n; k++) { PetscReal tmp = a[j * n + k]; a[j * n + k] = a[p * n + k]; a[p * n + k] = tmp; }
    const PetscReal inv = 1.0 / a[j * n + j];
    for (PetscInt i = j + 1; i < n; i++) {
      const PetscReal f = a[i * n + j] * inv;
      a[i * n + j] = f;
      if (f != 0.0) for (PetscInt k = j + 1; k < n; k++) a[i * n + k] -= f * a[j * n + k];
    }
  }
  return 0;
}
static void lu_solve(const PetscReal *a, PetscInt n, const PetscInt *piv, PetscReal *x)
{
  for (PetscInt j = 0; j < n; j++) if (piv[j] != j) { PetscReal tmp = x[j]; x[j] = x[piv[j]]; x[piv[j]] = tmp; }
  for (PetscInt i = 0; i < n; i++) { PetscReal s = x[i]; for (PetscInt k = 0; k < i; k++) s -= a[i * n + k] * x[k]; x[i] = s; }
  for (PetscInt i = n - 1; i >= 0; i--) { PetscReal s = x[i]; for (PetscInt k = i + 1; k < n; k++) s -= a[i * n + k] * x[k]; x[i] = s / a[i * n + i]; }
}
/* A x = b in place for the arrow factor: z2 = S^-1 (b2 - A21 Ad^-1 b1), z1 = Ad^-1 (b1 - A12 z2) */
static void arrow_solve(const RomCtx *c, PetscReal *x)
{
  const PetscInt am = c->am, l = c->r - am;
  PetscReal *x2 = x + am;
  for (PetscInt i = 0; i < am; i++) {
    const PetscReal yi = x[i] / c->ad[i], *a = c->A12 + i * l;
    x[i] = yi;
    for (PetscInt k = 0; k < l; k++) x2[k] -= a[k] * yi;
  }
  chol_solve(c->SL, c->SU, l, x2);
  for (PetscInt i = 0; i < am; i++) {
    const PetscReal *a = c->A12 + i * l;
    PetscReal s = 0.0;
    for (PetscInt k = 0; k < l; k++) s += a[k] * x2[k];
    x[i] -= s / c->ad[i];
  }
}
static inline void solveA(const RomCtx *c, PetscReal *x)
{
  if (c->arrow_ok) arrow_solve(c, x);
  else if (c->chol_ok) chol_solve(c->L, c->U, c->r, x);
  else lu_solve(c->L, c->r, c->lpiv, x);
}

/* the arrow factor of the symmetric parts (see RomCtx.am); 1 if a pivot is not positive */
static int arrow_factor(RomCtx *c, PetscReal shift)
{
  const PetscInt r = c->r, am = c->am, l = r - am;
  const PetscReal s2 = shift * shift;
  for (PetscInt i = 0; i < am; i++) {
    const PetscReal d = c->Ks[i * r + i] + shift * c->Ds[i * r + i] + s2 * c->Ms[i * r + i];
    if (!(d > 0)) return 1;
    c->ad[i] = d;
    PetscReal *a = c->A12 + i * l;
    for (PetscInt k = 0; k < l; k++) {   /* row am + k, column i: the lower triangle of the symmetric parts */
      const PetscInt e = (am + k) * r + i;
      a[k] = c->Ks[e] + shift * c->Ds[e] + s2 * c->Ms[e];
    }
  }
  PetscReal *S = c->SL;
  for (PetscInt k = 0; k < l; k++)
    for (PetscInt m = 0; m <= k; m++) {
      const PetscInt e = (am + k) * r + am + m;
      S[k * l + m] = c->Ks[e] + shift * c->Ds[e] + s2 * c->Ms[e];
    }
  for (PetscInt i = 0; i < am; i++) {   /* S -= A21 Ad^-1 A12, row by row of the border */
    const PetscReal *a = c->A12 + i * l, inv = 1.0 / c->ad[i];
    for (PetscInt k = 0; k < l; k++) {
      const PetscReal f = a[k] * inv;
      PetscReal *Sk = S + k * l;
      for (PetscInt m = 0; m <= k; m++) Sk[m] -= f * a[m];
    }
  }
  return cholesky(S, c->SU, c->tmp2, l);
}

/* A(shift) = shift^2 M + shift D + K with the model's own (symmetric) M_r, D, K: Cholesky of its
   symmetric part when they are symmetric to round-off (sym_ok; Newton's residual removes the
   difference), LU with partial pivoting otherwise or when the Cholesky fails */
static PetscErrorCode factor(RomCtx *c, PetscReal shift)
{
  const PetscInt r = c->r;
  const PetscReal s2 = shift * shift;
  PetscFunctionBeginUser;
  c->n_fact++;
  c->fact_id++;   /* invalidates the cached columns A^-1 B_l^T and capacitance entries */
  c->chol_ok = c->sym_ok;
  c->arrow_ok = c->sym_ok && c->am > 0;
  if (c->arrow_ok && arrow_factor(c, shift)) c->arrow_ok = 0;
  if (c->arrow_ok) {
    c->fact_shift = shift;
    PetscFunctionReturn(0);
  }
  if (c->chol_ok) {
    for (PetscInt i = 0; i < r; i++)
      for (PetscInt j = 0; j <= i; j++) c->L[i * r + j] = c->Ks[i * r + j] + shift * c->Ds[i * r + j] + s2 * c->Ms[i * r + j];
    if (cholesky(c->L, c->U, c->tmp2, r)) c->chol_ok = 0;
  }
  if (!c->chol_ok) {
    for (PetscInt i = 0; i < r; i++)
      for (PetscInt j = 0; j < r; j++) c->L[i * r + j] = c->Ko[i * r + j] + shift * c->Do[i * r + j] + s2 * c->Mo[i * r + j];
    if (lu(c->L, r, c->lpiv)) { c->fact_shift = -1; SETERRQ(PETSC_COMM_SELF, PETSC_ERR_MAT_LU_ZRPVT, "singular shift^2 M + shift D + K"); }
  }
  c->fact_shift = shift;
  PetscFunctionReturn(0);
}

/* column l of A^-1 B^T, once per factorization, only for the constraints that are active */
static inline const PetscReal *ainvbt(RomCtx *c, PetscInt l)
{
  PetscReal *x = c->AinvB + l * c->r;
  if (c->col_id[l] != c->fact_id) {
    for (PetscInt i = 0; i < c->r; i++) x[i] = c->B[l * c->r + i];
    solveA(c, x);
    c->col_id[l] = c->fact_id;
  }
  return x;
}
/* B_l A^-1 B_m^T */
static inline PetscReal cap(RomCtx *c, PetscInt l, PetscInt m)
{
  const PetscInt nl = c->nl;
  if (c->cap_id[l * nl + m] != c->fact_id) {
    const PetscReal *x = ainvbt(c, m), *b = c->B + l * c->r;
    PetscReal s = 0.0;
    for (PetscInt i = 0; i < c->r; i++) s += b[i] * x[i];
    c->Cap[l * nl + m] = s; c->cap_id[l * nl + m] = c->fact_id;
  }
  return c->Cap[l * nl + m];
}

/* The Jacobian as a MatShell (MatMult = RomMatMult); the linearization goes to the exact solve:
   A(shift) factored when the shift changes, and the capacitance I - W_a B_a A^-1 B_a^T of the active
   constraints a = {l : W_l != 0} (N_a d x N_a d, W_a block diagonal with the d x d blocks) by LU. */
PetscErrorCode RomIJacobianShell(TS ts, PetscReal t, Vec U, Vec Udot, PetscReal shift, Mat A, Mat P, void *ctx)
{
  RomCtx *c = (RomCtx *)ctx;
  const PetscInt d = c->dim, dd = d * d;
  PetscInt na = 0;
  PetscFunctionBeginUser;
  c->n_ijac++;
  PetscCall(linearize(c, t, U, shift));
  if (c->first) {   /* the dense stage Jacobian and its LU (the exact solve), unless the last one is this one */
    const PetscInt nb = c->ncon * d * d;
    int same = c->jlu_ok && shift == c->fact_shift;
    for (PetscInt j = 0; j < nb && same; j++) same = c->NzJ[j] == c->jNz[j] && c->NvJ[j] == c->jNv[j];
    if (same) PetscFunctionReturn(0);   /* the same matrix: the same factor, bit for bit */
    c->jlu_ok = 0;
    first_jacobian(c, shift);
    memcpy(c->Jlu, c->Jd, sizeof(PetscReal) * c->r * c->r);
    c->n_fact++;
    if (lu(c->Jlu, c->r, c->jpiv)) SETERRQ(PETSC_COMM_SELF, PETSC_ERR_MAT_LU_ZRPVT, "singular stage Jacobian of the state-space form");
    memcpy(c->jNz, c->NzJ, sizeof(PetscReal) * nb);
    memcpy(c->jNv, c->NvJ, sizeof(PetscReal) * nb);
    c->fact_shift = shift;
    c->jlu_ok = 1;
    PetscFunctionReturn(0);
  }
  if (shift != c->fact_shift) PetscCall(factor(c, shift));
  for (PetscInt j = 0; j < c->ncon; j++) {
    int on = 0;
    for (PetscInt k = 0; k < dd; k++) on |= c->W[j * dd + k] != 0.0;
    if (on) c->act[na++] = j;
  }
  c->nact = na;
  if (na) {
    PetscReal *M = c->Mcap;
    const PetscInt m = na * d;
    for (PetscInt i = 0; i < na; i++)
      for (PetscInt a = 0; a < d; a++) {
        const PetscReal *w = c->W + c->act[i] * dd + a * d;   /* row a of constraint act[i]'s block */
        for (PetscInt j = 0; j < na; j++)
          for (PetscInt b = 0; b < d; b++) {
            PetscReal s = w[0] * cap(c, c->act[i] * d, c->act[j] * d + b);
            for (PetscInt e = 1; e < d; e++) s += w[e] * cap(c, c->act[i] * d + e, c->act[j] * d + b);
            M[(i * d + a) * m + j * d + b] = (i == j && a == b ? 1.0 : 0.0) - s;
          }
      }
    if (lu(M, m, c->piv)) SETERRQ(PETSC_COMM_SELF, PETSC_ERR_MAT_LU_ZRPVT, "singular contact capacitance");
  }
  /* no MatAssembly: the MatShell was assembled once at creation */
  PetscFunctionReturn(0);
}

/* Y = J^-1 X exactly. J = [[s I, -I], [M^-1 (K - B^T N_z B), s I + M^-1 (D - B^T N_v B)]] (the stage
 * Jacobian; M = M_r, D = C_r + G_r, K = K_r the model's own matrices). Multiplied through by M:
 *   dq = S^-1 (M (b + s a) + D a - B^T N_v B a),  S = A(s) - B^T W B,  dp = s dq - a,
 *   A(s) = s^2 M + s D + K,  W = N_z + s N_v,
 *   S^-1 = A^-1 + A^-1 B_a^T (I - W_a B_a A^-1 B_a^T)^-1 W_a B_a A^-1   (Woodbury on the active constraints) */
PetscErrorCode RomApplyInverse(RomCtx *c, Vec X, Vec Y)
{
  const PetscReal *x;
  PetscReal *y;
  const PetscInt r = c->r, na = c->nact, d = c->dim, dd = d * d;
  const PetscReal s = c->shift;
  PetscFunctionBeginUser;
  c->n_apply++;
  PetscCall(VecGetArrayRead(X, &x));
  PetscCall(VecGetArrayWrite(Y, &y));
  if (c->first) {   /* the LU of the last IJacobian */
    memcpy(y, x, sizeof(PetscReal) * r);
    lu_solve(c->Jlu, r, c->jpiv, y);
    PetscCall(VecRestoreArrayRead(X, &x));
    PetscCall(VecRestoreArrayWrite(Y, &y));
    PetscFunctionReturn(0);
  }
  const PetscReal *a = x, *b = x + r;
  PetscReal *dq = y, *dp = y + r, *tmp = c->tmp, *w = c->tmp2;
  if (c->m_identity) for (PetscInt i = 0; i < r; i++) dq[i] = b[i] + s * a[i];
  else {
    for (PetscInt i = 0; i < r; i++) { w[i] = b[i] + s * a[i]; dq[i] = 0.0; }
    mv_add(c, c->MoT, w, dq);
  }
  if (c->do_diag) { if (!c->d_zero) diag_add(c->DoT, r, a, dq); }
  else mv_add(c, c->DoT, a, dq);
  if (c->implicit_contact && c->has_nv) { /* - B^T N_v B a, block by block */
    for (PetscInt l = 0; l < c->ncon; l++) {
      const PetscReal *nv = c->NvJ + l * dd;
      int on = 0;
      for (PetscInt k = 0; k < dd; k++) on |= nv[k] != 0.0;
      if (!on) continue;
      PetscReal ba[2];
      for (PetscInt e = 0; e < d; e++) {
        const PetscReal *bl = c->B + (l * d + e) * r;
        PetscReal sum = 0;
        for (PetscInt i = 0; i < r; i++) sum += bl[i] * a[i];
        ba[e] = sum;
      }
      for (PetscInt e = 0; e < d; e++) {
        const PetscReal *bl = c->B + (l * d + e) * r;
        PetscReal g = ba[0] * nv[e * d];
        for (PetscInt f = 1; f < d; f++) g += nv[e * d + f] * ba[f];
        for (PetscInt i = 0; i < r; i++) dq[i] -= bl[i] * g;
      }
    }
  }
  solveA(c, dq);
  if (c->implicit_contact && na) {
    for (PetscInt i = 0; i < na; i++) {
      PetscReal bq[2];
      for (PetscInt e = 0; e < d; e++) {
        const PetscReal *bl = c->B + (c->act[i] * d + e) * r;
        PetscReal sum = 0;
        for (PetscInt j = 0; j < r; j++) sum += bl[j] * dq[j];
        bq[e] = sum;
      }
      const PetscReal *w = c->W + c->act[i] * dd;
      for (PetscInt e = 0; e < d; e++) {
        PetscReal g = w[e * d] * bq[0];
        for (PetscInt f = 1; f < d; f++) g += w[e * d + f] * bq[f];
        tmp[i * d + e] = g;
      }
    }
    lu_solve(c->Mcap, na * d, c->piv, tmp);
    for (PetscInt i = 0; i < na; i++)
      for (PetscInt e = 0; e < d; e++) {
        const PetscReal *col = ainvbt(c, c->act[i] * d + e), ti = tmp[i * d + e];
        for (PetscInt j = 0; j < r; j++) dq[j] += col[j] * ti;
      }
  }
  for (PetscInt i = 0; i < r; i++) dp[i] = s * dq[i] - a[i];
  PetscCall(VecRestoreArrayRead(X, &x));
  PetscCall(VecRestoreArrayWrite(Y, &y));
  PetscFunctionReturn(0);
}

static PetscErrorCode RomPCApply(PC pc, Vec X, Vec Y)
{
  RomCtx *c;
  PetscFunctionBeginUser;
  PetscCall(PCShellGetContext(pc, &c));
  PetscCall(RomApplyInverse(c, X, Y));
  PetscFunctionReturn(0);
}

/* Y = J X for the MatShell (-snes_test_jacobian, MatComputeOperator, Krylov methods) */
static PetscErrorCode RomMatMult(Mat A, Vec X, Vec Y)
{
  RomCtx *c;
  const PetscReal *x;
  PetscReal *y;
  PetscFunctionBeginUser;
  PetscCall(MatShellGetContext(A, &c));
  const PetscInt r = c->r, d = c->dim;
  const PetscReal s = c->shift;
  c->n_mult++;
  PetscCall(VecGetArrayRead(X, &x));
  PetscCall(VecGetArrayWrite(Y, &y));
  if (c->first) {   /* the dense Jacobian of the last IJacobian */
    for (PetscInt i = 0; i < r; i++) {
      PetscReal v = 0.0;
      for (PetscInt j = 0; j < r; j++) v += c->Jd[i * r + j] * x[j];
      y[i] = v;
    }
    PetscCall(VecRestoreArrayRead(X, &x));
    PetscCall(VecRestoreArrayWrite(Y, &y));
    PetscFunctionReturn(0);
  }
  const PetscReal *a = x, *b = x + r;
  PetscReal *yq = y, *yp = y + r;
  for (PetscInt i = 0; i < r; i++) {
    PetscReal v = s * b[i];
    for (PetscInt j = 0; j < r; j++) v += c->K[i * r + j] * a[j] + c->D[i * r + j] * b[j];
    yq[i] = s * a[i] - b[i];
    yp[i] = v;
  }
  for (PetscInt l = 0; l < c->ncon; l++) {
    PetscReal ba[2], bb[2];
    for (PetscInt e = 0; e < d; e++) {
      const PetscReal *bl = c->B + (l * d + e) * r;
      ba[e] = 0; bb[e] = 0;
      for (PetscInt i = 0; i < r; i++) { ba[e] += bl[i] * a[i]; bb[e] += bl[i] * b[i]; }
    }
    for (PetscInt e = 0; e < d; e++) {
      const PetscReal *nz = c->NzJ + (l * d + e) * d, *nv = c->NvJ + (l * d + e) * d, *btl = c->Bt + (l * d + e) * r;
      PetscReal g = nz[0] * ba[0] + nv[0] * bb[0];
      for (PetscInt f = 1; f < d; f++) g += nz[f] * ba[f] + nv[f] * bb[f];
      for (PetscInt i = 0; i < r; i++) yp[i] -= btl[i] * g;
    }
  }
  PetscCall(VecRestoreArrayRead(X, &x));
  PetscCall(VecRestoreArrayWrite(Y, &y));
  PetscFunctionReturn(0);
}

/* does every two-sided constraint lie on the side it had at the linearization? */
static PetscErrorCode same_sides(RomCtx *c, Vec U, PetscBool *same)
{
  const PetscReal *u;
  const PetscInt r = c->r;
  PetscFunctionBeginUser;
  *same = PETSC_TRUE;
  PetscCall(VecGetArrayRead(U, &u));
  const PetscReal om = omega_(c, c->lin_t);
  for (PetscInt j = 0; j < c->nl; j++) {
    const PetscReal *b = c->B + j * r;
    PetscReal s = 0.0;
    for (PetscInt i = 0; i < r; i++) s += b[i] * u[i];
    if (side_of(c, j, s + c->rc[j] * om) != c->sides[j]) { *same = PETSC_FALSE; break; }
  }
  PetscCall(VecRestoreArrayRead(U, &u));
  PetscFunctionReturn(0);
}

/* Newton on the stage equations without SNESComputeJacobian/KSPSolve (their per-call options queries
 * cost more than the arithmetic at this size): NEWTONLS with a full step (line search basic), KSPPREONLY
 * and the exact inverse, SNESConvergedDefault with the SNES's tolerances. With piecewise-linear laws
 * (deadband p = 1, linear; no or linear contact damping), an iterate on which no constraint changed side
 * solved the stage equation exactly (it is linear there): the residual check is skipped. */
static PetscErrorCode RomSNESSolve(SNES snes, Vec X)
{
  RomCtx *c;
  Vec F, Y;
  Mat A, P;
  void *jctx;
  PetscErrorCode (*jac)(SNES, Vec, Mat, Mat, void *);
  PetscReal atol, rtol, stol, fnorm, xnorm, ynorm;
  PetscInt maxit, maxf, i;
  SNESConvergedReason reason = SNES_CONVERGED_ITERATING;
  PetscFunctionBeginUser;
  PetscCall(SNESShellGetContext(snes, &c));
  c->n_snes++;
  PetscCall(SNESGetFunction(snes, &F, NULL, NULL));
  PetscCall(SNESGetJacobian(snes, &A, &P, &jac, &jctx));
  PetscCall(SNESGetTolerances(snes, &atol, &rtol, &stol, &maxit, &maxf));
  if (!c->snes_dy) PetscCall(VecDuplicate(X, &c->snes_dy));
  Y = c->snes_dy;
  PetscCall(SNESComputeFunction(snes, X, F));
  PetscCall(VecNorm(F, NORM_2, &fnorm));
  PetscCall(SNESSetIterationNumber(snes, 0));
  PetscCall(SNESSetFunctionNorm(snes, fnorm));
  if (PetscIsInfOrNanReal(fnorm)) {
    PetscCall(SNESSetConvergedReason(snes, SNES_DIVERGED_FNORM_NAN));
    PetscFunctionReturn(0);
  }
  PetscCall(SNESConvergedDefault(snes, 0, 0.0, 0.0, fnorm, &reason, NULL));
  for (i = 0; i < maxit && !reason; i++) {
    c->n_newton++;
    PetscCall((*jac)(snes, X, A, P, jctx));
    PetscCall(RomApplyInverse(c, F, Y));
    PetscCall(VecAXPY(X, -1.0, Y));
    if (c->linear_shortcut && c->pwlinear) {
      PetscBool same;
      PetscCall(same_sides(c, X, &same));
      if (same) {
        c->n_shortcut++;
        PetscCall(SNESSetIterationNumber(snes, i + 1));
        reason = SNES_CONVERGED_ITS;
        break;
      }
    }
    PetscCall(SNESComputeFunction(snes, X, F));
    PetscCall(VecNormBegin(F, NORM_2, &fnorm));
    PetscCall(VecNormBegin(X, NORM_2, &xnorm));
    PetscCall(VecNormBegin(Y, NORM_2, &ynorm));
    PetscCall(VecNormEnd(F, NORM_2, &fnorm));
    PetscCall(VecNormEnd(X, NORM_2, &xnorm));
    PetscCall(VecNormEnd(Y, NORM_2, &ynorm));
    if (PetscIsInfOrNanReal(fnorm)) { reason = SNES_DIVERGED_FNORM_NAN; break; }
    PetscCall(SNESSetIterationNumber(snes, i + 1));
    PetscCall(SNESSetFunctionNorm(snes, fnorm));
    PetscCall(SNESConvergedDefault(snes, i + 1, xnorm, ynorm, fnorm, &reason, NULL));
  }
  if (!reason) reason = SNES_DIVERGED_MAX_IT;
  PetscCall(SNESSetConvergedReason(snes, reason));
  PetscFunctionReturn(0);
}

/* ---------------------------------------------------------------- the monitor's arithmetic */
int RomFinite(RomCtx *c, const PetscReal *u)
{
  const PetscInt n = c->first ? c->r : 2 * c->r;
  for (PetscInt i = 0; i < n; i++) if (!isfinite(u[i])) return 0;
  return 1;
}

/* recorder.SampleRecorder._track_peak */
static inline void track_peak(RomCtx *c, const PetscReal *N)
{
  for (PetscInt j = 0; j < c->nl; j++) if (fabs(N[j]) > fabs(c->peak[j])) c->peak[j] = N[j];
}

/* One row [t, q, p, z, v, N, peak, probe] per sample due up to t (recorder.SampleRecorder.sample):
   dense output between steps, the step's own state at a sample it lands on. */
PetscErrorCode RomTakeSamples(RomCtx *c, TS ts, PetscReal t, Vec U, PetscInt *taken)
{
  const PetscInt r = c->r, nl = c->nl;
  PetscFunctionBeginUser;
  *taken = 0;
  while (c->next_sample < c->nsample && c->sample_t[c->next_sample] <= t + c->sample_tol && c->nrows < c->row_cap) {
    const PetscReal ts_ = c->sample_t[c->next_sample];
    const PetscReal *u;
    Vec src = U;
    if (!(fabs(ts_ - t) <= c->sample_tol) && c->dense_output) {
      PetscCall(TSInterpolate(ts, ts_, c->work));
      src = c->work;
    }
    PetscReal *row = c->rows + (size_t)c->nrows * c->row_len;
    PetscCall(VecGetArrayRead(src, &u));
    row[0] = ts_;
    memcpy(row + 1, u, sizeof(PetscReal) * (c->first ? r : 2 * r));
    PetscCall(VecRestoreArrayRead(src, &u));
    PetscReal *z = row + 1 + 2 * r, *v = z + nl, *N = v + nl, *pk = N + nl, *probe = pk + nl;
    if (c->first) RomRate(c, ts_, row + 1, z, v, N, row + 1 + r);   /* p = eta' from the equation */
    else {
      constraint_state(c, ts_, row + 1, row + 1 + r, z, v);
      RomLaws(c, z, v, N, NULL, NULL, 0);
    }
    track_peak(c, N);
    for (PetscInt j = 0; j < nl; j++) { pk[j] = c->peak[j]; c->peak[j] = 0.0; }
    const PetscReal om = omega_(c, ts_);
    for (PetscInt k = 0; k < c->nprobe; k++) {
      const PetscReal *pb = c->probe_B + k * r;
      PetscReal s = 0.0;
      for (PetscInt i = 0; i < r; i++) s += pb[i] * row[1 + i];
      probe[k] = s + c->probe_r[k] * om;
    }
    c->nrows++; c->next_sample++; (*taken)++;
  }
  PetscFunctionReturn(0);
}

/* one constraint's (or support's) step in stats.ImpactAccumulator.add: the trapezoid sums over the
   step of length 2 half, the impacts, the contact runs, and the values kept for the next step */
static inline void accumulate(RomCtx *c, PetscInt j, int contact, PetscReal half, PetscReal f2, PetscReal z2, PetscReal pw_)
{
  PetscReal *pc = c->acc_prev, *pf = pc + c->nl, *pz = pf + c->nl, *pw = pz + c->nl;   /* rows of the Python side's (4, nl) array */
  const PetscReal cn = contact ? 1.0 : 0.0;
  if (!c->acc_started) {
    c->acc_impacts[j] += contact;
  } else {
    const PetscReal cp = pc[j];
    c->acc_contact_time[j] += half * (cp + cn);
    c->acc_f2[j] += half * (pf[j] + f2);
    c->acc_z2[j] += half * (pz[j] + z2);
    c->acc_power[j] += half * (pw[j] + pw_);
    c->acc_run[j] += half * cp;
    const int ended = (cp > 0) && !contact;
    if (ended) {
      if (c->acc_run[j] > c->acc_duration_max[j] || isnan(c->acc_run[j])) c->acc_duration_max[j] = c->acc_run[j];
      c->acc_run[j] = 0.0;
    }
    c->acc_impacts[j] += contact && (cp == 0);
    c->acc_run[j] += half * cn;
  }
  pc[j] = cn; pf[j] = f2; pz[j] = z2; pw[j] = pw_;
}

/* stats.ImpactAccumulator.add and SampleRecorder._track_peak for the state at the end of a step, operation
   by operation as in Python (so a checkpoint taken on either side continues on the other) */
/* the same for supports of two directions (recorder.SampleRecorder.step with laws.PlanarLaws.radial):
   per support the radial quantities |u|, v.n, |F|, contact = gap coordinate > clearance, the power
   |F.n| |v.n| and the work rate |F.n| |v.t| (its trapezoid integral in acc_work) */
static void step_statistics_planar(RomCtx *c, PetscReal t, const PetscReal *u)
{
  const PetscInt nc = c->ncon;
  PetscReal *z = c->z, *v = c->v, *N = c->N;
  constraint_state(c, t, u, pstate(c, u), z, v);
  RomLaws(c, z, v, N, NULL, NULL, 0);
  const PetscReal half = c->acc_started ? 0.5 * (t - c->acc_t_prev) : 0.0;
  for (PetscInt j = 0; j < nc; j++) {
    const PetscReal *uj = z + 2 * j, *wj = v + 2 * j, *fj = N + 2 * j;
    PetscReal gap, n[2], curved;
    gap_coordinate(c, j, uj, &gap, n, &curved);
    const PetscReal r = hypot(uj[0], uj[1]), vn = wj[0] * n[0] + wj[1] * n[1];
    const PetscReal vt = fabs(n[0] * wj[1] - n[1] * wj[0]), f = hypot(fj[0], fj[1]);
    const PetscReal fn = fabs(fj[0] * n[0] + fj[1] * n[1]);
    const int contact = gap > c->pl_gap[j];
    const PetscReal f2 = f * f, z2 = r * r, pw_ = fn * fabs(vn), work = fn * vt;
    if (c->acc_started) c->acc_work[j] += half * (c->acc_work_prev[j] + work);
    c->acc_work_prev[j] = work;
    const PetscReal af = fabs(f), az = fabs(r);
    if (af > c->acc_force_peak[j] || isnan(af)) c->acc_force_peak[j] = af;
    if (az > c->acc_displacement_peak[j] || isnan(az)) c->acc_displacement_peak[j] = az;
    if (c->alpha_speed && contact) {   /* recorder.SampleRecorder._track_alpha_speed */
      const PetscReal s = c->pl_alpha[j] * fabs(vn);
      if (s > c->alpha_speed[j] || isnan(s)) c->alpha_speed[j] = s;
    }
    accumulate(c, j, contact, half, f2, z2, pw_);
  }
  if (!c->acc_started) { c->acc_t0 = t; c->acc_started = 1; }
  c->acc_t_prev = t;
  track_peak(c, N);
}

void RomStepStatistics(RomCtx *c, PetscReal t, const PetscReal *u)
{
  const PetscInt nl = c->nl;
  if (c->dim == 2 && nl) { step_statistics_planar(c, t, u); return; }
  PetscReal *z = c->z, *v = c->v, *N = c->N;
  if (!nl) { c->acc_t0 = c->acc_started ? c->acc_t0 : t; c->acc_t_prev = t; c->acc_started = 1; return; }
  constraint_state(c, t, u, pstate(c, u), z, v);
  RomLaws(c, z, v, N, NULL, NULL, 0);
  const PetscReal half = c->acc_started ? 0.5 * (t - c->acc_t_prev) : 0.0;
  for (PetscInt j = 0; j < nl; j++) {
    const int contact = N[j] != 0;
    const PetscReal f2 = N[j] * N[j], z2 = z[j] * z[j], pw_ = fabs(N[j] * v[j]);
    const PetscReal aN = fabs(N[j]), az = fabs(z[j]);
    if (aN > c->acc_force_peak[j] || isnan(aN)) c->acc_force_peak[j] = aN;
    if (az > c->acc_displacement_peak[j] || isnan(az)) c->acc_displacement_peak[j] = az;
    if (c->alpha_speed && contact) {   /* recorder.SampleRecorder._track_alpha_speed */
      const PetscReal s = c->alpha[j] * fabs(v[j]);
      if (s > c->alpha_speed[j] || isnan(s)) c->alpha_speed[j] = s;
    }
    accumulate(c, j, contact, half, f2, z2, pw_);
  }
  if (!c->acc_started) { c->acc_t0 = t; c->acc_started = 1; }
  c->acc_t_prev = t;
  track_peak(c, N);
}

/* ---------------------------------------------------------------- wiring */
PetscErrorCode RomAttach(RomCtx *c, TS ts, Vec F, Vec G, Mat J, int shell)
{
  PetscFunctionBeginUser;
  PetscCall(TSSetIFunction(ts, F, RomIFunction, c));
  PetscCall(TSSetIJacobian(ts, J, J, shell ? RomIJacobianShell : RomIJacobianDense, c));
  PetscCall(TSSetRHSFunction(ts, G, RomRHSFunction, c));
  PetscFunctionReturn(0);
}
PetscErrorCode RomCreateShellMat(RomCtx *c, Mat *A)
{
  const PetscInt n = c->first ? c->r : 2 * c->r;
  PetscFunctionBeginUser;
  PetscCall(MatCreateShell(PETSC_COMM_SELF, n, n, n, n, c, A));
  PetscCall(MatShellSetOperation(*A, MATOP_MULT, (void (*)(void))RomMatMult));
  PetscCall(MatAssemblyBegin(*A, MAT_FINAL_ASSEMBLY));
  PetscCall(MatAssemblyEnd(*A, MAT_FINAL_ASSEMBLY));
  PetscFunctionReturn(0);
}
PetscErrorCode RomSetPCShell(RomCtx *c, PC pc)
{
  PetscFunctionBeginUser;
  PetscCall(PCSetType(pc, PCSHELL));
  PetscCall(PCShellSetContext(pc, c));
  PetscCall(PCShellSetApply(pc, RomPCApply));
  PetscCall(PCShellSetName(pc, "dbf_hpc reduced model: exact solve (Cholesky of shift^2 M + shift D + K, of its arrow structure when it has one; Woodbury on the active constraints)"));
  PetscFunctionReturn(0);
}
PetscErrorCode RomSetSNESShell(RomCtx *c, SNES snes)
{
  PetscFunctionBeginUser;
  PetscCall(SNESSetType(snes, SNESSHELL));
  PetscCall(SNESShellSetContext(snes, c));
  PetscCall(SNESShellSetSolve(snes, RomSNESSolve));
  PetscFunctionReturn(0);
}
PetscErrorCode RomDestroy(RomCtx *c)
{
  PetscFunctionBeginUser;
  if (c->snes_dy) PetscCall(VecDestroy(&c->snes_dy));
  PetscFunctionReturn(0);
}
