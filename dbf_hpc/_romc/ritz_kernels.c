/* Column kernels of the Rayleigh-Ritz DBF path (ritz_kernels.h). The reductions use
 * `omp simd` (-fopenmp-simd): vector lanes sum in another order than numpy's BLAS, a round-off
 * difference (the DBFs of the numpy fallback agree to 1e-12; tests/test_dbf.py). */
#include "ritz_kernels.h"

/* Rows per chunk: the modes' chunk (n x CHUNK doubles, 24 KB for 6 modes) stays in L1 while every
 * column passes, so the modes are read from memory once per call instead of once per column. */
#define CHUNK 512

static double dot(long n, const double *restrict x, const double *restrict y)
{
    double s = 0.0;
#pragma omp simd reduction(+ : s)
    for (long r = 0; r < n; r++)
        s += x[r] * y[r];
    return s;
}

/* y[0:len] += sum_i Phi_i[0:len] w[i * stride] (Phi_i = Phi + i * nloc), four modes per sweep */
static void add_modes(long len, long n, long nloc, const double *Phi, const double *w, long stride, double *restrict y)
{
    long i = 0;
    for (; i + 3 < n; i += 4) {
        const double *restrict m0 = Phi + i * nloc, *restrict m1 = m0 + nloc;
        const double *restrict m2 = m1 + nloc, *restrict m3 = m2 + nloc;
        double c0 = w[i * stride], c1 = w[(i + 1) * stride], c2 = w[(i + 2) * stride], c3 = w[(i + 3) * stride];
#pragma omp simd
        for (long r = 0; r < len; r++)
            y[r] += m0[r] * c0 + m1[r] * c1 + m2[r] * c2 + m3[r] * c3;
    }
    for (; i < n; i++) {
        const double *restrict m0 = Phi + i * nloc;
        double c0 = w[i * stride];
#pragma omp simd
        for (long r = 0; r < len; r++)
            y[r] += m0[r] * c0;
    }
}

/* y[0:len] += sum_k V_k(j)[r0:r0 + len] w[k * stride] for the column's own Krylov vectors (posj[k * ncol]:
 * its column in step k's block, -1 none; zero coefficients skipped) */
static void add_own(long len, long p, const double *const *V, const long *posj, long ncol, long nloc, long r0,
                    const double *w, long stride, double *restrict y)
{
    for (long k = 0; k < p; k++) {
        long q = posj[k * ncol];
        double ck = w[k * stride];
        if (q < 0 || ck == 0.0)
            continue;
        const double *restrict v = V[k] + q * nloc + r0;
#pragma omp simd
        for (long r = 0; r < len; r++)
            y[r] += v[r] * ck;
    }
}

void ritz_dots(long nloc, long ncol, long n, const double *Phi, long p, const double *const *V,
               const long *pos, const double *a, double *c)
{
    for (long t = 0; t < (n + p) * ncol; t++)
        c[t] = 0.0;
    for (long r0 = 0; r0 < nloc; r0 += CHUNK) {
        long len = nloc - r0 < CHUNK ? nloc - r0 : CHUNK;
        for (long j = 0; j < ncol; j++) {
            const double *restrict x = a + j * nloc + r0;
            long i = 0;
            for (; i + 3 < n; i += 4) {
                const double *restrict m0 = Phi + i * nloc + r0, *restrict m1 = m0 + nloc;
                const double *restrict m2 = m1 + nloc, *restrict m3 = m2 + nloc;
                double s0 = 0.0, s1 = 0.0, s2 = 0.0, s3 = 0.0;
#pragma omp simd reduction(+ : s0, s1, s2, s3)
                for (long r = 0; r < len; r++) {
                    double xr = x[r];
                    s0 += m0[r] * xr;
                    s1 += m1[r] * xr;
                    s2 += m2[r] * xr;
                    s3 += m3[r] * xr;
                }
                c[i * ncol + j] += s0;
                c[(i + 1) * ncol + j] += s1;
                c[(i + 2) * ncol + j] += s2;
                c[(i + 3) * ncol + j] += s3;
            }
            for (; i < n; i++)
                c[i * ncol + j] += dot(len, Phi + i * nloc + r0, x);
            for (long k = 0; k < p; k++) {
                long q = pos[k * ncol + j];
                if (q >= 0)
                    c[(n + k) * ncol + j] += dot(len, V[k] + q * nloc + r0, x);
            }
        }
    }
}

void ritz_subtract(long nloc, long ncol, long n, const double *Phi, long p, const double *const *V,
                   const long *pos, const double *c, double *a)
{
    for (long r0 = 0; r0 < nloc; r0 += CHUNK) {
        long len = nloc - r0 < CHUNK ? nloc - r0 : CHUNK;
        for (long j = 0; j < ncol; j++) {
            double *restrict x = a + j * nloc + r0;
            double acc[CHUNK];
            for (long r = 0; r < len; r++)
                acc[r] = 0.0;
            add_modes(len, n, nloc, Phi + r0, c + j, ncol, acc);
            add_own(len, p, V, pos + j, ncol, nloc, r0, c + n * ncol + j, ncol, acc);
#pragma omp simd
            for (long r = 0; r < len; r++)
                x[r] -= acc[r];
        }
    }
}

void ritz_combine(long nloc, long ncol, long n, const double *Phi, long p, const double *const *V,
                  const long *pos, const double *y, long width, double *out)
{
    for (long r0 = 0; r0 < nloc; r0 += CHUNK) {
        long len = nloc - r0 < CHUNK ? nloc - r0 : CHUNK;
        for (long j = 0; j < ncol; j++) {
            double *restrict o = out + j * nloc + r0;
            const double *yj = y + j * width;
            for (long r = 0; r < len; r++)
                o[r] = 0.0;
            add_modes(len, n, nloc, Phi + r0, yj, 1, o);
            add_own(len, p, V, pos + j, ncol, nloc, r0, yj + n, 1, o);
        }
    }
}

/* The sums of ritz_check_sums over the rows [lo, hi) of column j (no e_g term), added to acc */
static void check_range(long lo, long hi, const double *restrict x, const double *restrict d,
                        const double *restrict mx, const double *restrict md, const double *restrict kx,
                        const double *restrict kd, const double *restrict ramp, double l, double g2, double *acc)
{
    double r2 = 0.0, x2 = 0.0, mass = 0.0, rx = 0.0, rd2 = 0.0, d2 = 0.0, h2 = 0.0;
#pragma omp simd reduction(+ : r2, x2, mass, rx, rd2, d2, h2)
    for (long r = lo; r < hi; r++) {
        double res = kx[r] - l * mx[r];
        double rhs = g2 * mx[r];
        double resd = kd[r] - l * md[r] - rhs;
        r2 += res * res;
        x2 += x[r] * x[r];
        mass += x[r] * mx[r];
        rx += ramp[r] * x[r];
        rd2 += resd * resd;
        d2 += d[r] * d[r];
        h2 += rhs * rhs;
    }
    acc[0] += r2;
    acc[1] += x2;
    acc[2] += mass;
    acc[3] += rx;
    acc[4] += rd2;
    acc[5] += d2;
    acc[6] += h2;
}

void ritz_check_sums(long nloc, long ncol, const double *X, const double *D, const double *MX, const double *MD,
                     const double *KX, const double *KD, const double *lam, const double *k, const double *gx,
                     const double *gd, const long *grow, const double *ramp, double *sums)
{
    for (long j = 0; j < ncol; j++) {
        const double *x = X + j * nloc, *d = D + j * nloc, *mx = MX + j * nloc, *md = MD + j * nloc;
        const double *kx = KX + j * nloc, *kd = KD + j * nloc;
        const double l = lam[j], g2 = gx[j] * gx[j];
        double acc[7] = {0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0};
        long q = grow[j];
        if (q < 0) {
            check_range(0, nloc, x, d, mx, md, kx, kd, ramp, l, g2, acc);
        } else {   /* the constraint's own row apart: its spring and load terms cancel the rest there */
            check_range(0, q, x, d, mx, md, kx, kd, ramp, l, g2, acc);
            check_range(q + 1, nloc, x, d, mx, md, kx, kd, ramp, l, g2, acc);
            double res = kx[q] - l * mx[q] + k[j] * gx[j];
            double rhs = g2 * mx[q] - gx[j];
            double resd = kd[q] - l * md[q] - rhs + k[j] * gd[j];
            acc[0] += res * res;
            acc[1] += x[q] * x[q];
            acc[2] += x[q] * mx[q];
            acc[3] += ramp[q] * x[q];
            acc[4] += resd * resd;
            acc[5] += d[q] * d[q];
            acc[6] += rhs * rhs;
        }
        for (int t = 0; t < 7; t++)
            sums[t * ncol + j] = acc[t];
    }
}
