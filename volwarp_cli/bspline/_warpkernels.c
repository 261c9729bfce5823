/* The warp's inner loops, compiled ahead of time (module volwarp_cli.bspline._warpkernels).
 *
 * Why C and not numba like the rest of volwarp: `volwarp warp` is a one-shot
 * command whose whole run is about a second, and numba costs about half a
 * second of it before any work (its import, the LLVM start-up and loading each
 * cached kernel). These kernels are all the warp and capture commands need,
 * the label map's warp included (its one-pass scatter and the reading of its
 * planes, at the end: the intensity scatter's helpers, a label's weights); compiled
 * when the package is installed, they load in a millisecond.
 *
 * Every function takes buffers (numpy arrays; the wrappers are in pullback.py,
 * basis.py, pushforward.py and warp/labels.py), checks their types, shapes and
 * index ranges itself (a wrong call is a Python exception, never a stray read or
 * write), and releases the GIL while it runs, so the callers' threads share the work.
 *
 * Built with -ffp-contract=off: no fused multiply-adds, so a voxel's values
 * are the same on every machine and whatever block it is computed in (the
 * exact local updates rely on the latter).
 */

#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

/* ---------------------------------------------------------------- buffers */

/* The warp reads its input where it lies: a memory-mapped NRRD's samples start wherever its
 * header ends (x86-64 and arm64 load unaligned floats; copying the input to align it would
 * cost a copy of the volume). */
#define BUFFERS_UNALIGNED_OK 1
#include "../_buffers.h"

/* Row loops that run as vectors get AVX-512 (x86-64-v4) and AVX2 clones on x86-64, the
 * best the CPU has chosen when the module loads (same IEEE operations, no FMA: the same
 * results as the baseline, which a test builds with -DVOLWARP_NO_CLONES to compare).
 * AVX-512: 32 registers and 8 doubles per vector (row_boxes still spills some of its 21
 * neighbours; the AVX2 clone spills more); 0.84 of an all-general scatter's time. */
#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__) && !defined(VOLWARP_NO_CLONES)
#define VECTOR_CLONES __attribute__((target_clones("arch=x86-64-v4", "avx2", "default")))
#else
#define VECTOR_CLONES
#endif

#define MIN(a, b) ((a) < (b) ? (a) : (b))
#define MAX(a, b) ((a) > (b) ? (a) : (b))

/* ------------------------------------------------------------- pullback */
/* Trilinear (or, with equal indices and zero weights, nearest) gather of the
 * source at separable per-axis sample positions: out[g, f, e] for g in [g0, g1); the
 * range of the values written goes to range[0], range[1] (NaN-free input). */

/* The input is finite (capture_volume checks): the range reduction may run as vectors. */
#if defined(__GNUC__) && !defined(__clang__)
#define SAMPLE_OPT __attribute__((optimize("finite-math-only", "no-signed-zeros")))
#else
#define SAMPLE_OPT
#endif

#define SAMPLE_BODY(T)                                                                        \
    for (Py_ssize_t g = g0; g < g1; g++) {                                                   \
        const T *p0 = data + z0[g] * sy * sx, *p1 = data + z1[g] * sy * sx;                   \
        double wz = fz[g];                                                                    \
        for (Py_ssize_t f = 0; f < ny; f++) {                                                 \
            Py_ssize_t b0 = y0[f] * sx, b1 = y1[f] * sx;                                      \
            double wy = fy[f];                                                                \
            const T *r00 = p0 + b0, *r01 = p0 + b1, *r10 = p1 + b0, *r11 = p1 + b1;           \
            T *o = out + (g * ny + f) * nx;                                                   \
            for (Py_ssize_t e = 0; e < nx; e++) {                                             \
                Py_ssize_t c0 = x0[e], c1 = x1[e];                                            \
                double wx = fx[e];                                                            \
                double v00 = r00[c0] + wx * ((double)r00[c1] - r00[c0]);                      \
                double v01 = r01[c0] + wx * ((double)r01[c1] - r01[c0]);                      \
                double v10 = r10[c0] + wx * ((double)r10[c1] - r10[c0]);                      \
                double v11 = r11[c0] + wx * ((double)r11[c1] - r11[c0]);                      \
                double v0 = v00 + wy * (v01 - v00);                                           \
                double v1 = v10 + wy * (v11 - v10);                                           \
                T r = (T)(v0 + wz * (v1 - v0));                                               \
                o[e] = r;                                                                     \
                lo = MIN(lo, (double)r);                                                      \
                hi = MAX(hi, (double)r);                                                      \
            }                                                                                 \
        }                                                                                     \
    }                                                                                         \
    range[0] = lo;                                                                            \
    range[1] = hi;

#define SAMPLE_FN(NAME, T)                                                                     \
    SAMPLE_OPT VECTOR_CLONES static void NAME(                                                 \
        const T *restrict data, Py_ssize_t sy, Py_ssize_t sx, const int32_t *x0,               \
        const int32_t *x1, const double *fx, const int32_t *y0, const int32_t *y1,             \
        const double *fy, const int32_t *z0, const int32_t *z1, const double *fz,              \
        T *restrict out, Py_ssize_t ny, Py_ssize_t nx, Py_ssize_t g0, Py_ssize_t g1,           \
        double *range)                                                                         \
    {                                                                                          \
        double lo = HUGE_VAL, hi = -HUGE_VAL;                                                  \
        SAMPLE_BODY(T)                                                                         \
    }

SAMPLE_FN(sample_f32, float)
SAMPLE_FN(sample_f64, double)

/* The gather when every weight is 0 (a capture at oversample 1: each domain voxel one input
 * voxel): out = the source at the lower indices, the same numbers as the blend, which is
 * v + 0 * d = v + 0.0 for finite d: -0.0 becomes +0.0, here by its bits (the optimizer may
 * drop a + 0.0 under no-signed-zeros). */
SAMPLE_OPT static inline float plus_zero_f32(float v)
{
    uint32_t b;
    memcpy(&b, &v, sizeof b);
    b = (b << 1) ? b : 0;
    memcpy(&v, &b, sizeof b);
    return v;
}

SAMPLE_OPT static inline double plus_zero_f64(double v)
{
    uint64_t b;
    memcpy(&b, &v, sizeof b);
    b = (b << 1) ? b : 0;
    memcpy(&v, &b, sizeof b);
    return v;
}

#define COPY_FN(NAME, T, PLUS_ZERO)                                                            \
    SAMPLE_OPT VECTOR_CLONES static void NAME(                                                 \
        const T *restrict data, Py_ssize_t sy, Py_ssize_t sx, const int32_t *x0,               \
        const int32_t *y0, const int32_t *z0, T *restrict out, Py_ssize_t ny, Py_ssize_t nx,   \
        Py_ssize_t g0, Py_ssize_t g1, double *range)                                           \
    {                                                                                          \
        double lo = HUGE_VAL, hi = -HUGE_VAL;                                                  \
        int runs = nx > 0; /* (x0[0] is read only when there is a column) */                   \
        for (Py_ssize_t e = 1; e < nx; e++)                                                    \
            runs &= x0[e] == x0[0] + e;                                                        \
        for (Py_ssize_t g = g0; g < g1; g++) {                                                 \
            const T *p0 = data + z0[g] * sy * sx;                                              \
            for (Py_ssize_t f = 0; f < ny; f++) {                                              \
                const T *r = p0 + y0[f] * sx;                                                  \
                T *o = out + (g * ny + f) * nx;                                                \
                if (runs) { /* consecutive columns: a plain copy, as vectors */               \
                    const T *c = r + x0[0];                                                    \
                    for (Py_ssize_t e = 0; e < nx; e++) {                                      \
                        T v = PLUS_ZERO(c[e]);                                                 \
                        o[e] = v;                                                              \
                        lo = MIN(lo, (double)v);                                               \
                        hi = MAX(hi, (double)v);                                               \
                    }                                                                          \
                    continue;                                                                  \
                }                                                                              \
                for (Py_ssize_t e = 0; e < nx; e++) {                                          \
                    T v = PLUS_ZERO(r[x0[e]]);                                                 \
                    o[e] = v;                                                                  \
                    lo = MIN(lo, (double)v);                                                   \
                    hi = MAX(hi, (double)v);                                                   \
                }                                                                              \
            }                                                                                  \
        }                                                                                      \
        range[0] = lo;                                                                         \
        range[1] = hi;                                                                         \
    }

COPY_FN(copy_f32, float, plus_zero_f32)
COPY_FN(copy_f64, double, plus_zero_f64)

static int all_zero(const double *w, Py_ssize_t a, Py_ssize_t b)
{
    for (Py_ssize_t i = a; i < b; i++)
        if (w[i] != 0.0)
            return 0;
    return 1;
}

static PyObject *py_sample(PyObject *self, PyObject *args)
{
    PyObject *o[11];
    Py_ssize_t g0, g1;
    Py_buffer b[11];
    int n = 0;
    static const int kinds[11] = {FLOATS, KIND(I32), KIND(I32), KIND(F64), KIND(I32), KIND(I32), KIND(F64),
                                  KIND(I32),   KIND(I32), KIND(F64), FLOATS};
    static const int dims[11] = {3, 1, 1, 1, 1, 1, 1, 1, 1, 1, 3};
    static const char *names[11] = {"data", "x0", "x1", "fx", "y0", "y1", "fy",
                                    "z0",   "z1", "fz", "out"};
    if (!PyArg_ParseTuple(args, "OOOOOOOOOOOnn", &o[0], &o[1], &o[2], &o[3], &o[4], &o[5],
                          &o[6], &o[7], &o[8], &o[9], &o[10], &g0, &g1))
        return NULL;
    for (; n < 11; n++)
        if (get_buf(o[n], &b[n], n == 10 ? WRITE : READ, kinds[n], dims[n], names[n]) < 0)
            goto fail;
    Py_ssize_t nz = b[10].shape[0], ny = b[10].shape[1], nx = b[10].shape[2];
    Py_ssize_t iz = b[0].shape[0], iy = b[0].shape[1], ix = b[0].shape[2];
    if (buf_kind(&b[0]) != buf_kind(&b[10]) || b[1].shape[0] < nx || b[2].shape[0] < nx ||
        b[3].shape[0] < nx || b[4].shape[0] < ny || b[5].shape[0] < ny || b[6].shape[0] < ny ||
        b[7].shape[0] < g1 || b[8].shape[0] < g1 || b[9].shape[0] < g1 || g0 < 0 || g1 > nz) {
        PyErr_SetString(PyExc_ValueError, "sample: inconsistent arguments");
        goto fail;
    }
    /* every sample index inside the source */
    for (int k = 0; k < 3; k++) {
        const int32_t *lo = (const int32_t *)b[1 + 3 * k].buf;
        const int32_t *hi = (const int32_t *)b[2 + 3 * k].buf;
        Py_ssize_t len = k == 0 ? nx : (k == 1 ? ny : g1), lim = k == 0 ? ix : (k == 1 ? iy : iz);
        for (Py_ssize_t i = (k == 2 ? g0 : 0); i < len; i++)
            if (lo[i] < 0 || hi[i] < 0 || lo[i] >= lim || hi[i] >= lim) {
                PyErr_SetString(PyExc_IndexError, "sample: index outside the source");
                goto fail;
            }
    }
    double range[2];
    const int copy = all_zero(b[3].buf, 0, nx) && all_zero(b[6].buf, 0, ny) &&
                     all_zero(b[9].buf, g0, g1);
    Py_BEGIN_ALLOW_THREADS
    if (copy && buf_kind(&b[0]) == F32)
        copy_f32(b[0].buf, iy, ix, b[1].buf, b[4].buf, b[7].buf, b[10].buf, ny, nx, g0, g1, range);
    else if (copy)
        copy_f64(b[0].buf, iy, ix, b[1].buf, b[4].buf, b[7].buf, b[10].buf, ny, nx, g0, g1, range);
    else if (buf_kind(&b[0]) == F32)
        sample_f32(b[0].buf, iy, ix, b[1].buf, b[2].buf, b[3].buf, b[4].buf, b[5].buf, b[6].buf,
                   b[7].buf, b[8].buf, b[9].buf, b[10].buf, ny, nx, g0, g1, range);
    else
        sample_f64(b[0].buf, iy, ix, b[1].buf, b[2].buf, b[3].buf, b[4].buf, b[5].buf, b[6].buf,
                   b[7].buf, b[8].buf, b[9].buf, b[10].buf, ny, nx, g0, g1, range);
    Py_END_ALLOW_THREADS
    release_all(b, n);
    return Py_BuildValue("(dd)", range[0], range[1]);
fail:
    release_all(b, n);
    return NULL;
}

/* ---------------------------------------------------- separable evaluator */
/* Tensor-product spline of the control offsets dq[Cz, Cy, Cx, 3] on domain voxels
 * [x0, x1) x [y0, y1) x [z0, z1): three 1-D passes of 4 terms (z, then y, then x).
 * Voxel (e, f, g) goes to out[g - oz, f - oy, e - ox, :]. The summation order depends
 * on the voxel only, so it gets the same value in any block. */

/* The x pass for one component's row when x is contiguous in the output: out[i] = the
 * four weights of voxel i (wT[k][i], a transposed copy of wx) times the region's four
 * y-pass values c0..c3, summed in the same order as the strided loop (same values). */
#define XROW_FN(NAME, T)                                                                       \
    VECTOR_CLONES static void NAME(T *restrict out, const double *restrict w0,                 \
                                   const double *restrict w1, const double *restrict w2,       \
                                   const double *restrict w3, Py_ssize_t n, double c0,         \
                                   double c1, double c2, double c3)                            \
    {                                                                                          \
        for (Py_ssize_t i = 0; i < n; i++)                                                     \
            out[i] = (T)(w0[i] * c0 + w1[i] * c1 + w2[i] * c2 + w3[i] * c3);                   \
    }
XROW_FN(xrow_f32, float)
XROW_FN(xrow_f64, double)

#define SEPARABLE_BODY(T, XROW)                                                                \
    for (Py_ssize_t g = z0; g < z1; g++) {                                                     \
        Py_ssize_t c = g / gz, gb = g % gz;                                                    \
        const double *w = wz + 4 * gb;                                                         \
        for (Py_ssize_t jj = 0; jj < nyr; jj++) {                                              \
            for (Py_ssize_t ii = 0; ii < nxr; ii++) {                                          \
                const double *d = dq + ((c * cy + ry0 + jj) * cx + rx0 + ii) * 3;              \
                double *q = qz + (jj * nxr + ii) * 3;                                          \
                for (int m = 0; m < 3; m++)                                                    \
                    q[m] = w[0] * d[m] + w[1] * d[pz + m] + w[2] * d[2 * pz + m]               \
                           + w[3] * d[3 * pz + m];                                             \
            }                                                                                  \
        }                                                                                      \
        for (Py_ssize_t f = y0; f < y1; f++) {                                                 \
            Py_ssize_t b = f / gy, fb = f - b * gy, bb = b - ry0;                              \
            const double *v = wy + 4 * fb;                                                     \
            for (Py_ssize_t ii = 0; ii < nxr; ii++) {                                          \
                const double *q = qz + (bb * nxr + ii) * 3;                                    \
                Py_ssize_t py = nxr * 3;                                                       \
                for (int m = 0; m < 3; m++)                                                    \
                    qy[ii * 3 + m] = v[0] * q[m] + v[1] * q[py + m] + v[2] * q[2 * py + m]     \
                                     + v[3] * q[3 * py + m];                                   \
            }                                                                                  \
            T *row = (T *)(out + (g - oz) * st0 + (f - oy) * st1);                             \
            for (Py_ssize_t a = rx0; a < rx1; a++) {                                           \
                const double *q = qy + (a - rx0) * 3;                                          \
                Py_ssize_t e0 = MAX(a * gx, x0), e1 = MIN(a * gx + gx, x1);                    \
                if (sxe == 1) {                                                                \
                    const Py_ssize_t k = e0 - a * gx;                                          \
                    for (int m = 0; m < 3; m++)                                                \
                        XROW(row + (e0 - ox) + m * sce, wT + k, wT + gx + k, wT + 2 * gx + k,   \
                             wT + 3 * gx + k, e1 - e0, q[m], q[3 + m], q[6 + m], q[9 + m]);     \
                    continue;                                                                  \
                }                                                                              \
                for (Py_ssize_t e = e0; e < e1; e++) {                                         \
                    const double *u = wx + 4 * (e - a * gx);                                   \
                    for (int m = 0; m < 3; m++)                                                \
                        row[(e - ox) * sxe + m * sce] = (T)(u[0] * q[m] + u[1] * q[3 + m]      \
                                                            + u[2] * q[6 + m] + u[3] * q[9 + m]); \
                }                                                                              \
            }                                                                                  \
        }                                                                                      \
    }

static PyObject *py_separable(PyObject *self, PyObject *args)
{
    PyObject *o[5];
    Py_ssize_t x0, x1, y0, y1, z0, z1, ox, oy, oz;
    Py_buffer b[5];
    int n = 0;
    static const int kinds[5] = {KIND(F64), KIND(F64), KIND(F64), KIND(F64), FLOATS};
    static const int dims[5] = {4, 2, 2, 2, 4};
    static const char *names[5] = {"dq", "wx", "wy", "wz", "out"};
    if (!PyArg_ParseTuple(args, "OOOOnnnnnnOnnn", &o[0], &o[1], &o[2], &o[3], &x0, &x1, &y0,
                          &y1, &z0, &z1, &o[4], &ox, &oy, &oz))
        return NULL;
    for (; n < 5; n++)
        if (get_buf(o[n], &b[n], n == 4 ? WRITE | STRIDED : READ, kinds[n], dims[n], names[n]) < 0)
            goto fail;
    if (x1 <= x0 || y1 <= y0 || z1 <= z0) {
        for (int k = 0; k < n; k++)
            PyBuffer_Release(&b[k]);
        Py_RETURN_NONE;
    }
    Py_ssize_t cz = b[0].shape[0], cy = b[0].shape[1], cx = b[0].shape[2];
    Py_ssize_t gx = b[1].shape[0], gy = b[2].shape[0], gz = b[3].shape[0];
    Py_ssize_t snz = b[4].shape[0], sny = b[4].shape[1], snx = b[4].shape[2];
    Py_ssize_t rx0 = x0 / gx, rx1 = (x1 - 1) / gx + 1, ry0 = y0 / gy, ry1 = (y1 - 1) / gy + 1;
    Py_ssize_t nxr = rx1 - rx0 + 3, nyr = ry1 - ry0 + 3;
    if (b[0].shape[3] != 3 || b[4].shape[3] != 3 || b[1].shape[1] != 4 || b[2].shape[1] != 4 ||
        b[3].shape[1] != 4 || x0 < 0 || y0 < 0 || z0 < 0 || rx1 + 3 > cx || ry1 + 3 > cy ||
        (z1 - 1) / gz + 4 > cz || x0 - ox < 0 || y0 - oy < 0 || z0 - oz < 0 ||
        x1 - ox > snx || y1 - oy > sny || z1 - oz > snz ||
        b[4].strides[3] % b[4].itemsize || b[4].strides[2] % b[4].itemsize) {
        PyErr_SetString(PyExc_ValueError, "separable: block outside the lattice or the output");
        goto fail;
    }
    double *qz = PyMem_RawMalloc(sizeof(double) * (3 * (size_t)(nxr * nyr + nxr) + 4 * gx));
    if (!qz) {
        PyErr_NoMemory();
        goto fail;
    }
    double *qy = qz + 3 * nxr * nyr, *wT = qy + 3 * nxr;
    const double *dq = b[0].buf, *wx = b[1].buf, *wy = b[2].buf, *wz = b[3].buf;
    for (Py_ssize_t k = 0; k < 4; k++) /* wx [gx][4] transposed: wT[k][i] */
        for (Py_ssize_t i = 0; i < gx; i++)
            wT[k * gx + i] = wx[i * 4 + k];
    Py_ssize_t pz = cy * cx * 3, st0 = b[4].strides[0], st1 = b[4].strides[1];
    Py_ssize_t sxe = b[4].strides[2] / b[4].itemsize, sce = b[4].strides[3] / b[4].itemsize;
    char *out = b[4].buf; /* any strides: interleaved (x, y, z) triplets or planar */
    Py_BEGIN_ALLOW_THREADS
    if (buf_kind(&b[4]) == F32) {
        SEPARABLE_BODY(float, xrow_f32)
    } else {
        SEPARABLE_BODY(double, xrow_f64)
    }
    Py_END_ALLOW_THREADS
    PyMem_RawFree(qz);
    release_all(b, n);
    Py_RETURN_NONE;
fail:
    release_all(b, n);
    return NULL;
}

/* ---------------------------------------------------------- pushforward */

/* The constants pushforward.py documents and exports (it takes them from this module) */
#define QUANTUM 1099511627776.0 /* 2**40: fixed-point unit of the accumulators */
#define IQUANTUM ((int64_t)1 << 40)
#define SHIFT 1048576.0 /* makes coordinates positive so that truncation is floor */
#define ISHIFT ((int64_t)1048576)
#define ROUND (0.5 - 1e-6) /* nearest modes: round half down, with a tolerance */
#define COVERED_HI 0.8     /* weights from which a voxel counts as inside the model */
#define COVERED_LO 0.6     /* and up to which as on its silhouette */
#define GROW_BELOW 0.8     /* a box holding less of its voxel's image volume grows to it */

/* floor(x) as an integer for |x| < 2**62 (libm's floor is a call without SSE4.1). */
static inline int64_t ifloor(double x)
{
    int64_t t = (int64_t)x;
    return t - (x < (double)t);
}

typedef struct {
    const float *uh[2]; /* deformation offsets, planar: [3][nzb][nyb][nxb], one-voxel margin */
    Py_ssize_t cstride, nyb, nxb;
    int npass;
    Py_ssize_t ox, oy, oz; /* domain voxel of uh[:, 1, 1, 1] */
    const void *values;   /* domain samples: voxel (e, f, g) at ((g - voz) vy + f) vx + e; the
                           * pointer is shifted by the buffer's first (x, y), so that a buffer
                           * of some columns and rows of the planes serves as whole ones */
    int values_f64;
    Py_ssize_t voz;
    Py_ssize_t vy, vx;   /* the values buffer's rows and columns per plane */
    Py_ssize_t dvy, dvx; /* the domain's rows and columns */
    double off[3], scale[3];
    Py_ssize_t lo[3], hi[3];
    double sign;
    double inv_vmax;
    int box;
    int track; /* find the touched target box (else bbox stays empty) */
    const unsigned char *still; /* [npass][Rz][Ry][Rx]: region's control points unmoved in
                                 * pass p's lattice, or NULL */
    Py_ssize_t regions[3], gran[3], vz;
    int64_t *acc; /* [nz, ty, tx, 2]: target planes [tz_lo, tz_hi), plane z in slot z - rb,
                   * less nz from nz on (a ring when rb is a multiple of nz below tz_lo);
                   * shifted like values: the buffer's first row and column may be any */
    Py_ssize_t nz, ty, tx, tz_lo, tz_hi, rb;
    Py_ssize_t tx_lo, tx_hi, ty_lo, ty_hi; /* contributions kept: x in [tx_lo, tx_hi), y in
                                            * [ty_lo, ty_hi) (and z in [tz_lo, tz_hi)) */
    int64_t bbox[6];
} Scatter;

/* One component's extent of a voxel's box, from its offset c and its six neighbours'
 * offsets: the faces across the component's own axis (own_m, own_p) are offset by the
 * half voxel h, the other four (o1..o4) only need the extreme neighbour. */
#define BOX_SIDE(c, own_m, own_p, o1, o2, o3, o4, h, base, lo, hi)                            \
    do {                                                                                       \
        const double c_ = (c), a0_ = 0.5 * (c_ + (own_m)) - (h);                              \
        const double a1_ = 0.5 * (c_ + (own_p)) + (h);                                        \
        const double n0_ = MIN(MIN(o1, o2), MIN(o3, o4)), n1_ = MAX(MAX(o1, o2), MAX(o3, o4)); \
        lo = MIN(MIN(a0_, a1_), 0.5 * (c_ + n0_)) + (base);                                    \
        hi = MAX(MAX(a0_, a1_), 0.5 * (c_ + n1_)) + (base);                                    \
    } while (0)

/* One extent of a grown box: the side `side` about the middle of [lo, hi], within [nlo, nhi]. */
static inline void grow_side(double side, double nlo, double nhi, double *lo, double *hi)
{
    const double mid = 0.5 * (*lo + *hi);
    *lo = MAX(mid - 0.5 * side, nlo);
    *hi = MIN(mid + 0.5 * side, nhi);
}

/* The box of one voxel (its offsets u0[0], u1[0], u2[0], base position (bx, by, bz)) that
 * holds less than GROW_BELOW of its image's volume |det J|, grown to it (pushforward.py):
 * a rotation about an oblique axis shrinks the face centres' box to 35% of the voxel's
 * image (45 degrees about x, then z), and the mass scale alone left gaps between such
 * boxes (a constant came out down to 41% inside). Each side goes from the face centres'
 * box s towards the box of the image's 8 corners c, s + k (c - s), one k for the three
 * (its tangent's root, then two Newton steps: plain arithmetic, the same bits on every
 * machine), and stays within the voxel's and its neighbours' offsets widened by the half
 * voxel, where the reach bounds (reach.py) put every box. The box only grows: its mass
 * only falls. */
static void grow_box(const float *u0, const float *u1, const float *u2, Py_ssize_t sF,
                     Py_ssize_t sG, double bx, double by, double bz, double sx, double sy,
                     double sz, double *x0, double *x1, double *y0, double *y1, double *z0,
                     double *z1, double *mass)
{
    const float *uc[3] = {u0, u1, u2};
    const Py_ssize_t step[3] = {1, sF, sG};
    const double base[3] = {bx, by, bz}, half[3] = {0.5 * sx, 0.5 * sy, 0.5 * sz};
    double J[3][3], nlo[3], nhi[3]; /* J[component][axis] */
    for (int c = 0; c < 3; c++) {
        double lo = uc[c][0], hi = uc[c][0];
        for (int a = 0; a < 3; a++) {
            const double m = uc[c][-step[a]], p = uc[c][step[a]];
            J[c][a] = 0.5 * (p - m) + (a == c ? 2.0 * half[c] : 0.0);
            lo = MIN(lo, MIN(m, p));
            hi = MAX(hi, MAX(m, p));
        }
        nlo[c] = base[c] + lo - half[c];
        nhi[c] = base[c] + hi + half[c];
    }
    const double det = J[0][0] * (J[1][1] * J[2][2] - J[1][2] * J[2][1]) -
                       J[0][1] * (J[1][0] * J[2][2] - J[1][2] * J[2][0]) +
                       J[0][2] * (J[1][0] * J[2][1] - J[1][1] * J[2][0]);
    double *lo[3] = {x0, y0, z0}, *hi[3] = {x1, y1, z1};
    double side[3], more[3];
    for (int c = 0; c < 3; c++) {
        side[c] = *hi[c] - *lo[c];
        more[c] = MAX(fabs(J[c][0]) + fabs(J[c][1]) + fabs(J[c][2]) - side[c], 0.0);
    }
    const double want = GROW_BELOW * fabs(det);
    double k = 1.0;
    const double least = side[0] * side[1] * side[2];
    if ((side[0] + more[0]) * (side[1] + more[1]) * (side[2] + more[2]) > want) {
        /* the volume is a cubic in k of non-negative coefficients: above its tangent at 0,
         * whose root k0 is too large, then convex and rising, so Newton's steps from k0
         * come down towards the root without passing it (two leave the volume within
         * 0.07% over the share, measured over 20000 random rotations and stretches) */
        k = (want / least - 1.0) /
            (more[0] / side[0] + more[1] / side[1] + more[2] / side[2]);
        k = MIN(k, 1.0);
        for (int i = 0; i < 2; i++) {
            const double a = side[0] + k * more[0], b = side[1] + k * more[1],
                         c = side[2] + k * more[2];
            k -= (a * b * c - want) / (more[0] * b * c + a * more[1] * c + a * b * more[2]);
        }
    }
    for (int c = 0; c < 3; c++)
        grow_side(side[c] + k * more[c], nlo[c], nhi[c], lo[c], hi[c]);
    *mass = fabs(det) / ((*x1 - *x0) * (*y1 - *y0) * (*z1 - *z0));
}

/* Phase 1, one row of n voxels (no stores into the accumulators, so it runs as
 * vectors): the box of each voxel's image relative to its base position (paper 6:
 * the six face centres are averages of neighbouring entries; per component, the two
 * faces across its own axis are offset by the half voxel, the four others only need
 * the extreme neighbour, since rounding is monotone), in target coordinates (voxel
 * e0 + e has base position (bx + sx (e0 + e), by, bz)), and its mass factor
 * |det J| / box volume (the Jacobian from the same face-centre differences; see
 * pushforward.py). */
VECTOR_CLONES static void row_boxes(const float *restrict u0, const float *restrict u1,
                                   const float *restrict u2, Py_ssize_t sF, Py_ssize_t sG,
                                   Py_ssize_t e0, Py_ssize_t n, double bx, double by, double bz,
                                   double sx, double sy, double sz, double *restrict xmin,
                                   double *restrict xmax, double *restrict ymin,
                                   double *restrict ymax, double *restrict zmin,
                                   double *restrict zmax, double *restrict mass)
{
    const double hx = 0.5 * sx, hy = 0.5 * sy, hz = 0.5 * sz;
    for (Py_ssize_t e = 0; e < n; e++) {
        double x_xm = u0[e - 1], x_xp = u0[e + 1], x_ym = u0[e - sF], x_yp = u0[e + sF],
               x_zm = u0[e - sG], x_zp = u0[e + sG];
        double y_xm = u1[e - 1], y_xp = u1[e + 1], y_ym = u1[e - sF], y_yp = u1[e + sF],
               y_zm = u1[e - sG], y_zp = u1[e + sG];
        double z_xm = u2[e - 1], z_xp = u2[e + 1], z_ym = u2[e - sF], z_yp = u2[e + sF],
               z_zm = u2[e - sG], z_zp = u2[e + sG];
        /* the voxel's own index, not the row offset: a voxel gets the same box whatever
         * block it is in (int32: converts as a vector; rows < 2**31) */
        double base = bx + sx * (int32_t)(e0 + e);
        double bx0, bx1, by0, by1, bz0, bz1;
        BOX_SIDE(u0[e], x_xm, x_xp, x_ym, x_yp, x_zm, x_zp, hx, base, bx0, bx1);
        BOX_SIDE(u1[e], y_ym, y_yp, y_xm, y_xp, y_zm, y_zp, hy, by, by0, by1);
        BOX_SIDE(u2[e], z_zm, z_zp, z_xm, z_xp, z_ym, z_yp, hz, bz, bz0, bz1);
        double dxx = sx + 0.5 * (x_xp - x_xm), dxy = 0.5 * (y_xp - y_xm), dxz = 0.5 * (z_xp - z_xm);
        double dyx = 0.5 * (x_yp - x_ym), dyy = sy + 0.5 * (y_yp - y_ym), dyz = 0.5 * (z_yp - z_ym);
        double dzx = 0.5 * (x_zp - x_zm), dzy = 0.5 * (y_zp - y_zm), dzz = sz + 0.5 * (z_zp - z_zm);
        double det = dxx * (dyy * dzz - dyz * dzy) - dxy * (dyx * dzz - dyz * dzx)
                    + dxz * (dyx * dzy - dyy * dzx);
        /* a degenerate box gets inf or NaN here; phase 2 skips it before use */
        mass[e] = fabs(det) / ((bx1 - bx0) * (by1 - by0) * (bz1 - bz0));
        xmin[e] = bx0;
        xmax[e] = bx1;
        ymin[e] = by0;
        ymax[e] = by1;
        zmin[e] = bz0;
        zmax[e] = bz1;
    }
    for (Py_ssize_t e = 0; e < n; e++)
        if (mass[e] > 1.0 / GROW_BELOW && mass[e] < INFINITY)
            grow_box(u0 + e, u1 + e, u2 + e, sF, sG, bx + sx * (int32_t)(e0 + e), by, bz, sx, sy,
                     sz, xmin + e, xmax + e, ymin + e, ymax + e, zmin + e, zmax + e, mass + e);
}

/* Fixed-point accumulation of pairs (weight, weighted value) with 2-lane vectors (GCC
 * vector extensions: SSE2 on x86-64, NEON on arm64). quantize2 rounds to the nearest
 * integer (ties to even, so quantize2(-x) = -quantize2(x)) by adding 1.5 * 2**52, exact
 * for |x| < 2**51; here |x| <= 6 * 2**40 (overlaps <= 1, |value| <= 1, and |det J| is
 * at most 6 box volumes). */
typedef double v2d __attribute__((vector_size(16)));
typedef int64_t v2i __attribute__((vector_size(16)));
#define MAGIC 6755399441055744.0

static inline v2i quantize2(v2d x)
{
    const v2d m = {MAGIC, MAGIC};
    v2d t = x + m;
    v2i bits, mbits;
    memcpy(&bits, &t, sizeof bits);
    memcpy(&mbits, &m, sizeof mbits);
    return bits - mbits;
}

typedef double v4d __attribute__((vector_size(32)));
typedef int64_t v4i __attribute__((vector_size(32)));

/* Two target voxels side by side: acc[0:4] += quantize(w2 * kv2) lane by lane, the same
 * numbers as two add2 calls (one 256-bit add in the AVX2 clone). */
static inline void add4(int64_t *acc, v4d kv2, v4d w2)
{
    const v4d m = {MAGIC, MAGIC, MAGIC, MAGIC};
    v4d t = kv2 * w2 + m;
    v4i bits, mbits, a;
    memcpy(&bits, &t, sizeof bits);
    memcpy(&mbits, &m, sizeof mbits);
    memcpy(&a, acc, sizeof a);
    a += bits - mbits;
    memcpy(acc, &a, sizeof a);
}

/* acc[0:2] += quantize2(w * kv), kv = (weight scale, value scale) */
static inline void add2(int64_t *acc, v2d kv, double w)
{
    v2i a;
    memcpy(&a, acc, sizeof a);
    a += quantize2(kv * w);
    memcpy(acc, &a, sizeof a);
}

/* The target voxels [v0, v1] that a box side [lo, hi] covers (clipped to [first, last],
 * coordinates > -2**20), and its overlaps with the first and the last of them. */
typedef struct {
    int64_t v0, v1;
    double a0, a1, lo, hi;
} Span;

static inline int span_of(double lo, double hi, int64_t first, int64_t last, Span *s)
{
    s->lo = lo;
    s->hi = hi;
    s->v0 = MAX((int64_t)(lo - 0.5 + SHIFT) - ISHIFT + 1, first);
    s->v1 = MIN(ISHIFT - (int64_t)(SHIFT - hi - 0.5) - 1, last);
    s->a0 = MIN(hi, s->v0 + 0.5) - MAX(lo, s->v0 - 0.5);
    s->a1 = MIN(hi, s->v1 + 0.5) - MAX(lo, s->v1 - 0.5);
    return s->v1 >= s->v0;
}

/* span_of for a row of boxes, as vectors (the general voxels' spans, before the scalar
 * accumulation): the same numbers. Sides are first clamped to [first - 2, last + 2],
 * which changes no span's voxels nor the overlaps of a non-empty one (a side beyond
 * that range is beyond the first or last voxel's centre-side face either way), and
 * keeps the conversions in int32 range (and NaN out of them: MAX(NaN, x) is x). A
 * degenerate side (not hi > lo, NaN included) gets an empty span (v1 < v0): the
 * voxel is skipped. Targets < 2**20 - 2 voxels per axis, as span_of assumes. */
VECTOR_CLONES static void row_spans(const double *restrict lo, const double *restrict hi,
                                    Py_ssize_t n, int32_t first, int32_t last,
                                    int32_t *restrict v0, int32_t *restrict v1,
                                    double *restrict a0, double *restrict a1)
{
    const double f2 = first - 2.0, l2 = last + 2.0;
    for (Py_ssize_t e = 0; e < n; e++) {
        const double l = MIN(MAX(lo[e], f2), l2), h = MIN(MAX(hi[e], f2), l2);
        const int32_t p = MAX((int32_t)(l - 0.5 + SHIFT) - (int32_t)ISHIFT + 1, first);
        const int32_t q = MIN((int32_t)ISHIFT - (int32_t)(SHIFT - h - 0.5) - 1, last);
        v0[e] = p;
        v1[e] = hi[e] > lo[e] ? q : p - 1;
        a0[e] = MIN(h, p + 0.5) - MAX(l, p - 0.5);
        a1[e] = MIN(h, q + 0.5) - MAX(l, q - 0.5);
    }
}

/* keep[e]: voxel e's spans are all non-empty (its box is valid and reaches the window) */
VECTOR_CLONES static void row_keep(int32_t *const v0[3], int32_t *const v1[3], Py_ssize_t e0,
                                   Py_ssize_t e1, unsigned char *restrict keep)
{
    const int32_t *x0 = v0[0], *x1 = v1[0], *y0 = v0[1], *y1 = v1[1], *z0 = v0[2], *z1 = v1[2];
    for (Py_ssize_t e = e0; e < e1; e++)
        keep[e] = (x1[e] >= x0[e]) & (y1[e] >= y0[e]) & (z1[e] >= z0[e]);
}

/* Phase 2's common case, in runs. A general voxel whose box covers 2 x 2 x 2 target voxels
 * (a cube: row_cubes) adds to each of its 4 target rows r = 2 dz + dy (plane z0 + dz, row
 * y0 + dy) a pair (weight, weighted value) at column x0 (side h = 0) and one at x0 + 1
 * (h = 1). row_quanta makes those 16 fixed-point integers for a piece of a row as vectors:
 * the very numbers splat_narrow's add4 calls make (the same IEEE operations in the same
 * order, no FMA), component c of side h of row r of voxel e at q[(4 r + 2 h + c) n + e - e0].
 * Side by side, cubes usually start at consecutive columns of the same pair of rows and
 * planes (on a 256^3 warp with every point of a 9^3 lattice moved, 94% of the voxels are
 * cubes, in runs of 20 on average): add_run adds a run to each of its rows in one pass.
 * Integer sums, whatever their order: the targets are those of one splat_narrow a voxel,
 * bit for bit. Measured on that warp in process: 12-16% less time, one thread or two.
 *
 * QCHUNK voxels a piece: their 16 streams (8.5 KB) stay in the first-level cache with the
 * row buffers they are made from (a whole row's, 33 KB for 256 voxels, did not: about 10%
 * slower, no faster than one splat_narrow a voxel).
 * QPAD: the streams are 3 cache lines more than a piece apart (pieces of 2**k voxels put
 * every stream at the same address modulo 4096, where a load waits for any earlier store
 * that matches it there: the processor compares those bits only). */
#define QCHUNK 64
#define QPAD 24
#define MAGIC_BITS 0x4338000000000000LL /* the bits of MAGIC */

static inline int64_t quantize1(double x)
{
    const double t = x + MAGIC;
    uint64_t bits; /* (unsigned: the difference of a voxel not kept, whose quanta are never
                    * read, may be out of range; wrapped, not undefined) */
    memcpy(&bits, &t, sizeof bits);
    return (int64_t)(bits - (uint64_t)MAGIC_BITS);
}

#define QUANTA_OF_ROW(r, w)                                                                    \
    do {                                                                                       \
        const double w0_ = (w) * ax0[e], w1_ = (w) * ax1[e];                                   \
        q[(4 * (r) + 0) * n + e - e0] = quantize1(kq * w0_);                                   \
        q[(4 * (r) + 1) * n + e - e0] = quantize1(kqv * w0_);                                  \
        q[(4 * (r) + 2) * n + e - e0] = quantize1(kq * w1_);                                   \
        q[(4 * (r) + 3) * n + e - e0] = quantize1(kqv * w1_);                                  \
    } while (0)

/* (ivdep: the 16 streams of q, n apart, never overlap; without it GCC tests each pair's
 * overlap before the loop, too many tests, and leaves the loop scalar) */
#define ROW_QUANTA_BODY(vals)                                                                  \
    _Pragma("GCC ivdep") for (Py_ssize_t e = e0; e < e1; e++) {                                \
        const double kq = sgn * QUANTUM * mass[e];                                             \
        const double kqv = kq * ((double)(vals)[e] * inv_vmax);                                \
        QUANTA_OF_ROW(0, az0[e] * ay0[e]);                                                     \
        QUANTA_OF_ROW(1, az0[e] * ay1[e]);                                                     \
        QUANTA_OF_ROW(2, az1[e] * ay0[e]);                                                     \
        QUANTA_OF_ROW(3, az1[e] * ay1[e]);                                                     \
    }

VECTOR_CLONES static void row_quanta(const double *restrict ax0, const double *restrict ax1,
                                     const double *restrict ay0, const double *restrict ay1,
                                     const double *restrict az0, const double *restrict az1,
                                     const double *restrict mass, const void *values, int f64,
                                     double sgn, double inv_vmax, Py_ssize_t e0, Py_ssize_t e1,
                                     Py_ssize_t n, int64_t *restrict q)
{
    if (f64) {
        const double *restrict vd = values;
        ROW_QUANTA_BODY(vd)
    } else {
        const float *restrict vf = values;
        ROW_QUANTA_BODY(vf)
    }
}

/* cube[e]: voxel e is not still and its box covers 2 x 2 x 2 target voxels (so it is
 * kept); returns how many are */
VECTOR_CLONES static Py_ssize_t row_cubes(int32_t *const v0[3], int32_t *const v1[3],
                                          const unsigned char *restrict still, Py_ssize_t e0,
                                          Py_ssize_t e1, unsigned char *restrict cube)
{
    const int32_t *x0 = v0[0], *x1 = v1[0], *y0 = v0[1], *y1 = v1[1], *z0 = v0[2], *z1 = v1[2];
    Py_ssize_t count = 0;
    for (Py_ssize_t e = e0; e < e1; e++) {
        cube[e] = (x1[e] - x0[e] == 1) & (y1[e] - y0[e] == 1) & (z1[e] - z0[e] == 1) &
                  (still[e] == 0);
        count += cube[e];
    }
    return count;
}

/* A run of len cubes from voxel e of a piece (row_quanta's q, n apart) into its target
 * row r (row: the first cube's column): each cube's pair of side 0 at its column, of side
 * 1 at the next. One pass over the row: column j gets cube j's side 0 and cube j - 1's
 * side 1 (in two passes, the second 16 bytes off the first's stores, each load of the
 * second waited for those stores). */
static inline void add_run(int64_t *restrict row, const int64_t *restrict q, Py_ssize_t n,
                           int r, Py_ssize_t e, Py_ssize_t len)
{
    const int64_t *restrict a0 = q + (4 * r) * n + e, *restrict a1 = a0 + n;
    const int64_t *restrict b0 = a1 + n, *restrict b1 = b0 + n;
    row[0] += a0[0];
    row[1] += a1[0];
    for (Py_ssize_t j = 1; j < len; j++) {
        row[2 * j] += a0[j] + b0[j - 1];
        row[2 * j + 1] += a1[j] + b1[j - 1];
    }
    row[2 * len] += b0[len - 1];
    row[2 * len + 1] += b1[len - 1];
}

/* Still voxels [a, b) of a row whose x spans are one target column each, the columns
 * consecutive from x0 (a scan's grid warped onto itself: each still voxel is its own
 * target voxel), their y and z spans those of the row (trow, wrow: the nrow target rows
 * and their weights): the numbers of the per-voxel path (its mass, then add2's two
 * products, each rounded as quantize2 rounds), made as vectors a piece of QCHUNK voxels
 * at a time (k: 2 QCHUNK doubles). A warp with one point moved is mostly still voxels:
 * one at a time, they were most of its scatter. */
#define STILL_RUN_MIN 8 /* shorter stretches one voxel at a time: at oversample 2 every
                         * other still voxel is one column, alone, and a call for each
                         * made those warps' still voxels 1.6x slower */
VECTOR_CLONES static void still_run(int64_t *const trow[4], const double wrow[4], int nrow,
                                    const double *restrict xw, const double *restrict xa0,
                                    int64_t x0, const void *values, int f64, double sgn,
                                    double inv_vmax, double det_still, double yw, double zw,
                                    Py_ssize_t a, Py_ssize_t b, double *restrict k)
{
    double *restrict kq = k, *restrict kqv = k + QCHUNK;
    for (Py_ssize_t c0 = a; c0 < b; c0 += QCHUNK) {
        const Py_ssize_t m = MIN(QCHUNK, b - c0);
        for (Py_ssize_t j = 0; j < m; j++) {
            const double val = f64 ? ((const double *)values)[c0 + j]
                                   : (double)((const float *)values)[c0 + j];
            const double mass = det_still / (xw[c0 + j] * yw * zw); /* as row_boxes */
            kq[j] = sgn * QUANTUM * mass;
            kqv[j] = kq[j] * (val * inv_vmax);
        }
        for (int r = 0; r < nrow; r++) {
            int64_t *restrict row = trow[r] + 2 * (x0 + (c0 - a));
            const double wr = wrow[r];
            _Pragma("GCC ivdep") for (Py_ssize_t j = 0; j < m; j++) {
                const double w = wr * xa0[c0 + j];
                row[2 * j] += quantize1(kq[j] * w);
                row[2 * j + 1] += quantize1(kqv[j] * w);
            }
        }
    }
}

/* Phase 2 for one voxel: add kv times each overlap volume to the covered target voxels
 * (target plane z in slot z - rb of acc, less nz from nz on; line, plane: strides of y
 * and z in int64s). */
static inline int64_t *plane_at(int64_t *acc, int64_t z, Py_ssize_t rb, Py_ssize_t nz,
                                Py_ssize_t plane)
{
    int64_t slot = z - rb;
    return acc + (slot >= nz ? slot - nz : slot) * plane;
}

/* splat's common case, a box at most 2 target voxels wide on each axis: voxels [x0, x1]
 * (x1 - x0 <= 1) with overlaps ax0, ax1, and likewise y and z */
static inline void splat_narrow(int64_t *restrict acc, Py_ssize_t rb, Py_ssize_t nz,
                                Py_ssize_t line, Py_ssize_t plane, int64_t x0, int64_t x1,
                                double ax0, double ax1, int64_t y0, int64_t y1, double ay0,
                                double ay1, int64_t z0, int64_t z1, double az0, double az1,
                                v2d kv)
{
    const int two_x = x1 > x0;
    if (two_x && y1 > y0 && z1 > z0) { /* the usual box: 2 x 2 x 2 voxels, no loop */
        int64_t *p0 = plane_at(acc, z0, rb, nz, plane) + y0 * line + x0 * 2;
        int64_t *p1 = plane_at(acc, z0 + 1, rb, nz, plane) + y0 * line + x0 * 2;
        const v4d kv2 = {kv[0], kv[1], kv[0], kv[1]};
        double w = az0 * ay0;
        add4(p0, kv2, (v4d){w * ax0, w * ax0, w * ax1, w * ax1});
        w = az0 * ay1;
        add4(p0 + line, kv2, (v4d){w * ax0, w * ax0, w * ax1, w * ax1});
        w = az1 * ay0;
        add4(p1, kv2, (v4d){w * ax0, w * ax0, w * ax1, w * ax1});
        w = az1 * ay1;
        add4(p1 + line, kv2, (v4d){w * ax0, w * ax0, w * ax1, w * ax1});
        return;
    }
    for (int64_t dz = 0; dz <= z1 - z0; dz++) {
        int64_t *p = plane_at(acc, z0 + dz, rb, nz, plane) + y0 * line + x0 * 2;
        const double wz = dz ? az1 : az0;
        for (int64_t dy = 0; dy <= y1 - y0; dy++) {
            int64_t *row = p + dy * line;
            const double wzy = wz * (dy ? ay1 : ay0);
            if (two_x) {
                const double w0 = wzy * ax0, w1 = wzy * ax1;
                const v4d kv2 = {kv[0], kv[1], kv[0], kv[1]}, w2 = {w0, w0, w1, w1};
                add4(row, kv2, w2);
            } else {
                add2(row, kv, wzy * ax0);
            }
        }
    }
}

static inline void splat(int64_t *restrict acc, Py_ssize_t rb, Py_ssize_t nz, Py_ssize_t line,
                         Py_ssize_t plane, const Span *x, const Span *y, const Span *z, v2d kv)
{
    if (x->v1 - x->v0 <= 1 && y->v1 - y->v0 <= 1 && z->v1 - z->v0 <= 1) {
        splat_narrow(acc, rb, nz, line, plane, x->v0, x->v1, x->a0, x->a1, y->v0, y->v1, y->a0,
                     y->a1, z->v0, z->v1, z->a0, z->a1, kv);
        return;
    }
    /* a box over two voxels wide: overlaps computed as they go */
    for (int64_t tz = z->v0; tz <= z->v1; tz++) {
        double wz = MIN(z->hi, tz + 0.5) - MAX(z->lo, tz - 0.5);
        for (int64_t ty = y->v0; ty <= y->v1; ty++) {
            int64_t *row = plane_at(acc, tz, rb, nz, plane) + ty * line;
            double wzy = wz * (MIN(y->hi, ty + 0.5) - MAX(y->lo, ty - 0.5));
            for (int64_t tx = x->v0; tx <= x->v1; tx++)
                add2(row + 2 * tx, kv, wzy * (MIN(x->hi, tx + 0.5) - MAX(x->lo, tx - 0.5)));
        }
    }
}

/* Which voxels of a row, block columns [e_lo, e_lo + n), lie in still regions for pass
 * p: every control point of the regions their face centres reach (the voxel's 3x3x3
 * neighbourhood, clamped to the domain, which also covers the margin's extrapolation)
 * has zero offset, so their offsets are exactly 0. cb: the z and y regions that
 * neighbourhood reaches (c0, c1, b0, b1); ra[i], rb_[i]: the x regions of voxels e - 1
 * and e + 1 (clamped), relative to the first. Returns how many. */
static Py_ssize_t row_still(const Scatter *s, int p, const Py_ssize_t cb[4], const int32_t *ra,
                            const int32_t *rb_, unsigned char *fast, unsigned char *reg)
{
    const Py_ssize_t gx = s->gran[0];
    const Py_ssize_t rx = s->regions[0], ry = s->regions[1];
    const Py_ssize_t dx = s->dvx;
    const Py_ssize_t c0 = cb[0], c1 = cb[1], b0 = cb[2], b1 = cb[3];
    const Py_ssize_t e_lo = s->lo[0], n = s->hi[0] - e_lo;
    const Py_ssize_t a0 = MAX(e_lo - 1, 0) / gx, a1 = MIN(e_lo + n, dx - 1) / gx;
    for (Py_ssize_t a = a0; a <= a1; a++) {
        unsigned char all = 1;
        for (Py_ssize_t c = c0; c <= c1; c++)
            for (Py_ssize_t b = b0; b <= b1; b++)
                all &= s->still[((p * s->regions[2] + c) * ry + b) * rx + a];
        reg[a - a0] = all;
    }
    Py_ssize_t count = 0;
    for (Py_ssize_t i = 0; i < n; i++) {
        fast[i] = reg[ra[i]] & reg[rb_[i]];
        count += fast[i];
    }
    return count;
}

/* The cubes of a row's general voxels [i0, i1) added, run by run (row_quanta), piece by
 * piece; the kept voxels that are not cubes listed in others (for splat), their count
 * returned; touched: the target box the cubes reached, (x, y, z) lowest then highest. */
VECTOR_CLONES static Py_ssize_t scatter_cubes(int64_t *restrict acc, Py_ssize_t rb,
                                              Py_ssize_t nz, Py_ssize_t line, Py_ssize_t plane,
                                              int32_t *const v0[3], double *const a0[3],
                                              double *const a1[3], const double *mass,
                                              const void *values, int f64, double sgn,
                                              double inv_vmax, const unsigned char *keep,
                                              const unsigned char *cube, Py_ssize_t i0,
                                              Py_ssize_t i1, Py_ssize_t qn, int64_t *quanta,
                                              int32_t *others, int64_t touched[6])
{
    Py_ssize_t nothers = 0;
    touched[0] = touched[1] = touched[2] = IQUANTUM;
    touched[3] = touched[4] = touched[5] = -1;
    for (Py_ssize_t c0 = i0; c0 < i1; c0 += QCHUNK) {
        const Py_ssize_t c1 = MIN(c0 + QCHUNK, i1);
        row_quanta(a0[0], a1[0], a0[1], a1[1], a0[2], a1[2], mass, values, f64, sgn, inv_vmax,
                   c0, c1, qn, quanta);
        for (Py_ssize_t i = c0; i < c1;) {
            if (!cube[i]) {
                others[nothers] = (int32_t)i;
                nothers += keep[i] != 0;
                i++;
                continue;
            }
            /* a run: the cubes from i on at consecutive columns of the same rows and planes */
            const Py_ssize_t first = i;
            const int32_t X = v0[0][i], Y = v0[1][i], Z = v0[2][i];
            for (i++; i < c1 && cube[i] && v0[1][i] == Y && v0[2][i] == Z &&
                      v0[0][i] == X + (int32_t)(i - first);
                 i++)
                ;
            const Py_ssize_t len = i - first;
            int64_t *pz[2] = {plane_at(acc, Z, rb, nz, plane),
                              plane_at(acc, (int64_t)Z + 1, rb, nz, plane)};
            for (int r = 0; r < 4; r++)
                add_run(pz[r >> 1] + ((int64_t)Y + (r & 1)) * line + (int64_t)X * 2, quanta, qn,
                        r, first - c0, len);
            /* the next row of voxels adds to the row below these two: asked for now, its
             * lines reach the cache while this row runs (11% of the scatter's samples; the
             * warp 2-3% slower without, about this machine's noise; a prefetch never
             * faults, so a row past the accumulators' is asked for and never read) */
            for (int dz = 0; dz < 2; dz++) {
                /* (an address, not a pointer: it may lie past the accumulators) */
                const uintptr_t below = (uintptr_t)pz[dz] +
                                        (uintptr_t)((((int64_t)Y + 2) * line + (int64_t)X * 2) *
                                                    (int64_t)sizeof(int64_t));
                for (Py_ssize_t b = 0; b < 16 * (len + 1); b += 64)
                    __builtin_prefetch((const void *)(below + (uintptr_t)b), 1, 3);
            }
            touched[0] = MIN(touched[0], X);
            touched[1] = MIN(touched[1], Y);
            touched[2] = MIN(touched[2], Z);
            touched[3] = MAX(touched[3], X + len);
            touched[4] = MAX(touched[4], Y + 1);
            touched[5] = MAX(touched[5], Z + 1);
        }
    }
    return nothers;
}

VECTOR_CLONES static void scatter_run(Scatter *s)
{
    int64_t *restrict acc = s->acc;
    const Py_ssize_t tz0 = s->tz_lo, tz1 = s->tz_hi, rb = s->rb;
    const Py_ssize_t tx0 = s->tx_lo, tx1 = s->tx_hi, ty0 = s->ty_lo, ty1 = s->ty_hi;
    const Py_ssize_t tx = s->tx, ty = s->ty;
    const Py_ssize_t nz = s->nz;
    const Py_ssize_t sF = s->nxb, sG = s->nyb * s->nxb, cs = s->cstride;
    const double sx = s->scale[0], sy = s->scale[1], sz = s->scale[2];
    const double hx = 0.5 * sx, hy = 0.5 * sy, hz = 0.5 * sz;
    const Py_ssize_t e_lo = s->lo[0], e_hi = s->hi[0], n = e_hi - e_lo;
    const int npass = s->npass, box = s->box, f64 = s->values_f64;
    const double inv_vmax = s->inv_vmax;
    const int track = s->track;
    const Py_ssize_t line = tx * 2, plane = ty * tx * 2;
    const double bx = s->off[0];
    int64_t bx0 = IQUANTUM, by0 = IQUANTUM, bz0 = IQUANTUM, bx1 = -1, by1 = -1, bz1 = -1;
    int64_t touched[6]; /* scatter_cubes' box */
    /* row buffers: 7 doubles (boxes), 6 doubles and 6 int32 (their spans) and a Span
     * (still voxels' x) per voxel, a piece's 16 streams of quanta, still_run's x spans
     * and its piece's kq, kqv, a list, flags */
    const Py_ssize_t qn = MIN(n, QCHUNK) + QPAD; /* a stream of quanta, QPAD included */
    char *mem = malloc((size_t)n * (15 * sizeof(double) + sizeof(Span) + 10 * sizeof(int32_t) +
                                    5) + (size_t)qn * 16 * sizeof(int64_t) +
                       2 * QCHUNK * sizeof(double) + 8);
    if (!mem)
        return; /* the caller checks bbox[0] for this */
    double *xmin = (double *)mem, *xmax = xmin + n, *ymin = xmin + 2 * n, *ymax = xmin + 3 * n,
           *zmin = xmin + 4 * n, *zmax = xmin + 5 * n, *mass = xmin + 6 * n;
    double *sa0[3] = {xmin + 7 * n, xmin + 8 * n, xmin + 9 * n};
    double *sa1[3] = {xmin + 10 * n, xmin + 11 * n, xmin + 12 * n};
    Span *xstill = (Span *)(xmin + 13 * n);
    int32_t *ra = (int32_t *)(xstill + n), *rb_ = ra + n;
    int32_t *sv0[3] = {rb_ + n, rb_ + 2 * n, rb_ + 3 * n};
    int32_t *sv1[3] = {rb_ + 4 * n, rb_ + 5 * n, rb_ + 6 * n};
    /* (8-byte aligned: 13 n doubles, n Spans and 8 n int32 before it) */
    int64_t *quanta = (int64_t *)(rb_ + 7 * n);
    double *xw = (double *)(quanta + 16 * qn), *xa0 = xw + n, *kbuf = xa0 + n;
    int32_t *xend = (int32_t *)(kbuf + 2 * QCHUNK);
    int32_t *others = xend + n; /* a row's kept voxels not cubes */
    /* still flags per pass, kept while the rows reach the same z and y regions */
    unsigned char *fasts[2] = {(unsigned char *)(others + n), (unsigned char *)(others + n) + n};
    unsigned char *keep = fasts[1] + n, *cube = keep + n, *reg = cube + n; /* reg: up to n + 2 */
    Py_ssize_t known[2][4] = {{-1, -1, -1, -1}, {-1, -1, -1, -1}}, nknown[2] = {0, 0};
    /* Still voxels: offsets exactly 0, so the boxes of phase 1 are base -/+ half a voxel,
     * each side a function of one index, and the mass is sx (sy sz) over the box volume:
     * the same doubles that row_boxes computes from zeros (tested), found per axis once. */
    if (box && s->still) {
        const Py_ssize_t gx = s->gran[0], a0 = MAX(e_lo - 1, 0) / gx;
        for (Py_ssize_t i = 0; i < n; i++) {
            const Py_ssize_t e = e_lo + i;
            const double base = bx + sx * (int32_t)e;
            span_of(-hx + base, hx + base, tx0, tx1 - 1, &xstill[i]);
            ra[i] = (int32_t)(MAX(e - 1, 0) / gx - a0);
            rb_[i] = (int32_t)(MIN(e + 1, s->dvx - 1) / gx - a0);
            xw[i] = xstill[i].hi - xstill[i].lo;
            xa0[i] = xstill[i].a0;
        }
        for (Py_ssize_t i = n - 1; i >= 0; i--) /* (still_run's stretches) */
            xend[i] = xstill[i].v1 != xstill[i].v0 ? (int32_t)i
                      : i + 1 < n && xstill[i + 1].v1 == xstill[i + 1].v0 &&
                              xstill[i + 1].v0 == xstill[i].v0 + 1
                          ? xend[i + 1]
                          : (int32_t)(i + 1);
    }
    const double det_still = sx * (sy * sz);
    /* A domain voxel's box covers 2 x 2 x 2 target voxels in the usual case where it is
     * about a target voxel wide; half as wide (oversample 2), rarely: no runs looked for
     * (a 256^3 warp at oversample 2 was 3-5% slower for looking) */
    const int cubes_likely = sx > 0.75 && sy > 0.75 && sz > 0.75;
    for (Py_ssize_t g = s->lo[2]; g < s->hi[2]; g++) {
        const double bz = s->off[2] + sz * g;
        Span zstill;
        const int zok = span_of(-hz + bz, hz + bz, tz0, tz1 - 1, &zstill);
        for (Py_ssize_t f = s->lo[1]; f < s->hi[1]; f++) {
            const double by = s->off[1] + sy * f;
            const Py_ssize_t vrow = ((g - s->voz) * s->vy + f) * s->vx + e_lo;
            const void *row_values = /* (the row's first sample, for the run kernels) */
                (const char *)s->values + vrow * (f64 ? sizeof(double) : sizeof(float));
            const Py_ssize_t urow = ((g - s->oz + 1) * s->nyb + (f - s->oy + 1)) * s->nxb +
                                    e_lo - s->ox + 1;
            Span ystill;
            const int yzok = span_of(-hy + by, hy + by, ty0, ty1 - 1, &ystill) && zok;
            const double yw = ystill.hi - ystill.lo, zw = zstill.hi - zstill.lo;
            Py_ssize_t cb[4] = {0, 0, 0, 0};
            if (s->still) { /* the z and y regions the row's neighbourhood reaches */
                cb[0] = MAX(g - 1, 0) / s->gran[2];
                cb[1] = MIN(g + 1, s->vz - 1) / s->gran[2];
                cb[2] = MAX(f - 1, 0) / s->gran[1];
                cb[3] = MIN(f + 1, s->dvy - 1) / s->gran[1];
            }
            for (int p = 0; p < npass; p++) {
                unsigned char *fast = fasts[p];
                if (box && s->still && memcmp(cb, known[p], sizeof cb) != 0) {
                    nknown[p] = row_still(s, p, cb, ra, rb_, fast, reg);
                    memcpy(known[p], cb, sizeof cb);
                }
                const Py_ssize_t nfast = box && s->still ? nknown[p] : 0;
                const float *u = s->uh[p] + urow;
                const double sgn = p == 0 ? s->sign : -s->sign;
                if (!box) { /* nearest: map and round (ties down, see pushforward.py) */
                    for (Py_ssize_t i = 0; i < n; i++) {
                        double val = f64 ? ((const double *)s->values)[vrow + i]
                                         : (double)((const float *)s->values)[vrow + i];
                        int64_t x = ifloor(bx + sx * (e_lo + i) + u[i] + ROUND);
                        int64_t y = ifloor(by + u[cs + i] + ROUND);
                        int64_t z = ifloor(bz + u[2 * cs + i] + ROUND);
                        if (x < tx0 || y < ty0 || z < tz0 || x >= tx1 || y >= ty1 || z >= tz1)
                            continue;
                        v2d kv = {sgn * QUANTUM, sgn * QUANTUM * (val * inv_vmax)};
                        add2(plane_at(acc, z, rb, nz, plane) + y * line + x * 2, kv, 1.0);
                        if (track) {
                            bx0 = MIN(bx0, x); by0 = MIN(by0, y); bz0 = MIN(bz0, z);
                            bx1 = MAX(bx1, x); by1 = MAX(by1, y); bz1 = MAX(bz1, z);
                        }
                    }
                    continue;
                }
                /* boxes for the voxels between the row's first and last general one */
                Py_ssize_t i0 = 0, i1 = n, nothers = 0;
                int runs = 0; /* the row's cubes added in runs (scatter_cubes) */
                if (nfast) {
                    while (i0 < n && fast[i0])
                        i0++;
                    while (i1 > i0 && fast[i1 - 1])
                        i1--;
                }
                if (i1 > i0) {
                    row_boxes(u + i0, u + cs + i0, u + 2 * cs + i0, sF, sG, e_lo + i0, i1 - i0,
                              bx, by, bz, sx, sy, sz, xmin + i0, xmax + i0, ymin + i0,
                              ymax + i0, zmin + i0, zmax + i0, mass + i0);
                    row_spans(xmin + i0, xmax + i0, i1 - i0, (int32_t)tx0, (int32_t)tx1 - 1,
                              sv0[0] + i0, sv1[0] + i0, sa0[0] + i0, sa1[0] + i0);
                    row_spans(ymin + i0, ymax + i0, i1 - i0, (int32_t)ty0, (int32_t)ty1 - 1,
                              sv0[1] + i0, sv1[1] + i0, sa0[1] + i0, sa1[1] + i0);
                    row_spans(zmin + i0, zmax + i0, i1 - i0, (int32_t)tz0, (int32_t)tz1 - 1,
                              sv0[2] + i0, sv1[2] + i0, sa0[2] + i0, sa1[2] + i0);
                    row_keep(sv0, sv1, i0, i1, keep);
                    if (cubes_likely) { /* runs where most general voxels are cubes */
                        if (!nfast) /* (no still voxel in this row: row_cubes reads none) */
                            memset(fast + i0, 0, i1 - i0);
                        runs = 2 * row_cubes(sv0, sv1, fast, i0, i1, cube) >= i1 - i0;
                    }
                }
                if (runs) {
                    nothers = scatter_cubes(acc, rb, nz, line, plane, sv0, sa0, sa1, mass,
                                            row_values, f64, sgn, inv_vmax, keep, cube, i0, i1,
                                            qn, quanta, others, touched);
                    if (track) {
                        bx0 = MIN(bx0, touched[0]); by0 = MIN(by0, touched[1]);
                        bz0 = MIN(bz0, touched[2]); bx1 = MAX(bx1, touched[3]);
                        by1 = MAX(by1, touched[4]); bz1 = MAX(bz1, touched[5]);
                    }
                }
                /* still voxels of this row share their y and z spans: the (at most 4)
                 * target rows they reach and those rows' weights az * ay, as splat has */
                int64_t *trow[4];
                double wrow[4];
                int nrow = 0;
                const int narrow_yz = nfast && yzok && ystill.v1 - ystill.v0 <= 1 &&
                                      zstill.v1 - zstill.v0 <= 1;
                if (narrow_yz)
                    for (int64_t dz = 0; dz <= zstill.v1 - zstill.v0; dz++)
                        for (int64_t dy = 0; dy <= ystill.v1 - ystill.v0; dy++) {
                            trow[nrow] = plane_at(acc, zstill.v0 + dz, rb, nz, plane) +
                                         (ystill.v0 + dy) * line;
                            wrow[nrow++] = (dz ? zstill.a1 : zstill.a0) *
                                           (dy ? ystill.a1 : ystill.a0);
                        }
                /* Phase 2: overlaps with the target voxels, accumulated (a scatter: scalar):
                 * the still voxels and the general ones not in a run (a row without still
                 * voxels: those listed only) */
                const int listed = runs && !nfast;
                const Py_ssize_t nloop = listed ? nothers : n;
                for (Py_ssize_t k = 0; k < nloop; k++) {
                    const Py_ssize_t i = listed ? others[k] : k;
                    Span xs, ys, zs;
                    const Span *X = &xs, *Y = &ys, *Z = &zs;
                    double m;
                    if (nfast && fast[i]) {
                        X = &xstill[i];
                        Y = &ystill;
                        Z = &zstill;
                        if (!yzok || X->v1 < X->v0)
                            continue;
                        Py_ssize_t j = i; /* a stretch of one-column spans: [i, j) */
                        if (narrow_yz && !listed && xend[i] - i >= STILL_RUN_MIN)
                            for (j = i + 1; j < xend[i] && fast[j];)
                                j++;
                        if (j - i >= STILL_RUN_MIN) {
                            still_run(trow, wrow, nrow, xw, xa0, X->v0, row_values, f64, sgn,
                                      inv_vmax, det_still, yw, zw, i, j, kbuf);
                            if (track) {
                                bx0 = MIN(bx0, X->v0); by0 = MIN(by0, Y->v0);
                                bz0 = MIN(bz0, Z->v0); bx1 = MAX(bx1, xstill[j - 1].v1);
                                by1 = MAX(by1, Y->v1); bz1 = MAX(bz1, Z->v1);
                            }
                            k = j - 1; /* (not listed: k is i) */
                            continue;
                        }
                        m = det_still / ((X->hi - X->lo) * yw * zw); /* as row_boxes */
                        if (narrow_yz && X->v1 - X->v0 <= 1) { /* splat's common case */
                            double val = f64 ? ((const double *)s->values)[vrow + i]
                                             : (double)((const float *)s->values)[vrow + i];
                            double kq = sgn * QUANTUM * m;
                            const double kqv = kq * (val * inv_vmax);
                            if (X->v1 > X->v0) {
                                const v4d kv2 = {kq, kqv, kq, kqv};
                                for (int r = 0; r < nrow; r++) {
                                    const double w0 = wrow[r] * X->a0, w1 = wrow[r] * X->a1;
                                    const v4d w2 = {w0, w0, w1, w1};
                                    add4(trow[r] + X->v0 * 2, kv2, w2);
                                }
                            } else { /* (one column, not in a long enough stretch) */
                                const v2d kv = {kq, kqv};
                                for (int r = 0; r < nrow; r++)
                                    add2(trow[r] + X->v0 * 2, kv, wrow[r] * X->a0);
                            }
                            if (track) {
                                bx0 = MIN(bx0, X->v0); by0 = MIN(by0, Y->v0);
                                bz0 = MIN(bz0, Z->v0); bx1 = MAX(bx1, X->v1);
                                by1 = MAX(by1, Y->v1); bz1 = MAX(bz1, Z->v1);
                            }
                            continue;
                        }
                    } else { /* spans from row_spans, read in place */
                        if (!keep[i] || (runs && cube[i])) /* (a cube: added in its run) */
                            continue;
                        const int64_t x0 = sv0[0][i], x1 = sv1[0][i], y0 = sv0[1][i],
                                      y1 = sv1[1][i], z0 = sv0[2][i], z1 = sv1[2][i];
                        double val = f64 ? ((const double *)s->values)[vrow + i]
                                         : (double)((const float *)s->values)[vrow + i];
                        double kq = sgn * QUANTUM * mass[i];
                        v2d kv = {kq, kq * (val * inv_vmax)};
                        if (x1 - x0 <= 1 && y1 - y0 <= 1 && z1 - z0 <= 1) {
                            splat_narrow(acc, rb, nz, line, plane, x0, x1, sa0[0][i],
                                         sa1[0][i], y0, y1, sa0[1][i], sa1[1][i], z0, z1,
                                         sa0[2][i], sa1[2][i], kv);
                        } else {
                            xs = (Span){x0, x1, sa0[0][i], sa1[0][i], xmin[i], xmax[i]};
                            ys = (Span){y0, y1, sa0[1][i], sa1[1][i], ymin[i], ymax[i]};
                            zs = (Span){z0, z1, sa0[2][i], sa1[2][i], zmin[i], zmax[i]};
                            splat(acc, rb, nz, line, plane, &xs, &ys, &zs, kv);
                        }
                        if (track) {
                            bx0 = MIN(bx0, x0); by0 = MIN(by0, y0); bz0 = MIN(bz0, z0);
                            bx1 = MAX(bx1, x1); by1 = MAX(by1, y1); bz1 = MAX(bz1, z1);
                        }
                        continue;
                    }
                    double val = f64 ? ((const double *)s->values)[vrow + i]
                                     : (double)((const float *)s->values)[vrow + i];
                    double kq = sgn * QUANTUM * m;
                    v2d kv = {kq, kq * (val * inv_vmax)};
                    splat(acc, rb, nz, line, plane, X, Y, Z, kv);
                    if (track) {
                        bx0 = MIN(bx0, X->v0); by0 = MIN(by0, Y->v0); bz0 = MIN(bz0, Z->v0);
                        bx1 = MAX(bx1, X->v1); by1 = MAX(by1, Y->v1); bz1 = MAX(bz1, Z->v1);
                    }
                }
            }
        }
    }
    free(mem);
    s->bbox[0] = bx0; s->bbox[1] = by0; s->bbox[2] = bz0;
    s->bbox[3] = bx1; s->bbox[4] = by1; s->bbox[5] = bz1;
}

static PyObject *py_scatter(PyObject *self, PyObject *args)
{
    PyObject *o_uha, *o_uhb, *o_values, *o_acc, *o_still;
    Scatter s;
    int npass, box;
    Py_buffer b[5];
    int n = 0;
    long long sign;
    memset(&s, 0, sizeof s);
    int ring;
    Py_ssize_t vox, voy, ax, ay;
    if (!PyArg_ParseTuple(args, "OOi(nnn)O(nn)(ddd)(ddd)(nnn)(nnn)LdpO(nnnnnn)ppO(nnn)(nn)(nn)(nn)",
                          &o_uha,
                          &o_uhb, &npass, &s.ox, &s.oy, &s.oz, &o_values, &s.voz, &s.vz,
                          &s.off[0], &s.off[1],
                          &s.off[2], &s.scale[0], &s.scale[1], &s.scale[2], &s.lo[0], &s.lo[1],
                          &s.lo[2], &s.hi[0], &s.hi[1], &s.hi[2], &sign, &s.inv_vmax, &box,
                          &o_acc, &s.tx_lo, &s.tx_hi, &s.ty_lo, &s.ty_hi, &s.tz_lo, &s.tz_hi, &ring, &s.track, &o_still, &s.gran[0],
                          &s.gran[1], &s.gran[2], &vox, &voy, &s.dvx, &s.dvy, &ax, &ay))
        return NULL;
    if (get_buf(o_uha, &b[n++], READ, KIND(F32), 4, "uh") < 0 ||
        get_buf(o_uhb, &b[n++], READ, KIND(F32), 4, "uh_new") < 0 ||
        get_buf(o_values, &b[n++], READ, FLOATS, 3, "values") < 0 ||
        get_buf(o_acc, &b[n++], WRITE, KIND(I64), 4, "acc") < 0 ||
        (o_still != Py_None && get_buf(o_still, &b[n++], READ, KIND(U8), 4, "still") < 0)) {
        n--;
        goto fail;
    }
    if (o_still != Py_None) {
        s.still = b[4].buf;
        for (int k = 0; k < 3; k++)
            s.regions[k] = b[4].shape[3 - k];
    }
    s.sign = sign < 0 ? -1.0 : 1.0;
    s.npass = npass;
    s.box = box;
    s.uh[0] = b[0].buf;
    s.uh[1] = b[1].buf;
    s.cstride = b[0].shape[1] * b[0].shape[2] * b[0].shape[3];
    s.nyb = b[0].shape[2];
    s.nxb = b[0].shape[3];
    s.values_f64 = buf_kind(&b[2]) == F64;
    s.vy = b[2].shape[1];
    s.vx = b[2].shape[2];
    if (s.dvx < 0) /* the values are whole planes */
        s.dvx = s.vx;
    if (s.dvy < 0)
        s.dvy = s.vy;
    /* (the shifts are integers, applied as addresses: only in-range entries are read) */
    s.values = (const void *)((uintptr_t)b[2].buf -
                              (uintptr_t)((voy * s.vx + vox) * (s.values_f64 ? 8 : 4)));
    s.nz = b[3].shape[0];
    /* planes [tz_lo, tz_hi) held: from slot 0 on, or in a ring of nz slots (slot z mod nz) */
    s.rb = ring && s.nz > 0 ? s.tz_lo - s.tz_lo % s.nz : s.tz_lo;
    s.ty = b[3].shape[1];
    s.tx = b[3].shape[2];
    s.acc = (int64_t *)((uintptr_t)b[3].buf - (uintptr_t)((ay * s.tx + ax) * 2 * 8));
    /* the block, its one-voxel margin in uh, and the domain */
    int bad = npass < 1 || npass > 2 || (sign != 1 && sign != -1) || b[3].shape[3] != 2 ||
              b[0].shape[0] != 3 || s.tz_lo < 0 || s.tz_hi < s.tz_lo ||
              s.tz_hi - s.tz_lo > s.nz || s.tx_lo < ax || s.tx_hi < s.tx_lo ||
              s.tx_hi > ax + s.tx || s.ty_lo < ay || s.ty_hi < s.ty_lo || s.ty_hi > ay + s.ty ||
              ax < 0 || ay < 0 || vox < 0 || voy < 0;
    for (int k = 0; k < 4 && !bad; k++)
        bad = b[1].shape[k] != b[0].shape[k];
    Py_ssize_t org[3] = {s.ox, s.oy, s.oz};
    Py_ssize_t ub[3] = {b[0].shape[3], b[0].shape[2], b[0].shape[1]};
    Py_ssize_t vb[3] = {s.dvx, s.dvy, s.vz}; /* the domain */
    /* the block's planes, rows and columns are among those given */
    bad = bad || (s.lo[2] < s.hi[2] && (s.lo[2] < s.voz || s.hi[2] > s.voz + b[2].shape[0]));
    bad = bad || (s.lo[0] < s.hi[0] && (s.lo[0] < vox || s.hi[0] > vox + s.vx));
    bad = bad || (s.lo[1] < s.hi[1] && (s.lo[1] < voy || s.hi[1] > voy + s.vy));
    for (int k = 0; k < 3 && !bad; k++)
        bad = s.lo[k] < s.hi[k] && (s.lo[k] < 0 || s.hi[k] > vb[k] || s.lo[k] - org[k] < 0 ||
                                    s.hi[k] - org[k] + 2 > ub[k]);
    /* one still mask per pass; the regions tile the domain: regions * granularity = size */
    bad = bad || (s.still && b[4].shape[0] != npass);
    for (int k = 0; k < 3 && !bad && s.still; k++)
        bad = s.gran[k] < 1 || s.regions[k] * s.gran[k] != vb[k];
    if (bad) {
        PyErr_SetString(PyExc_ValueError, "scatter: block outside the domain or its buffers");
        goto fail;
    }
    s.bbox[3] = s.bbox[4] = s.bbox[5] = -1;
    if (s.lo[0] < s.hi[0] && s.lo[1] < s.hi[1] && s.lo[2] < s.hi[2]) {
        s.bbox[0] = -1; /* stays -1 only when the row buffers could not be allocated */
        Py_BEGIN_ALLOW_THREADS
        scatter_run(&s);
        Py_END_ALLOW_THREADS
        if (s.bbox[0] == -1) {
            PyErr_NoMemory();
            goto fail;
        }
    }
    release_all(b, n);
    return Py_BuildValue("(LLLLLL)", (long long)s.bbox[0], (long long)s.bbox[1],
                         (long long)s.bbox[2], (long long)s.bbox[3], (long long)s.bbox[4],
                         (long long)s.bbox[5]);
fail:
    release_all(b, n);
    return NULL;
}

/* The sample of a target voxel with weight w and weighted value v: v / w where
 * w >= COVERED_HI (inside the model), v + b (1 - w) where w <= COVERED_LO (its
 * silhouette), a linear ramp between. All three are computed, one kept: the same
 * value as evaluating only the one kept, and no branch in a vector loop. */
static inline double finalize_value(double w, double v, double background)
{
    const double inside = v / w, edge = v + background * (1.0 - w);
    const double t = (w - COVERED_LO) / (COVERED_HI - COVERED_LO);
    const double ramp = t * inside + (1.0 - t) * edge;
    return w >= COVERED_HI ? inside : (w <= COVERED_LO ? edge : ramp);
}

/* An int64 of magnitude below 2**51 as a double (exact): its bits added to those of
 * 1.5 * 2**52, less that number; integer and float vector operations only. */
static inline double small_int_to_double(int64_t x)
{
    int64_t bits = x + (int64_t)0x4338000000000000LL;
    double d;
    memcpy(&d, &bits, sizeof d);
    return d - 6755399441055744.0;
}

/* One row of n target voxels: acc pairs (weight, weighted value) to samples, the
 * accumulators cleared afterwards when asked. Rows whose sums all lie below 2**51 in
 * magnitude (every ordinary warp: a voxel's weight is about 1 in units of 2**40) are
 * converted as vectors, others one by one; the values are the same. */
#define FINALIZE_ROW(NAME, T)                                                                  \
    VECTOR_CLONES static void NAME(int64_t *restrict a, T *restrict o, Py_ssize_t n,          \
                                   double scale_w, double scale_v, double background,          \
                                   int clear)                                                  \
    {                                                                                          \
        const int64_t big = (int64_t)1 << 51;                                                  \
        int64_t far = 0;                                                                       \
        for (Py_ssize_t x = 0; x < 2 * n; x++)                                                 \
            far |= (a[x] >= big) | (a[x] <= -big);                                             \
        if (!far) {                                                                            \
            for (Py_ssize_t x = 0; x < n; x++)                                                 \
                o[x] = (T)finalize_value(small_int_to_double(a[2 * x]) * scale_w,              \
                                         small_int_to_double(a[2 * x + 1]) * scale_v,          \
                                         background);                                          \
        } else {                                                                               \
            for (Py_ssize_t x = 0; x < n; x++)                                                 \
                o[x] = (T)finalize_value((double)a[2 * x] * scale_w,                           \
                                         (double)a[2 * x + 1] * scale_v, background);          \
        }                                                                                      \
        if (clear) /* the accumulators are used again (a ring of planes) */                   \
            memset(a, 0, sizeof(int64_t) * 2 * (size_t)n);                                     \
    }

FINALIZE_ROW(finalize_row_f32, float)
FINALIZE_ROW(finalize_row_f64, double)

static PyObject *py_finalize(PyObject *self, PyObject *args)
{
    PyObject *o_acc, *o_out;
    double vmax, background;
    Py_ssize_t lo[3], hi[3];
    Py_buffer b[2];
    int n = 0;
    int clear = 0;
    if (!PyArg_ParseTuple(args, "Od(nnn)(nnn)Od|p", &o_acc, &vmax, &lo[0], &lo[1], &lo[2], &hi[0],
                          &hi[1], &hi[2], &o_out, &background, &clear))
        return NULL;
    if (get_buf(o_acc, &b[n++], clear ? WRITE : READ, KIND(I64), 4, "acc") < 0 ||
        get_buf(o_out, &b[n++], WRITE, FLOATS, 3, "out") < 0) {
        n--;
        goto fail;
    }
    /* acc and out share their y and x sizes; the block lies in both */
    Py_ssize_t nz = MIN(b[0].shape[0], b[1].shape[0]), ny = b[1].shape[1], nx = b[1].shape[2];
    int bad = b[0].shape[1] != ny || b[0].shape[2] != nx || b[0].shape[3] != 2;
    Py_ssize_t dims[3] = {nx, ny, nz};
    for (int k = 0; k < 3 && !bad; k++)
        bad = lo[k] < hi[k] && (lo[k] < 0 || hi[k] > dims[k]);
    if (bad) {
        PyErr_SetString(PyExc_ValueError, "finalize: block outside the accumulators");
        goto fail;
    }
    if (lo[0] < hi[0] && lo[1] < hi[1] && lo[2] < hi[2]) {
        int64_t *acc = b[0].buf;
        const double inv_q = 1.0 / QUANTUM;
        const int f32 = buf_kind(&b[1]) == F32;
        Py_BEGIN_ALLOW_THREADS
        for (Py_ssize_t z = lo[2]; z < hi[2]; z++)
            for (Py_ssize_t y = lo[1]; y < hi[1]; y++) {
                const Py_ssize_t at = (z * ny + y) * nx + lo[0];
                if (f32)
                    finalize_row_f32(acc + 2 * at, (float *)b[1].buf + at, hi[0] - lo[0],
                                     inv_q, inv_q * vmax, background, clear);
                else
                    finalize_row_f64(acc + 2 * at, (double *)b[1].buf + at, hi[0] - lo[0],
                                     inv_q, inv_q * vmax, background, clear);
            }
        Py_END_ALLOW_THREADS
    }
    release_all(b, n);
    Py_RETURN_NONE;
fail:
    release_all(b, n);
    return NULL;
}

/* ------------------------------------------------------------- label maps */
/* The one-pass label warp's loops (volwarp_cli/warp/labels.py, LabelStream): every
 * domain voxel of a label map pushed forward once, each of its contributions added to
 * the target voxel's total weight and to the weight of the voxel's own label there,
 * so that every label's weights come out of one pass whatever the number of labels.
 *
 * Exact: a contribution is the integer (2**-40 of a voxel's weight) that scatter_run
 * adds for the label's indicator, from the same helpers: row_boxes, row_spans,
 * row_still, the still voxels' shortcut, the same products in the same order (BOX_SIDE,
 * splat_narrow's and splat's overlaps, kv = (QUANTUM m, QUANTUM m inv_vmax) quantized
 * by quantize2). Integer sums do not depend on their order, so each label's weight at
 * a target voxel is the one a pass of the intensity scatter over that label's
 * indicator gives, and the total weight the one of the whole map's pass.
 *
 * The ring: target plane z in slot z - rb (less ring from ring on, rb a multiple of
 * ring), rows and columns from the window's (wy0, wx0): a voxel t has its total weight
 * wall[t], `slots` (code, weight) pairs head_l/head_w[t * slots ...] and a chain
 * head_next[t] of blocks of as many pairs more, from a pool shared by the ring (a
 * junction of many labels, a noisy map: nothing is dropped). A pool block is
 * (next, codes[slots], weights[slots]) int64s; state = (free list, blocks used,
 * blocks ever taken, blocks free). The scatter never grows the pool (it is Python's
 * array): before each row it checks that the pool holds a new block for every
 * contribution of a label the row can make, and otherwise returns the row to resume
 * from once the caller has grown it (a larger copy: block indices stay valid).
 * resolve_planes reads finished planes (winners, per-label totals and peaks) and
 * clears them, their chains back to the free list, for the ring's next turn.
 *
 * Label codes: 0 is the background (its voxels add to the total weight only), 1..n
 * the other labels in increasing id order, so comparing codes compares ids.
 *
 * Every index read from a buffer (codes, chain links, the free list) is checked
 * before use; a bad call or an inconsistent ring is a ValueError, never a stray
 * access. The GIL is released: the label shares run in threads. */

typedef struct {
    int64_t *wall;      /* [ring * ny * nx] total weight */
    int32_t *head_l;    /* [ring * ny * nx * slots] codes (0: free slot) */
    int64_t *head_w;    /* and weights */
    int32_t *head_next; /* [ring * ny * nx]: first chain block, -1 none */
    int64_t *pool;      /* [blocks * (2 slots + 1)] */
    int64_t *state;     /* free list, blocks used, blocks ever taken, blocks free */
    Py_ssize_t blocks, stride;
    int slots;
    int bad; /* a chain link or the free list outside the pool (a bad call) */
} LabelRing;

/* floor(a / b) for b > 0, as Python's // */
static inline Py_ssize_t floordiv(Py_ssize_t a, Py_ssize_t b)
{
    Py_ssize_t q = a / b;
    return q - ((a % b) != 0 && a < 0);
}

/* Add q to label `code` of voxel t beyond its own slots: in its chain, else in a new
 * block (from the free list, else from the pool's unused end). */
static void chain_add(LabelRing *r, Py_ssize_t t, int32_t code, int64_t q)
{
    const Py_ssize_t slots = r->slots, stride = r->stride, blocks = r->blocks;
    int64_t *pool = r->pool, *state = r->state;
    int64_t c = r->head_next[t], prev = -1;
    for (Py_ssize_t steps = 0; c >= 0; steps++) {
        if (c >= blocks || steps >= blocks) {
            r->bad = 1;
            return;
        }
        int64_t *b = pool + c * stride;
        for (Py_ssize_t s = 0; s < slots; s++) {
            if (b[1 + s] == code) {
                b[1 + slots + s] += q;
                return;
            }
            if (b[1 + s] == 0) {
                b[1 + s] = code;
                b[1 + slots + s] = q;
                return;
            }
        }
        prev = c;
        c = b[0];
    }
    int64_t blk;
    if (state[0] >= 0) {
        blk = state[0];
        if (blk >= blocks) {
            r->bad = 1;
            return;
        }
        state[0] = pool[blk * stride];
        state[3] -= 1;
    } else {
        blk = state[1];
        if (blk < 0 || blk >= blocks) { /* (the row's room was checked: cannot happen) */
            r->bad = 1;
            return;
        }
        state[1] += 1;
    }
    state[2] += 1;
    int64_t *b = pool + blk * stride;
    b[0] = -1;
    for (Py_ssize_t s = 0; s < slots; s++)
        b[1 + s] = 0;
    b[1] = code;
    b[1 + slots] = q;
    if (prev < 0)
        r->head_next[t] = (int32_t)blk;
    else
        pool[prev * stride] = blk;
}

/* A label's weight q at target voxel t, in one of its slots or in its chain (a
 * label's own pass adds no zero, so neither does this: no slot for it) */
static inline void label_slot(LabelRing *r, Py_ssize_t t, int32_t code, int64_t q)
{
    if (q == 0)
        return;
    const int slots = r->slots;
    int32_t *hl = r->head_l + t * slots;
    int64_t *hw = r->head_w + t * slots;
    for (int j = 0; j < slots; j++) {
        if (hl[j] == code) {
            hw[j] += q;
            return;
        }
        if (hl[j] == 0) {
            hl[j] = code;
            hw[j] = q;
            return;
        }
    }
    chain_add(r, t, code, q);
}

/* Where target voxels lie in the ring: plane z in slot z - rb, less ring from ring on;
 * rows and columns from (wy0, wx0). (Passed by value: kept in registers, not reloaded
 * after every store into the ring.) */
typedef struct {
    Py_ssize_t ring, rb, ny, nx, wy0, wx0;
} RingGeom;

/* the ring index of target voxel (0, y, z): add x */
static inline Py_ssize_t ring_row(RingGeom g, int64_t z, int64_t y)
{
    int64_t slot = z - g.rb;
    slot = slot >= g.ring ? slot - g.ring : slot;
    return (slot * g.ny + y - g.wy0) * g.nx - g.wx0;
}

/* One contribution to target voxel t: q[0] to its total weight, q[1] to its label's
 * (code 0, the background: to the total only) */
static inline void label_add(int64_t *restrict wall, LabelRing *r, Py_ssize_t t, int32_t code,
                             v2i q)
{
    wall[t] += q[0];
    if (code != 0)
        label_slot(r, t, code, q[1]);
}

/* splat_narrow for a label: voxels [x0, x1] (x1 - x0 <= 1) with overlaps ax0, ax1, and
 * likewise y and z; kv = (weight scale, label weight scale) */
static inline void label_narrow(int64_t *restrict wall, LabelRing *r, RingGeom g,
                                int32_t code, v2d kv, int64_t x0, int64_t x1, double ax0,
                                double ax1, int64_t y0, int64_t y1, double ay0, double ay1,
                                int64_t z0, int64_t z1, double az0, double az1)
{
    for (int64_t dz = 0; dz <= z1 - z0; dz++) {
        const double wz = dz ? az1 : az0;
        for (int64_t dy = 0; dy <= y1 - y0; dy++) {
            const double wzy = wz * (dy ? ay1 : ay0);
            const Py_ssize_t t = ring_row(g, z0 + dz, y0 + dy) + x0;
            label_add(wall, r, t, code, quantize2(kv * (wzy * ax0)));
            if (x1 > x0)
                label_add(wall, r, t + 1, code, quantize2(kv * (wzy * ax1)));
        }
    }
}

/* splat for a label: a box over two voxels wide, its overlaps as they go */
static void label_wide(int64_t *restrict wall, LabelRing *r, RingGeom g, int32_t code, v2d kv,
                       const Span *x, const Span *y, const Span *z)
{
    for (int64_t tz = z->v0; tz <= z->v1; tz++) {
        const double wz = MIN(z->hi, tz + 0.5) - MAX(z->lo, tz - 0.5);
        for (int64_t ty = y->v0; ty <= y->v1; ty++) {
            const double wzy = wz * (MIN(y->hi, ty + 0.5) - MAX(y->lo, ty - 0.5));
            const Py_ssize_t row = ring_row(g, tz, ty);
            for (int64_t tx = x->v0; tx <= x->v1; tx++)
                label_add(wall, r, row + tx, code,
                          quantize2(kv * (wzy * (MIN(x->hi, tx + 0.5) - MAX(x->lo, tx - 0.5)))));
        }
    }
}

typedef struct {
    const float *u; /* deformation offsets, planar [3][nzb][nyb][nxb], one-voxel margin */
    Py_ssize_t cs, nyb, nxb, ox, oy, oz;
    const int32_t *codes; /* [cnz][cny][cnx]: input voxel (cx, cy, cz) first */
    Py_ssize_t cny, cnx, cx, cy, cz, k, lead[3];
    double off[3], scale[3];
    Py_ssize_t lo[3], hi[3]; /* the block of domain voxels (x y z) */
    int box;
    double inv_vmax;
    Scatter still; /* row_still's fields (still NULL: no still regions) */
    Py_ssize_t tx0, tx1, ty0, ty1, tz0, tz1, ring, rb, wy0, wx0, ny, nx;
    const unsigned char *need; /* [ntz][nty][ntx] tiles of `tile` input voxels */
    Py_ssize_t nty, ntx, tile;
    Py_ssize_t start_f, start_g, stop_f, stop_g;
    LabelRing r;
} LabelScatter;

/* The pushforward of the block's rows from (start_f, start_g) on, rows in y order, each
 * through the block's planes (the rows of one y reach the same few target rows, which
 * stay in the cache while those of the next y, the oversample's, reach them too).
 * Leaves stop_f = -1 when done, else the row it stopped before, untouched (the pool
 * might not hold all that row can chain). Returns -1 when its row buffers could not be
 * allocated. */
static int label_scatter_run(LabelScatter *s)
{
    LabelRing *r = &s->r;
    const Py_ssize_t e0 = s->lo[0], n = s->hi[0] - e0, g0 = s->lo[2], g1 = s->hi[2];
    const Py_ssize_t f1 = s->hi[1], nzp = g1 - g0, k = s->k;
    const Py_ssize_t tx0 = s->tx0, tx1 = s->tx1, ty0 = s->ty0, ty1 = s->ty1, tz0 = s->tz0,
                     tz1 = s->tz1;
    const Py_ssize_t sF = s->nxb, sG = s->nyb * s->nxb, cs = s->cs;
    const double bx = s->off[0], sx = s->scale[0], sy = s->scale[1], sz = s->scale[2];
    const double hx = 0.5 * sx, hy = 0.5 * sy, hz = 0.5 * sz;
    const double inv_vmax = s->inv_vmax;
    const int box = s->box, has_still = box && s->still.still != NULL;
    const double det_still = sx * (sy * sz);
    /* nearest: weight 1, as scatter_run's (kv times 1.0) */
    const v2d kv_one = {QUANTUM, QUANTUM * (1.0 * inv_vmax)};
    const v2i q_one = quantize2(kv_one * 1.0);
    const RingGeom rg = {s->ring, s->rb, s->ny, s->nx, s->wy0, s->wx0};
    int64_t *const wall = r->wall;
    s->stop_f = s->stop_g = -1;
    /* per column: 7 doubles of boxes, 6 of overlaps and 4 of the still x sides and
     * overlaps; 6 int32 of spans, 2 of the still x spans, 2 of still regions; the input
     * column and its tile; flags. Per plane: the still z sides, spans and overlaps. */
    char *mem = malloc((size_t)n * (17 * sizeof(double) + 10 * sizeof(int32_t) +
                                    2 * sizeof(Py_ssize_t) + 4) +
                       (size_t)nzp * (4 * sizeof(double) + 2 * sizeof(int32_t)) + 64);
    if (!mem)
        return -1;
    double *xmin = (double *)mem, *xmax = xmin + n, *ymin = xmin + 2 * n, *ymax = xmin + 3 * n,
           *zmin = xmin + 4 * n, *zmax = xmin + 5 * n, *mass = xmin + 6 * n;
    double *sa0[3] = {xmin + 7 * n, xmin + 8 * n, xmin + 9 * n};
    double *sa1[3] = {xmin + 10 * n, xmin + 11 * n, xmin + 12 * n};
    double *xs_lo = xmin + 13 * n, *xs_hi = xmin + 14 * n, *xs_w0 = xmin + 15 * n,
           *xs_w1 = xmin + 16 * n;
    double *zs_lo = xmin + 17 * n, *zs_hi = zs_lo + nzp, *zs_w0 = zs_lo + 2 * nzp,
           *zs_w1 = zs_lo + 3 * nzp;
    Py_ssize_t *xi = (Py_ssize_t *)(zs_lo + 4 * nzp), *xt = xi + n;
    int32_t *sv0[3] = {(int32_t *)(xt + n), (int32_t *)(xt + n) + n, (int32_t *)(xt + n) + 2 * n};
    int32_t *sv1[3] = {sv0[2] + n, sv0[2] + 2 * n, sv0[2] + 3 * n};
    int32_t *xs_a = sv1[2] + n, *xs_b = xs_a + n, *ra = xs_b + n, *rb_ = ra + n;
    int32_t *zs_a = rb_ + n, *zs_b = zs_a + nzp;
    unsigned char *use = (unsigned char *)(zs_b + nzp), *fast = use + n, *reg = fast + n;
    /* (reg: row_still's x regions, up to n + 2, last) */
    memset(fast, 0, (size_t)n);
    for (Py_ssize_t i = 0; i < n; i++) {
        const Py_ssize_t e = e0 + i;
        xi[i] = floordiv(e - s->lead[0], k) - s->cx;
        xt[i] = floordiv(xi[i] + s->cx, s->tile);
        const double base = bx + sx * (int32_t)e;
        xs_lo[i] = -hx + base;
        xs_hi[i] = hx + base;
    }
    if (has_still) {
        const Py_ssize_t gx = s->still.gran[0], a0 = MAX(e0 - 1, 0) / gx;
        for (Py_ssize_t i = 0; i < n; i++) {
            const Py_ssize_t e = e0 + i;
            ra[i] = (int32_t)(MAX(e - 1, 0) / gx - a0);
            rb_[i] = (int32_t)(MIN(e + 1, s->still.dvx - 1) / gx - a0);
        }
    }
    /* the still voxels' x and z sides, spans and overlaps (base -/+ half a voxel) */
    row_spans(xs_lo, xs_hi, n, (int32_t)tx0, (int32_t)tx1 - 1, xs_a, xs_b, xs_w0, xs_w1);
    for (Py_ssize_t g = g0; g < g1; g++) {
        const double bz = s->off[2] + sz * g;
        zs_lo[g - g0] = -hz + bz;
        zs_hi[g - g0] = hz + bz;
    }
    row_spans(zs_lo, zs_hi, nzp, (int32_t)tz0, (int32_t)tz1 - 1, zs_a, zs_b, zs_w0, zs_w1);
    Py_ssize_t known[4] = {-1, -1, -1, -1}, nfast = 0;
    for (Py_ssize_t f = s->start_f; f < f1 && !r->bad; f++) {
        const double by = s->off[1] + sy * f;
        const Py_ssize_t yi = floordiv(f - s->lead[1], k) - s->cy, fu = f - s->oy + 1;
        const double ys_lo = -hy + by, ys_hi = hy + by;
        int32_t ys_a, ys_b;
        double ys_w0, ys_w1;
        row_spans(&ys_lo, &ys_hi, 1, (int32_t)ty0, (int32_t)ty1 - 1, &ys_a, &ys_b, &ys_w0,
                  &ys_w1);
        const Span ystill = {ys_a, ys_b, ys_w0, ys_w1, ys_lo, ys_hi};
        const double yw = ys_hi - ys_lo;
        for (Py_ssize_t g = f == s->start_f ? s->start_g : g0; g < g1 && !r->bad; g++) {
            const double bz = s->off[2] + sz * g;
            const Py_ssize_t zi = floordiv(g - s->lead[2], k) - s->cz, gu = g - s->oz + 1;
            const Py_ssize_t p_ = g - g0;
            const unsigned char *row_need =
                s->need + (floordiv(zi + s->cz, s->tile) * s->nty +
                           floordiv(yi + s->cy, s->tile)) * s->ntx;
            Py_ssize_t nuse = 0;
            for (Py_ssize_t i = 0; i < n; i++) {
                use[i] = row_need[xt[i]] != 0;
                nuse += use[i];
            }
            if (nuse == 0)
                continue; /* no voxel of the row can reach where a label lands */
            const int32_t *row_codes = s->codes + (zi * s->cny + yi) * s->cnx;
            if (has_still) { /* the voxels whose 3x3x3 neighbourhoods' regions are all still */
                const Py_ssize_t cb[4] = {MAX(g - 1, 0) / s->still.gran[2],
                                          MIN(g + 1, s->still.vz - 1) / s->still.gran[2],
                                          MAX(f - 1, 0) / s->still.gran[1],
                                          MIN(f + 1, s->still.dvy - 1) / s->still.gran[1]};
                if (memcmp(cb, known, sizeof cb) != 0) {
                    nfast = row_still(&s->still, 0, cb, ra, rb_, fast, reg);
                    memcpy(known, cb, sizeof cb);
                }
            }
            const float *u = s->u + (gu * s->nyb + fu) * s->nxb + e0 - s->ox + 1;
            const Py_ssize_t free_blocks = r->blocks - r->state[1] + r->state[3];
            if (!box) { /* nearest: map and round (ties down), weight 1 */
                if (n > free_blocks) {
                    s->stop_f = f;
                    s->stop_g = g;
                    break;
                }
                for (Py_ssize_t i = 0; i < n; i++) {
                    if (!use[i])
                        continue;
                    const double x = bx + sx * (e0 + i) + u[i] + ROUND;
                    const double y = by + u[cs + i] + ROUND;
                    const double z = bz + u[2 * cs + i] + ROUND;
                    /* (beyond 2**40: outside any target, and in ifloor's range) */
                    if (!(fabs(x) < 0x1p40 && fabs(y) < 0x1p40 && fabs(z) < 0x1p40))
                        continue;
                    const int64_t ix = ifloor(x), iy = ifloor(y), iz = ifloor(z);
                    if (ix < tx0 || iy < ty0 || iz < tz0 || ix >= tx1 || iy >= ty1 || iz >= tz1)
                        continue;
                    label_add(wall, r, ring_row(rg, iz, iy) + ix, row_codes[xi[i]], q_one);
                }
                continue;
            }
            /* phase 1: the general voxels' boxes (of each run of the row's voxels in needed
             * tiles, those between its first and last general one) and spans */
            for (Py_ssize_t i = 0; i < n;) {
                if (!use[i]) {
                    i++;
                    continue;
                }
                Py_ssize_t i0 = i;
                while (i < n && use[i])
                    i++;
                Py_ssize_t i1 = i;
                if (nfast) {
                    while (i0 < i1 && fast[i0])
                        i0++;
                    while (i1 > i0 && fast[i1 - 1])
                        i1--;
                }
                if (i1 <= i0)
                    continue;
                const Py_ssize_t m = i1 - i0;
                row_boxes(u + i0, u + cs + i0, u + 2 * cs + i0, sF, sG, e0 + i0, m, bx, by, bz,
                          sx, sy, sz, xmin + i0, xmax + i0, ymin + i0, ymax + i0, zmin + i0,
                          zmax + i0, mass + i0);
                row_spans(xmin + i0, xmax + i0, m, (int32_t)tx0, (int32_t)tx1 - 1, sv0[0] + i0,
                          sv1[0] + i0, sa0[0] + i0, sa1[0] + i0);
                row_spans(ymin + i0, ymax + i0, m, (int32_t)ty0, (int32_t)ty1 - 1, sv0[1] + i0,
                          sv1[1] + i0, sa0[1] + i0, sa1[1] + i0);
                row_spans(zmin + i0, zmax + i0, m, (int32_t)tz0, (int32_t)tz1 - 1, sv0[2] + i0,
                          sv1[2] + i0, sa0[2] + i0, sa1[2] + i0);
            }
            /* room in the pool for a new block per contribution of a label */
            const Span zstill = {zs_a[p_], zs_b[p_], zs_w0[p_], zs_w1[p_], zs_lo[p_], zs_hi[p_]};
            const int64_t nys = MAX(ystill.v1 - ystill.v0 + 1, 0),
                          nzs = MAX(zstill.v1 - zstill.v0 + 1, 0);
            int64_t room = 0;
            for (Py_ssize_t i = 0; i < n && room <= free_blocks; i++) {
                if (!use[i] || row_codes[xi[i]] == 0)
                    continue;
                if (nfast && fast[i])
                    room += MAX(xs_b[i] - xs_a[i] + 1, 0) * nys * nzs;
                else
                    room += (int64_t)MAX(sv1[0][i] - sv0[0][i] + 1, 0) *
                            MAX(sv1[1][i] - sv0[1][i] + 1, 0) * MAX(sv1[2][i] - sv0[2][i] + 1, 0);
            }
            if (room > free_blocks) {
                s->stop_f = f;
                s->stop_g = g;
                break;
            }
            /* phase 2: the overlaps with the target voxels, accumulated (narrow spans, of at
             * most two voxels, take the overlaps found above; wider ones compute them from
             * the box's sides: the same numbers) */
            const double zw = zstill.hi - zstill.lo;
            for (Py_ssize_t i = 0; i < n; i++) {
                if (!use[i])
                    continue;
                const int still = nfast && fast[i];
                int64_t x0, x1, y0, y1, z0, z1;
                double kq;
                if (still) { /* a still voxel: its box the affine image (no u read) */
                    x0 = xs_a[i], x1 = xs_b[i], y0 = ystill.v0, y1 = ystill.v1, z0 = zstill.v0,
                    z1 = zstill.v1;
                    /* (as row_boxes computes it from zero offsets) */
                    kq = QUANTUM * (det_still / ((xs_hi[i] - xs_lo[i]) * yw * zw));
                } else {
                    x0 = sv0[0][i], x1 = sv1[0][i], y0 = sv0[1][i], y1 = sv1[1][i], z0 = sv0[2][i],
                    z1 = sv1[2][i];
                    kq = QUANTUM * mass[i];
                }
                if (x1 < x0 || y1 < y0 || z1 < z0)
                    continue; /* (a degenerate box, or none of it in the window) */
                const int32_t code = row_codes[xi[i]];
                const v2d kv = {kq, kq * (1.0 * inv_vmax)};
                if (x1 - x0 <= 1 && y1 - y0 <= 1 && z1 - z0 <= 1) { /* splat_narrow's case */
                    if (still)
                        label_narrow(wall, r, rg, code, kv, x0, x1, xs_w0[i], xs_w1[i], y0, y1,
                                     ystill.a0, ystill.a1, z0, z1, zstill.a0, zstill.a1);
                    else
                        label_narrow(wall, r, rg, code, kv, x0, x1, sa0[0][i], sa1[0][i], y0, y1,
                                     sa0[1][i], sa1[1][i], z0, z1, sa0[2][i], sa1[2][i]);
                } else if (still) {
                    const Span xs = {x0, x1, xs_w0[i], xs_w1[i], xs_lo[i], xs_hi[i]};
                    label_wide(wall, r, rg, code, kv, &xs, &ystill, &zstill);
                } else {
                    const Span xs = {x0, x1, sa0[0][i], sa1[0][i], xmin[i], xmax[i]},
                               ys = {y0, y1, sa0[1][i], sa1[1][i], ymin[i], ymax[i]},
                               zs = {z0, z1, sa0[2][i], sa1[2][i], zmin[i], zmax[i]};
                    label_wide(wall, r, rg, code, kv, &xs, &ys, &zs);
                }
            }
        }
        if (s->stop_f >= 0)
            break;
    }
    free(mem);
    return 0;
}

/* A buffer's length (1-D) is at least a * b * c (all >= 0) */
static int holds(const Py_buffer *v, Py_ssize_t a, Py_ssize_t b, Py_ssize_t c)
{
    Py_ssize_t ab, abc;
    return a >= 0 && b >= 0 && c >= 0 && !__builtin_mul_overflow(a, b, &ab) &&
           !__builtin_mul_overflow(ab, c, &abc) && v->shape[0] >= abc;
}

/* The ring's buffers, checked: arguments wall, head_l, head_w, head_next, pool, state
 * (b[0..5]) for `size` voxels of `slots` pairs */
static int ring_of(Py_buffer *b, Py_ssize_t size, Py_ssize_t slots, LabelRing *r,
                   const char *name)
{
    r->wall = b[0].buf;
    r->head_l = b[1].buf;
    r->head_w = b[2].buf;
    r->head_next = b[3].buf;
    r->pool = b[4].buf;
    r->state = b[5].buf;
    r->slots = (int)slots;
    r->stride = 2 * slots + 1;
    r->blocks = slots >= 1 && slots < 1 << 20 ? b[4].shape[0] / r->stride : 0;
    r->bad = 0;
    const int64_t *st = r->state;
    if (slots < 1 || slots >= 1 << 20 || !holds(&b[0], size, 1, 1) ||
        !holds(&b[1], size, slots, 1) || !holds(&b[2], size, slots, 1) ||
        !holds(&b[3], size, 1, 1) || b[5].shape[0] != 4 || r->blocks > INT32_MAX ||
        st[0] < -1 || st[0] >= r->blocks || st[1] < 0 || st[1] > r->blocks || st[3] < 0 ||
        st[3] > st[1]) {
        PyErr_Format(PyExc_ValueError, "%s: ring buffers, pool or state inconsistent", name);
        return -1;
    }
    return 0;
}

static PyObject *py_scatter_labels(PyObject *self, PyObject *args)
{
    PyObject *o_u, *o_codes, *o_still, *o_need, *o_ring[6];
    Py_buffer b[10];
    int n = 0;
    LabelScatter s;
    memset(&s, 0, sizeof s);
    Py_ssize_t clip[6], block[6], dom[3], gran[3], slots;
    if (!PyArg_ParseTuple(args, "O(nnn)O(nnn)n(nnn)(ddd)(ddd)(nnnnnn)pdO(nnn)(nnn)(nnnnnn)n(nn)(nn)"
                          "OOOOOOnOn(nn)",
                          &o_u, &s.ox, &s.oy, &s.oz, &o_codes, &s.cx, &s.cy, &s.cz, &s.k,
                          &s.lead[0], &s.lead[1], &s.lead[2], &s.off[0], &s.off[1], &s.off[2],
                          &s.scale[0], &s.scale[1], &s.scale[2], &block[0], &block[1],
                          &block[2], &block[3], &block[4], &block[5], &s.box, &s.inv_vmax,
                          &o_still, &gran[0], &gran[1], &gran[2], &dom[0], &dom[1], &dom[2],
                          &clip[0], &clip[1], &clip[2], &clip[3], &clip[4], &clip[5], &s.ring,
                          &s.wy0, &s.wx0, &s.ny, &s.nx, &o_ring[0], &o_ring[1], &o_ring[2],
                          &o_ring[3], &o_ring[4], &o_ring[5], &slots, &o_need, &s.tile,
                          &s.start_f, &s.start_g))
        return NULL;
    static const int kinds[6] = {KIND(I64), KIND(I32), KIND(I64), KIND(I32), KIND(I64), KIND(I64)};
    static const char *names[6] = {"wall", "head_l", "head_w", "head_next", "pool", "state"};
    if (get_buf(o_u, &b[n++], READ, KIND(F32), 4, "u") < 0 ||
        get_buf(o_codes, &b[n++], READ, KIND(I32), 3, "codes") < 0 ||
        get_buf(o_still, &b[n++], READ, KIND(U8), 3, "still") < 0 ||
        get_buf(o_need, &b[n++], READ, KIND(U8), 3, "need") < 0) {
        n--;
        goto fail;
    }
    for (int j = 0; j < 6; j++)
        if (get_buf(o_ring[j], &b[n++], WRITE, kinds[j], 1, names[j]) < 0) {
            n--;
            goto fail;
        }
    for (int j = 0; j < 3; j++) {
        s.lo[j] = block[2 * j];
        s.hi[j] = block[2 * j + 1];
    }
    s.tx0 = clip[0], s.tx1 = clip[1], s.ty0 = clip[2], s.ty1 = clip[3], s.tz0 = clip[4],
    s.tz1 = clip[5];
    if (s.lo[0] >= s.hi[0] || s.lo[1] >= s.hi[1] || s.lo[2] >= s.hi[2]) {
        release_all(b, n); /* (an empty block: nothing to do) */
        return Py_BuildValue("(nn)", (Py_ssize_t)-1, (Py_ssize_t)-1);
    }
    Py_ssize_t size;
    int bad = s.ring < 1 || s.ny < 0 || s.nx < 0 || __builtin_mul_overflow(s.ring, s.ny, &size) ||
              __builtin_mul_overflow(size, s.nx, &size);
    if (bad || ring_of(&b[4], size, slots, &s.r, "scatter_labels") < 0) {
        if (bad)
            PyErr_SetString(PyExc_ValueError, "scatter_labels: bad ring shape");
        goto fail;
    }
    const Py_buffer *bu = &b[0], *bc = &b[1], *bs = &b[2], *bn = &b[3];
    s.u = bu->buf;
    s.nyb = bu->shape[2];
    s.nxb = bu->shape[3];
    s.cs = bu->shape[1] * bu->shape[2] * bu->shape[3];
    s.codes = bc->buf;
    s.cny = bc->shape[1];
    s.cnx = bc->shape[2];
    s.need = bn->buf;
    s.nty = bn->shape[1];
    s.ntx = bn->shape[2];
    const Py_ssize_t org[3] = {s.ox, s.oy, s.oz};
    const Py_ssize_t ub[3] = {bu->shape[3], bu->shape[2], bu->shape[1]};
    const Py_ssize_t cb[3] = {bc->shape[2], bc->shape[1], bc->shape[0]};
    const Py_ssize_t corg[3] = {s.cx, s.cy, s.cz};
    const Py_ssize_t nb[3] = {bn->shape[2], bn->shape[1], bn->shape[0]};
    /* target voxels: the clip within the ring's rows, columns and planes, every index
     * small enough for row_spans (int32, < 2**20) */
    bad = bu->shape[0] != 3 || s.k < 1 || s.tile < 1 || s.tx0 < s.wx0 || s.tx1 < s.tx0 ||
          s.tx1 > s.wx0 + s.nx || s.ty0 < s.wy0 || s.ty1 < s.ty0 || s.ty1 > s.wy0 + s.ny ||
          s.tz0 < 0 || s.tz1 < s.tz0 || s.tz1 - s.tz0 > s.ring;
    for (int j = 0; j < 6 && !bad; j++)
        bad = clip[j] < 0 || clip[j] > (1 << 20) - 3;
    /* the block within the domain, its offsets (with their one-voxel margin) in u, its
     * input voxels in codes and their tiles in need */
    for (int j = 0; j < 3 && !bad; j++) {
        const Py_ssize_t i0 = floordiv(s.lo[j] - s.lead[j], s.k),
                         i1 = floordiv(s.hi[j] - 1 - s.lead[j], s.k);
        bad = s.lo[j] < 0 || s.hi[j] > dom[j] || s.lo[j] - org[j] < 0 ||
              s.hi[j] - org[j] + 2 > ub[j] || i0 - corg[j] < 0 || i1 - corg[j] >= cb[j] ||
              floordiv(i0, s.tile) < 0 || floordiv(i1, s.tile) >= nb[j];
    }
    /* the still regions tile the domain (regions * granularity = size) */
    if (s.box && bs->shape[0] * bs->shape[1] * bs->shape[2] > 0) {
        s.still.still = bs->buf;
        for (int j = 0; j < 3; j++) {
            s.still.regions[j] = bs->shape[2 - j];
            s.still.gran[j] = gran[j];
            bad = bad || gran[j] < 1 || s.still.regions[j] * gran[j] != dom[j];
        }
        s.still.lo[0] = s.lo[0];
        s.still.hi[0] = s.hi[0];
        s.still.dvx = dom[0];
        s.still.dvy = dom[1];
        s.still.vz = dom[2];
    }
    bad = bad || s.start_f < s.lo[1] || s.start_f > s.hi[1] || s.start_g < s.lo[2] ||
          s.start_g > s.hi[2];
    if (bad) {
        PyErr_SetString(PyExc_ValueError,
                        "scatter_labels: block outside the domain or its buffers");
        goto fail;
    }
    s.rb = s.tz0 - s.tz0 % s.ring;
    int ok;
    Py_BEGIN_ALLOW_THREADS
    ok = label_scatter_run(&s);
    Py_END_ALLOW_THREADS
    if (ok < 0) {
        PyErr_NoMemory();
        goto fail;
    }
    if (s.r.bad) {
        PyErr_SetString(PyExc_ValueError, "scatter_labels: a chain or the free list leaves the "
                                          "pool (ring or state inconsistent)");
        goto fail;
    }
    release_all(b, n);
    return Py_BuildValue("(nn)", s.stop_f, s.stop_g);
fail:
    release_all(b, n);
    return NULL;
}

typedef struct {
    Py_ssize_t z0, z1, ring, wy0, wx0, ny, nx, oy, ox, ncodes, below;
    int32_t *out;
    int64_t *counts, *total_hi, *total_lo, *peak_w, *peak_at;
    LabelRing r;
} LabelResolve;

/* One (code, weight) of a voxel (z, y, x): its label's total and peak, the voxel's best */
static inline int resolve_one(LabelResolve *s, int64_t c, int64_t w, Py_ssize_t z, Py_ssize_t y,
                              Py_ssize_t x, int64_t *w_fg, int64_t *best_w, int64_t *best)
{
    if (c < 1 || c >= s->ncodes)
        return -1;
    *w_fg += w;
    s->total_lo[c] += w & (int64_t)0xFFFFFFFF;
    s->total_hi[c] += w >> 32;
    if (w > s->peak_w[c]) {
        s->peak_w[c] = w;
        s->peak_at[3 * c] = z;
        s->peak_at[3 * c + 1] = y + s->wy0;
        s->peak_at[3 * c + 2] = x + s->wx0;
    }
    if (w > *best_w || (w == *best_w && c < *best)) {
        *best_w = w;
        *best = c;
    }
    return 0;
}

/* Planes [z0, z1): each voxel's winner (largest weight, ties to the smaller code, the
 * background competing with max(w, 1) - w_fg), each label's total and first voxel of
 * largest weight; the planes cleared and their chains returned to the free list.
 * Returns -1 on a code or chain link outside its range. */
static int label_resolve_run(LabelResolve *s)
{
    LabelRing *r = &s->r;
    const Py_ssize_t slots = r->slots, stride = r->stride, ny = s->ny, nx = s->nx;
    int64_t *pool = r->pool, *state = r->state;
    for (Py_ssize_t z = s->z0; z < s->z1; z++) {
        const Py_ssize_t slot = z % s->ring;
        for (Py_ssize_t y = 0; y < ny; y++) {
            const Py_ssize_t row = (slot * ny + y) * nx;
            int32_t *out = s->out + ((z - s->z0) * s->oy + y) * s->ox;
            for (Py_ssize_t x = 0; x < nx; x++) {
                const Py_ssize_t t = row + x;
                const int64_t w_all = r->wall[t];
                int64_t w_fg = 0, best_w = -1, best = 0;
                r->wall[t] = 0;
                int32_t *hl = r->head_l + t * slots;
                const int64_t *hw = r->head_w + t * slots;
                for (Py_ssize_t j = 0; j < slots && hl[j] != 0; j++) {
                    if (resolve_one(s, hl[j], hw[j], z, y, x, &w_fg, &best_w, &best) < 0)
                        return -1;
                    hl[j] = 0;
                }
                int64_t blk = r->head_next[t];
                r->head_next[t] = -1;
                for (Py_ssize_t steps = 0; blk >= 0; steps++) {
                    if (blk >= r->blocks || steps >= r->blocks)
                        return -1;
                    int64_t *b = pool + blk * stride;
                    for (Py_ssize_t j = 0; j < slots && b[1 + j] != 0; j++)
                        if (resolve_one(s, b[1 + j], b[1 + slots + j], z, y, x, &w_fg, &best_w,
                                        &best) < 0)
                            return -1;
                    const int64_t next = b[0];
                    b[0] = state[0]; /* (back to the free list) */
                    state[0] = blk;
                    state[3] += 1;
                    blk = next;
                }
                const int64_t w_b = MAX(w_all, IQUANTUM) - w_fg;
                if (best != 0 && !(best_w > w_b || (best_w == w_b && best < s->below)))
                    best = 0;
                out[x] = (int32_t)best;
                s->counts[best] += 1;
            }
        }
    }
    return 0;
}

static PyObject *py_resolve_planes(PyObject *self, PyObject *args)
{
    PyObject *o_ring[6], *o_out, *o[5];
    Py_buffer b[12];
    int n = 0;
    LabelResolve s;
    memset(&s, 0, sizeof s);
    Py_ssize_t slots;
    if (!PyArg_ParseTuple(args, "nnn(nn)(nn)OOOOOOnnOOOOOO", &s.z0, &s.z1, &s.ring, &s.wy0,
                          &s.wx0, &s.ny, &s.nx, &o_ring[0], &o_ring[1], &o_ring[2], &o_ring[3],
                          &o_ring[4], &o_ring[5], &slots, &s.below, &o_out, &o[0], &o[1], &o[2],
                          &o[3], &o[4]))
        return NULL;
    static const int kinds[6] = {KIND(I64), KIND(I32), KIND(I64), KIND(I32), KIND(I64), KIND(I64)};
    static const char *names[6] = {"wall", "head_l", "head_w", "head_next", "pool", "state"};
    static const char *tnames[5] = {"counts", "total_hi", "total_lo", "peak_w", "peak_at"};
    for (int j = 0; j < 6; j++)
        if (get_buf(o_ring[j], &b[n++], WRITE, kinds[j], 1, names[j]) < 0) {
            n--;
            goto fail;
        }
    if (get_buf(o_out, &b[n++], WRITE, KIND(I32), 3, "out") < 0) {
        n--;
        goto fail;
    }
    for (int j = 0; j < 5; j++)
        if (get_buf(o[j], &b[n++], WRITE, KIND(I64), j == 4 ? 2 : 1, tnames[j]) < 0) {
            n--;
            goto fail;
        }
    Py_ssize_t size;
    int bad = s.ring < 1 || s.ny < 0 || s.nx < 0 || __builtin_mul_overflow(s.ring, s.ny, &size) ||
              __builtin_mul_overflow(size, s.nx, &size);
    if (bad || ring_of(b, size, slots, &s.r, "resolve_planes") < 0) {
        if (bad)
            PyErr_SetString(PyExc_ValueError, "resolve_planes: bad ring shape");
        goto fail;
    }
    const Py_buffer *bo = &b[6];
    s.out = bo->buf;
    s.oy = bo->shape[1];
    s.ox = bo->shape[2];
    s.ncodes = b[7].shape[0];
    s.counts = b[7].buf;
    s.total_hi = b[8].buf;
    s.total_lo = b[9].buf;
    s.peak_w = b[10].buf;
    s.peak_at = b[11].buf;
    bad = s.z0 < 0 || s.z1 < s.z0 || s.z1 - s.z0 > s.ring || s.z1 - s.z0 > bo->shape[0] ||
          s.oy < s.ny || s.ox < s.nx || s.ncodes < 1 || b[8].shape[0] != s.ncodes ||
          b[9].shape[0] != s.ncodes || b[10].shape[0] != s.ncodes ||
          b[11].shape[0] != s.ncodes || b[11].shape[1] != 3;
    if (bad) {
        PyErr_SetString(PyExc_ValueError, "resolve_planes: planes outside the ring or buffers "
                                          "of other sizes");
        goto fail;
    }
    int ok = 0;
    if (s.z1 > s.z0) {
        Py_BEGIN_ALLOW_THREADS
        ok = label_resolve_run(&s);
        Py_END_ALLOW_THREADS
    }
    if (ok < 0) {
        PyErr_SetString(PyExc_ValueError, "resolve_planes: a label code or a chain outside "
                                          "its range (ring or state inconsistent)");
        goto fail;
    }
    release_all(b, n);
    Py_RETURN_NONE;
fail:
    release_all(b, n);
    return NULL;
}

static PyMethodDef methods[] = {
    {"sample", py_sample, METH_VARARGS,
     "sample(data, x0, x1, fx, y0, y1, fy, z0, z1, fz, out, g0, g1) -> (min, max) (indices "
     "int32, weights float64): trilinear "
     "gather of out[g0:g1] at separable sample positions, and the range of what it wrote."},
    {"separable", py_separable, METH_VARARGS,
     "separable(dq, wx, wy, wz, x0, x1, y0, y1, z0, z1, out, ox, oy, oz): the spline "
     "offsets on a block of domain voxels, three 1-D passes."},
    {"scatter", py_scatter, METH_VARARGS,
     "scatter(uh, uh_new, npass, origin, values, (voz, dz), off, scale, lo, hi, sign, inv_vmax, "
     "box, "
     "acc, (tx_lo, tx_hi, ty_lo, ty_hi, tz_lo, tz_hi), ring, track, still, granularity, "
     "(values x0, y0), (domain columns, rows: -1 for the values'), (acc x0, y0)) -> "
     "touched box (x0, y0, z0, x1, y1, z1), empty unless track: add a block's pushforward to "
     "the target voxels in the window (still: uint8 [npass, Rz, Ry, Rx], regions whose "
     "control points have zero offsets, or None)."},
    {"scatter_labels", py_scatter_labels, METH_VARARGS,
     "scatter_labels(u, origin, codes, codes_origin, k, lead, off, scale, block, box, inv_vmax, "
     "still, granularity, domain, clip, ring, win_lo, win_shape, wall, head_l, head_w, "
     "head_next, pool, state, slots, need, tile, start) -> (f, g): push a block of a label "
     "map's domain voxels into the ring of target planes, every label's weights at once "
     "(-1, -1 when done; else the row to resume from once the pool has grown)."},
    {"resolve_planes", py_resolve_planes, METH_VARARGS,
     "resolve_planes(z0, z1, ring, win_lo, win_shape, wall, head_l, head_w, head_next, pool, "
     "state, slots, below, out, counts, total_hi, total_lo, peak_w, peak_at): the winning "
     "label codes of the ring's finished planes, each label's total and peak weight; the "
     "planes cleared."},
    {"finalize", py_finalize, METH_VARARGS,
     "finalize(acc, vmax, lo, hi, out, background, clear=False): accumulators to samples on "
     "a block (and, with clear, the block's accumulators back to zero)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_warpkernels",
    "The warp's inner loops (pullback, separable spline, box pushforward, finalize, the label "
    "maps' one pass) in C.", -1,
    methods, NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__warpkernels(void)
{
    PyObject *m = PyModule_Create(&module);
    const char *names[5] = {"QUANTUM", "ROUND", "COVERED_HI", "COVERED_LO", "GROW_BELOW"};
    const double values[5] = {QUANTUM, ROUND, COVERED_HI, COVERED_LO, GROW_BELOW};
    for (int k = 0; m && k < 5; k++) {
        PyObject *v = PyFloat_FromDouble(values[k]);
        if (!v || PyModule_AddObjectRef(m, names[k], v) < 0) {
            Py_XDECREF(v);
            Py_CLEAR(m);
        } else {
            Py_DECREF(v);
        }
    }
    return m;
}
