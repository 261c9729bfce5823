/* The image-swept volume's inner loops (module volwarp_cli.sweep._sweepkernels): the
 * voxeliser's scan of each sub-segment between two templates (sweep_voxelize; the method
 * is told in sweep/voxelize.py) and the Bezier inverse's root finder (real_roots_unit,
 * for sweep/direct.py).
 *
 * Why C and not numba like the rest of volwarp: `volwarp sweep` is a one-shot command,
 * and numba cost most of a small sweep before any work (its import, the LLVM start-up
 * and loading each cached kernel: a 16^3 sweep took about 6 times `import numpy`).
 * Compiled when the package is installed, these kernels load in a millisecond, and the
 * sweep command imports no numba.
 *
 * Plain loops over a range of z slices or of polynomials: the callers split the ranges
 * over volwarp's threads (volwarp_cli.parallel), and each slice and polynomial is
 * computed on its own, so the result does not depend on the split. Every function takes
 * buffers (numpy arrays), checks their types, dimensions, C-contiguity and sizes, and
 * every index it reads (the sub-segments' templates, the template images' offsets and
 * sizes, the voxel boxes against the accumulators' block) before its loop, itself (a
 * wrong call is a ValueError, never a stray read or write), and releases the GIL while it
 * runs.
 *
 * The arithmetic is the numba kernels' it replaced, operation for operation (float64
 * intermediates, float32 accumulators read and written as numba did, the same order):
 * built with -ffp-contract=off (no fused multiply-adds), the results are the same bits.
 * The only departures are where numba's were undefined: a NaN template coordinate is
 * clamped to the template's first column or row (numba converted NaN to an index), and
 * the root finder's work arrays have room for every root its loops can record (numba's
 * had room for the mathematically possible ones only, which rounding to exact zeros can
 * exceed).
 */

#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

/* ---------------------------------------------------------------- buffers */

#include "../_buffers.h"

/* ---------------------------------------------------------------- the voxeliser */

enum { UNION, INTERSECTION, DIFFERENCE, BLEND, SUM, FIRST, OPS };
#define BLEND_FLOOR 1e-6

/* Everything sweep_voxelize's loop reads and writes (voxelize.py's _kernel_args). */
typedef struct {
    const double *P, *EX, *EY, *EZ, *SX, *SY, *SL; /* templates: (K, 3), (K), (K, F) */
    const int64_t *sub_a, *sub_b, *boxes;          /* sub-segments: (S), (S), (S, 6) */
    const uint8_t *closed;                         /* (S): 1 first, 2 last of a segment */
    const double *origin, *spacing;                /* (3) */
    const float *tex;                              /* template images, packed */
    const int64_t *off, *th, *tw, *tn, *ops;       /* per field: (F) */
    Py_ssize_t F, S;
    int64_t opac;
    double tol;
    float *acc, *wsum; /* (F, nz, ny, nx), (nz, ny, nx) when a field blends */
    uint8_t *covered;  /* (nz, ny, nx) */
    Py_ssize_t nz, ny, nx;
    int64_t zlo, zhi, oz, oy, ox;
    double *vals; /* (F), scratch */
} Voxeliser;

/* The bilinear sample (between slices: linear) of the template image of n slices h x w
 * from tex[off] at template coordinates (x, y), slice coordinate sl. */
static inline double bilinear(const float *tex, int64_t off, int64_t h, int64_t w, int64_t n,
                              double x, double y, double sl)
{
    double cx = x * (double)w - 0.5;
    double cy = (1.0 - y) * (double)h - 0.5;
    if (!(cx >= 0.0)) /* (below 0, or NaN) */
        cx = 0.0;
    else if (cx > (double)(w - 1))
        cx = (double)w - 1.0;
    if (!(cy >= 0.0))
        cy = 0.0;
    else if (cy > (double)(h - 1))
        cy = (double)h - 1.0;
    int64_t x0 = (int64_t)cx;
    int64_t y0 = (int64_t)cy;
    double fx = cx - (double)x0;
    double fy = cy - (double)y0;
    int64_t x1 = x0 + 1 < w ? x0 + 1 : x0;
    int64_t y1 = y0 + 1 < h ? y0 + 1 : y0;
    int64_t z0 = 0;
    double fz = 0.0;
    if (n > 1) {
        double cz = sl;
        if (!(cz >= 0.0))
            cz = 0.0;
        else if (cz > (double)(n - 1))
            cz = (double)n - 1.0;
        z0 = (int64_t)cz;
        fz = cz - (double)z0;
    }
    const float *t = tex + off + z0 * h * w;
    double v = ((t[y0 * w + x0] * (1.0 - fx) + t[y0 * w + x1] * fx) * (1.0 - fy) +
                (t[y1 * w + x0] * (1.0 - fx) + t[y1 * w + x1] * fx) * fy);
    if (fz > 0.0) { /* (then z0 < n - 1) */
        t += h * w;
        double v2 = ((t[y0 * w + x0] * (1.0 - fx) + t[y0 * w + x1] * fx) * (1.0 - fy) +
                     (t[y1 * w + x0] * (1.0 - fx) + t[y1 * w + x1] * fx) * fy);
        v = v * (1.0 - fz) + v2 * fz;
    }
    return v;
}

/* Clip [lo, hi] (index units) to where c + g i >= 0 (positive) or <= 0, widened by 1. */
static inline void half_line(double c, double g, int strict, int positive, double *lo,
                             double *hi)
{
    if (positive) {
        c = -c;
        g = -g;
    }
    /* want c + g i <= 0 */
    if (g > 1e-300) {
        double r = -c / g;
        if (r + 1.0 < *hi)
            *hi = r + 1.0;
    } else if (g < -1e-300) {
        double r = -c / g;
        if (r - 1.0 > *lo)
            *lo = r - 1.0;
    } else if (c > 0.0 || (strict && c >= 0.0)) {
        *hi = *lo - 1.0;
    }
}

/* The voxels of row (y, z) between templates a and b of sub-segment s, in region 0
 * (sA >= 0 > sB) or 1 (sA <= 0 < sB), combined into the accumulators. */
static void scan_row(const Voxeliser *k, Py_ssize_t s, int64_t z, int64_t y, int has_blend)
{
    const int64_t a = k->sub_a[s], b = k->sub_b[s];
    const int64_t *box = k->boxes + 6 * s;
    const double *origin = k->origin, *spacing = k->spacing;
    const Py_ssize_t F = k->F;
    double *vals = k->vals;
    const int64_t zl = z - k->oz, yl = y - k->oy;
    const double wz = origin[2] + spacing[2] * (double)z;
    const double wy = origin[1] + spacing[1] * (double)y;
    /* segment ends: accept points within tol of the end planes (rounding at seams) */
    const int last = (k->closed[s] & 2) != 0;
    const double ta = (k->closed[s] & 1) != 0 ? k->tol : 0.0;
    const double tb = last ? k->tol : 0.0;
    const double *Pa = k->P + 3 * a, *Pb = k->P + 3 * b;
    const double *EXa = k->EX + 3 * a, *EYa = k->EY + 3 * a, *EZa = k->EZ + 3 * a;
    const double *EXb = k->EX + 3 * b, *EYb = k->EY + 3 * b, *EZb = k->EZ + 3 * b;
    /* plane distances as functions of the x index: c + g * i */
    const double dax = origin[0] - Pa[0], day = wy - Pa[1], daz = wz - Pa[2];
    const double dbx = origin[0] - Pb[0], dby = wy - Pb[1], dbz = wz - Pb[2];
    const double cA = dax * EZa[0] + day * EZa[1] + daz * EZa[2];
    const double gA = spacing[0] * EZa[0];
    const double cB = dbx * EZb[0] + dby * EZb[1] + dbz * EZb[2];
    const double gB = spacing[0] * EZb[0];
    /* local template coordinates on A and B, also linear in i */
    const double cxa = 0.5 + (dax * EXa[0] + day * EXa[1] + daz * EXa[2]) / k->SX[a];
    const double gxa = spacing[0] * EXa[0] / k->SX[a];
    const double cya = 0.5 + (dax * EYa[0] + day * EYa[1] + daz * EYa[2]) / k->SY[a];
    const double gya = spacing[0] * EYa[0] / k->SY[a];
    const double cxb = 0.5 + (dbx * EXb[0] + dby * EXb[1] + dbz * EXb[2]) / k->SX[b];
    const double gxb = spacing[0] * EXb[0] / k->SX[b];
    const double cyb = 0.5 + (dbx * EYb[0] + dby * EYb[1] + dbz * EYb[2]) / k->SY[b];
    const double gyb = spacing[0] * EYb[0] / k->SY[b];
    const double *SLa = k->SL + a * F, *SLb = k->SL + b * F;
    for (int region = 0; region < 2; region++) {
        double lo = (double)box[0], hi = (double)box[1];
        if (region == 0) { /* sA >= 0 > sB */
            half_line(cA + ta, gA, 0, 1, &lo, &hi);
            half_line(cB - tb, gB, !last, 0, &lo, &hi);
        } else { /* sA <= 0 < sB */
            half_line(cA - ta, gA, 0, 0, &lo, &hi);
            half_line(cB + tb, gB, !last, 1, &lo, &hi);
        }
        if (hi < lo) /* (else box[0] <= lo <= hi <= box[1]: both convert exactly) */
            continue;
        int64_t i0 = (int64_t)ceil(lo);
        int64_t i1 = (int64_t)floor(hi);
        if (i0 < box[0])
            i0 = box[0];
        if (i1 > box[1])
            i1 = box[1];
        for (int64_t x = i0; x <= i1; x++) {
            const double sA = cA + gA * (double)x;
            const double sB = cB + gB * (double)x;
            if (region == 0) {
                if (!(sA >= -ta && (sB < 0.0 || (last && sB <= tb))))
                    continue;
            } else if (!(sA <= ta && sB > -tb)) {
                continue;
            }
            const double den = sA - sB;
            if (den == 0.0)
                continue;
            const double t = sA / den;
            const double xa = cxa + gxa * (double)x;
            const double ya = cya + gya * (double)x;
            const double xb = cxb + gxb * (double)x;
            const double yb = cyb + gyb * (double)x;
            const double xt = (1.0 - t) * xa + t * xb;
            const double yt = (1.0 - t) * ya + t * yb;
            if (xt < 0.0 || xt > 1.0 || yt < 0.0 || yt > 1.0)
                continue;
            for (Py_ssize_t f = 0; f < F; f++) {
                double va = bilinear(k->tex, k->off[f], k->th[f], k->tw[f], k->tn[f], xa, ya,
                                     SLa[f]);
                double vb = bilinear(k->tex, k->off[f], k->th[f], k->tw[f], k->tn[f], xb, yb,
                                     SLb[f]);
                vals[f] = (1.0 - t) * va + t * vb;
            }
            double w = 1.0;
            if (k->opac >= 0) {
                w = vals[k->opac];
                if (w < 0.0)
                    w = 0.0;
                w += BLEND_FLOOR;
            }
            const Py_ssize_t at = (zl * k->ny + yl) * k->nx + (x - k->ox);
            const Py_ssize_t plane = k->nz * k->ny * k->nx;
            const int cov = k->covered[at] != 0;
            for (Py_ssize_t f = 0; f < F; f++) {
                const double v = vals[f];
                const int64_t op = k->ops[f];
                float *acc = k->acc + f * plane + at;
                if (op == BLEND) {
                    *acc = (float)((double)*acc + w * v);
                } else if (!cov) {
                    *acc = (float)v;
                } else if (op == UNION) {
                    if (v > *acc)
                        *acc = (float)v;
                } else if (op == INTERSECTION) {
                    if (v < *acc)
                        *acc = (float)v;
                } else if (op == DIFFERENCE) {
                    double d = *acc - v;
                    *acc = (float)(d > 0.0 ? d : 0.0);
                } else if (op == SUM) {
                    double d = *acc + v;
                    if (d > 1.0)
                        d = 1.0;
                    else if (d < 0.0)
                        d = 0.0;
                    *acc = (float)d;
                }
            }
            if (has_blend)
                k->wsum[at] = (float)((double)k->wsum[at] + w);
            k->covered[at] = 1;
        }
    }
}

/* Every sub-segment over the z slices [zlo, zhi), in trajectory order. */
static void voxelise(const Voxeliser *k)
{
    int has_blend = 0;
    for (Py_ssize_t f = 0; f < k->F; f++)
        if (k->ops[f] == BLEND)
            has_blend = 1;
    for (int64_t z = k->zlo; z < k->zhi; z++)
        for (Py_ssize_t s = 0; s < k->S; s++) {
            const int64_t *box = k->boxes + 6 * s;
            if (z < box[4] || z > box[5] || box[0] > box[1])
                continue; /* (a box empty in x holds no voxel, whatever its y range) */
            for (int64_t y = box[2]; y <= box[3]; y++)
                scan_row(k, s, z, y, has_blend);
        }
}

/* Whether n slices of h x w samples from off lie in a buffer of len samples. */
static int image_fits(int64_t off, int64_t n, int64_t h, int64_t w, Py_ssize_t len)
{
    if (off < 0 || n < 1 || h < 1 || w < 1 || off > len)
        return 0;
    int64_t room = len - off;
    return h <= room / w && n <= room / (h * w);
}

enum {
    B_P, B_EX, B_EY, B_EZ, B_SX, B_SY, B_SL, B_SUB_A, B_SUB_B, B_CLOSED, B_BOXES, B_ORIGIN,
    B_SPACING, B_TEX, B_OFF, B_TH, B_TW, B_TN, B_OPS, B_ACC, B_WSUM, B_COVERED, N_BUFS
};

static const struct {
    const char *name;
    int kind, ndim, writable;
} voxel_bufs[N_BUFS] = {
    {"P", F64, 2, 0},      {"EX", F64, 2, 0},      {"EY", F64, 2, 0},     {"EZ", F64, 2, 0},
    {"SX", F64, 1, 0},     {"SY", F64, 1, 0},      {"SL", F64, 2, 0},     {"sub_a", I64, 1, 0},
    {"sub_b", I64, 1, 0},  {"closed", U8, 1, 0},   {"boxes", I64, 2, 0},  {"origin", F64, 1, 0},
    {"spacing", F64, 1, 0}, {"tex", F32, 1, 0},    {"off", I64, 1, 0},    {"th", I64, 1, 0},
    {"tw", I64, 1, 0},     {"tn", I64, 1, 0},      {"ops", I64, 1, 0},    {"acc", F32, 4, 1},
    {"wsum", F32, 3, 1},   {"covered", U8, 3, 1},
};

static PyObject *py_sweep_voxelize(PyObject *self, PyObject *args)
{
    static const char *fn = "sweep_voxelize";
    PyObject *o[N_BUFS];
    Py_buffer b[N_BUFS];
    int nb = 0;
    long long opac, zlo, zhi, oz, oy, ox;
    double tol;
    Voxeliser k;
    if (!PyArg_ParseTuple(args, "OOOOOOOOOOOOOOOOOOOLdOOOLLLLL:sweep_voxelize", &o[B_P],
                          &o[B_EX], &o[B_EY], &o[B_EZ], &o[B_SX], &o[B_SY], &o[B_SL],
                          &o[B_SUB_A], &o[B_SUB_B], &o[B_CLOSED], &o[B_BOXES], &o[B_ORIGIN],
                          &o[B_SPACING], &o[B_TEX], &o[B_OFF], &o[B_TH], &o[B_TW], &o[B_TN],
                          &o[B_OPS], &opac, &tol, &o[B_ACC], &o[B_WSUM], &o[B_COVERED], &zlo,
                          &zhi, &oz, &oy, &ox))
        return NULL;
    for (; nb < N_BUFS; nb++)
        if (get_buf(o[nb], &b[nb], voxel_bufs[nb].writable ? WRITE : READ,
                    KIND(voxel_bufs[nb].kind), voxel_bufs[nb].ndim, voxel_bufs[nb].name) < 0)
            goto fail;
    const Py_ssize_t K = b[B_P].shape[0];
    const Py_ssize_t S = b[B_SUB_A].shape[0];
    const Py_ssize_t F = b[B_OPS].shape[0];
    const Py_ssize_t *acc_n = b[B_ACC].shape, *cov_n = b[B_COVERED].shape;
    const char *bad = NULL;
    if (b[B_P].shape[1] != 3 || b[B_EX].shape[0] != K || b[B_EX].shape[1] != 3 ||
        b[B_EY].shape[0] != K || b[B_EY].shape[1] != 3 || b[B_EZ].shape[0] != K ||
        b[B_EZ].shape[1] != 3 || b[B_SX].shape[0] != K || b[B_SY].shape[0] != K ||
        b[B_SL].shape[0] != K || b[B_SL].shape[1] != F)
        bad = "expected templates P, EX, EY, EZ (K, 3), SX, SY (K) and SL (K, F)";
    else if (b[B_SUB_B].shape[0] != S || b[B_CLOSED].shape[0] != S ||
             b[B_BOXES].shape[0] != S || b[B_BOXES].shape[1] != 6)
        bad = "expected sub-segments sub_a, sub_b, closed (S) and boxes (S, 6)";
    else if (b[B_ORIGIN].shape[0] != 3 || b[B_SPACING].shape[0] != 3)
        bad = "expected origin and spacing of 3 values";
    else if (b[B_OFF].shape[0] != F || b[B_TH].shape[0] != F || b[B_TW].shape[0] != F ||
             b[B_TN].shape[0] != F)
        bad = "expected off, th, tw, tn and ops of one value per field";
    else if (acc_n[0] != F || acc_n[1] != cov_n[0] || acc_n[2] != cov_n[1] ||
             acc_n[3] != cov_n[2])
        bad = "expected acc (F, z, y, x) and covered (z, y, x) of one block";
    else if (opac >= F)
        bad = "opac: no such field";
    else if (!within_limit(zlo) || !within_limit(zhi) || !within_limit(oz) ||
             !within_limit(oy) || !within_limit(ox))
        bad = "an index beyond any grid";
    else if (zlo < zhi && (zlo < oz || zhi - oz > cov_n[0]))
        bad = "the z slices [zlo, zhi) are not in the block";
    if (bad) {
        PyErr_Format(PyExc_ValueError, "%s: %s", fn, bad);
        goto fail;
    }
    k.off = b[B_OFF].buf;
    k.th = b[B_TH].buf;
    k.tw = b[B_TW].buf;
    k.tn = b[B_TN].buf;
    k.ops = b[B_OPS].buf;
    int has_blend = 0;
    const Py_ssize_t tex_len = b[B_TEX].shape[0];
    for (Py_ssize_t f = 0; f < F; f++) {
        if (!image_fits(k.off[f], k.tn[f], k.th[f], k.tw[f], tex_len)) {
            PyErr_Format(PyExc_ValueError, "%s: field %zd: its template image (off %lld, "
                         "%lld x %lld x %lld) is not in tex (%zd samples)", fn, f,
                         (long long)k.off[f], (long long)k.tn[f], (long long)k.th[f],
                         (long long)k.tw[f], tex_len);
            goto fail;
        }
        if (k.ops[f] < 0 || k.ops[f] >= OPS) {
            PyErr_Format(PyExc_ValueError, "%s: field %zd: unknown operator code %lld", fn, f,
                         (long long)k.ops[f]);
            goto fail;
        }
        has_blend |= k.ops[f] == BLEND;
    }
    if (has_blend && (b[B_WSUM].shape[0] != cov_n[0] || b[B_WSUM].shape[1] != cov_n[1] ||
                      b[B_WSUM].shape[2] != cov_n[2])) {
        PyErr_Format(PyExc_ValueError, "%s: a field blends: expected wsum of covered's shape",
                     fn);
        goto fail;
    }
    k.sub_a = b[B_SUB_A].buf;
    k.sub_b = b[B_SUB_B].buf;
    k.boxes = b[B_BOXES].buf;
    for (Py_ssize_t s = 0; s < S; s++) {
        const int64_t *box = k.boxes + 6 * s;
        int ok = k.sub_a[s] >= 0 && k.sub_a[s] < K && k.sub_b[s] >= 0 && k.sub_b[s] < K;
        for (int j = 0; j < 6; j++)
            ok &= within_limit(box[j]);
        /* a box that holds voxels lies in the block in x and y (z: the slices, above) */
        if (ok && box[0] <= box[1] && box[2] <= box[3])
            ok = box[0] >= ox && box[1] - ox < cov_n[2] && box[2] >= oy &&
                 box[3] - oy < cov_n[1];
        if (!ok) {
            PyErr_Format(PyExc_ValueError, "%s: sub-segment %zd: its templates (%lld, %lld) "
                         "or its box are not in the arrays", fn, s, (long long)k.sub_a[s],
                         (long long)k.sub_b[s]);
            goto fail;
        }
    }
    k.vals = PyMem_RawMalloc((size_t)(F > 0 ? F : 1) * sizeof(double));
    if (!k.vals) {
        PyErr_NoMemory();
        goto fail;
    }
    k.P = b[B_P].buf;
    k.EX = b[B_EX].buf;
    k.EY = b[B_EY].buf;
    k.EZ = b[B_EZ].buf;
    k.SX = b[B_SX].buf;
    k.SY = b[B_SY].buf;
    k.SL = b[B_SL].buf;
    k.closed = b[B_CLOSED].buf;
    k.origin = b[B_ORIGIN].buf;
    k.spacing = b[B_SPACING].buf;
    k.tex = b[B_TEX].buf;
    k.F = F;
    k.S = S;
    k.opac = opac;
    k.tol = tol;
    k.acc = b[B_ACC].buf;
    k.wsum = b[B_WSUM].buf;
    k.covered = b[B_COVERED].buf;
    k.nz = cov_n[0];
    k.ny = cov_n[1];
    k.nx = cov_n[2];
    k.zlo = zlo;
    k.zhi = zhi;
    k.oz = oz;
    k.oy = oy;
    k.ox = ox;
    Py_BEGIN_ALLOW_THREADS
    voxelise(&k);
    Py_END_ALLOW_THREADS
    PyMem_RawFree(k.vals);
    release_all(b, nb);
    Py_RETURN_NONE;
fail:
    release_all(b, nb);
    return NULL;
}

/* ---------------------------------------------------------------- the root finder */

static inline double horner(const double *c, Py_ssize_t deg, double x)
{
    double v = c[deg];
    for (Py_ssize_t j = deg - 1; j >= 0; j--)
        v = v * x + c[j];
    return v;
}

/* The real roots in [0, 1] of the polynomial of ascending coefficients coef[0..D] into
 * out[0..D-1], increasing, NaN-padded. c, dc: room for D + 1 values; crit, roots: for
 * 2 D + 2 (each level records at most one root per interval and the end 1: at most two
 * more than the level below). */
static void unit_roots(const double *coef, Py_ssize_t D, double *out, double *c, double *dc,
                       double *crit, double *roots)
{
    Py_ssize_t ncrit = 0;
    for (Py_ssize_t k = D - 1; k >= 0; k--) {
        const Py_ssize_t deg = D - k;
        /* coefficients of the k-th derivative (degree deg) and of its derivative */
        for (Py_ssize_t j = 0; j <= deg; j++) {
            double f = 1.0;
            for (Py_ssize_t q = j + 1; q < j + k + 1; q++)
                f *= (double)q;
            c[j] = coef[j + k] * f;
        }
        for (Py_ssize_t j = 0; j < deg; j++)
            dc[j] = c[j + 1] * (double)(j + 1);
        Py_ssize_t nroots = 0;
        double a = 0.0;
        double fa = horner(c, deg, a);
        for (Py_ssize_t it = 0; it <= ncrit; it++) {
            const double b = it < ncrit ? crit[it] : 1.0;
            const double fb = horner(c, deg, b);
            if (fa == 0.0) {
                if (nroots == 0 || a - roots[nroots - 1] > 1e-13)
                    roots[nroots++] = a;
            } else if (fa * fb < 0.0) {
                double lo = a, hi = b, flo = fa;
                double x = 0.5 * (lo + hi);
                for (int i = 0; i < 100; i++) {
                    const double fx = horner(c, deg, x);
                    if (fx == 0.0)
                        break;
                    if ((fx < 0.0) == (flo < 0.0)) {
                        lo = x;
                        flo = fx;
                    } else {
                        hi = x;
                    }
                    const double d = deg > 0 ? horner(dc, deg - 1, x) : 0.0;
                    double nx = d != 0.0 ? x - fx / d : 0.5 * (lo + hi);
                    if (!(nx > lo && nx < hi))
                        nx = 0.5 * (lo + hi);
                    if (fabs(nx - x) <= 1e-15 * (1.0 + fabs(x)) || hi - lo <= 1e-15) {
                        x = nx;
                        break;
                    }
                    x = nx;
                }
                roots[nroots++] = x;
            }
            a = b;
            fa = fb;
        }
        if (fa == 0.0 && (nroots == 0 || a - roots[nroots - 1] > 1e-13))
            roots[nroots++] = a;
        for (Py_ssize_t j = 0; j < nroots; j++)
            crit[j] = roots[j];
        ncrit = nroots;
    }
    for (Py_ssize_t j = 0; j < D; j++)
        out[j] = j < ncrit ? crit[j] : NAN;
}

static PyObject *py_real_roots_unit(PyObject *self, PyObject *args)
{
    static const char *fn = "real_roots_unit";
    PyObject *o_coef, *o_out;
    Py_buffer b[2];
    int nb = 0;
    if (!PyArg_ParseTuple(args, "OO:real_roots_unit", &o_coef, &o_out))
        return NULL;
    if (get_buf(o_coef, &b[nb++], READ, KIND(F64), 2, "coef") < 0 ||
        get_buf(o_out, &b[nb++], WRITE, KIND(F64), 2, "out") < 0) {
        nb--;
        goto fail;
    }
    const Py_ssize_t n = b[0].shape[0], m = b[0].shape[1];
    if (m < 1 || b[1].shape[0] != n || b[1].shape[1] != m - 1) {
        PyErr_Format(PyExc_ValueError, "%s: expected coef (N, D + 1) and out (N, D), D >= 0; "
                     "got (%zd, %zd) and (%zd, %zd)", fn, n, m, b[1].shape[0], b[1].shape[1]);
        goto fail;
    }
    const Py_ssize_t D = m - 1;
    double *work = PyMem_RawMalloc((size_t)(2 * m + 4 * m + 4) * sizeof(double));
    if (!work) {
        PyErr_NoMemory();
        goto fail;
    }
    const double *coef = b[0].buf;
    double *out = b[1].buf;
    Py_BEGIN_ALLOW_THREADS
    double *c = work, *dc = work + m, *crit = work + 2 * m, *roots = crit + 2 * m + 2;
    for (Py_ssize_t v = 0; v < n; v++)
        unit_roots(coef + v * m, D, out + v * D, c, dc, crit, roots);
    Py_END_ALLOW_THREADS
    PyMem_RawFree(work);
    release_all(b, nb);
    Py_RETURN_NONE;
fail:
    release_all(b, nb);
    return NULL;
}

/* ---------------------------------------------------------------- module */

static PyMethodDef methods[] = {
    {"sweep_voxelize", py_sweep_voxelize, METH_VARARGS,
     "sweep_voxelize(P, EX, EY, EZ, SX, SY, SL, sub_a, sub_b, closed, boxes, origin, spacing, "
     "tex, off, th, tw, tn, ops, opac, tol, acc, wsum, covered, zlo, zhi, oz, oy, ox): "
     "voxelise the sub-segments (templates sub_a[s], sub_b[s]; voxel boxes (x0, x1, y0, y1, "
     "z0, z1) inclusive, the whole grid's indices) into the accumulators acc (float32 "
     "(F, z, y, x)), wsum (float32, covered's shape when a field blends) and covered (uint8 "
     "(z, y, x)) of the block whose first voxel is (oz, oy, ox), z slices [zlo, zhi). "
     "Templates: frames P, EX, EY, EZ (float64 (K, 3)), scales SX, SY (K), slice "
     "coordinates SL (K, F); closed (uint8 (S)): 1 first, 2 last sub-segment of a segment; "
     "tex: the template images (float32), field f's tn[f] x th[f] x tw[f] from off[f]; "
     "ops: the fields' operator codes (cvg.OP_CODES); opac: the opacity field or -1; tol: "
     "the end planes' tolerance (world units)."},
    {"real_roots_unit", py_real_roots_unit, METH_VARARGS,
     "real_roots_unit(coef, out): the real roots in [0, 1] of N polynomials (float64 "
     "ascending coefficients (N, D + 1)) into out (float64 (N, D)), increasing, NaN-padded: "
     "isolated by the derivative chain, each refined by safeguarded Newton."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_sweepkernels",
    "The image-swept volume's voxeliser and Bezier root finder in C.", -1, methods, NULL, NULL,
    NULL, NULL,
};

PyMODINIT_FUNC PyInit__sweepkernels(void)
{
    return PyModule_Create(&module);
}
