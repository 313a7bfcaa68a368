/* Column kernels of the Rayleigh-Ritz DBF path in blocks (dbf_ritz.RitzSpace.sources): each works
 * one column (one constraint) at a time, so that a column and its own Krylov vectors stay in cache
 * while the modes are swept, instead of numpy's whole-block passes with temporaries. Local rows only:
 * the caller sums across ranks. Layouts: a block of columns is n_local x ncol column-major; the modes
 * (Phi or M Phi) are n x n_local row-major; a step's block of Krylov vectors is addressed by V[k]
 * and, for column j, its column pos[k * ncol + j] (-1: none). */
#ifndef RITZ_KERNELS_H
#define RITZ_KERNELS_H

/* c[i, j] = Phi_i . a_j (i < n), c[n + k, j] = V_k(j) . a_j (k < p); c is (n + p) x ncol row-major */
void ritz_dots(long nloc, long ncol, long n, const double *Phi, long p, const double *const *V,
               const long *pos, const double *a, double *c);

/* a_j -= sum_i Phi_i c[i, j] + sum_k V_k(j) c[n + k, j] */
void ritz_subtract(long nloc, long ncol, long n, const double *Phi, long p, const double *const *V,
                   const long *pos, const double *c, double *a);

/* out_j = sum_i Phi_i y[j, i] + sum_k V_k(j) y[j, n + k]; y is ncol x width row-major */
void ritz_combine(long nloc, long ncol, long n, const double *Phi, long p, const double *const *V,
                  const long *pos, const double *y, long width, double *out);

/* The sums of RitzSpace.sources' checks for each column j (sums: 7 x ncol row-major):
 * |r|^2, |x|^2, x.Mx, ramp.x, |rd|^2, |d|^2, |rhs|^2 with
 *   r = Kx - lam Mx + k (g.x) e_g,   rhs = (g.x)^2 Mx - (g.x) e_g,   rd = Kd - lam Md - rhs + k (g.d) e_g
 * (e_g: the unit vector at local row grow[j], or none when grow[j] < 0). */
void ritz_check_sums(long nloc, long ncol, const double *X, const double *D, const double *MX, const double *MD,
                     const double *KX, const double *KD, const double *lam, const double *k, const double *gx,
                     const double *gd, const long *grow, const double *ramp, double *sums);

#endif
