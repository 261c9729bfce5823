/* Sampling images and vector grids at continuous indices, as ITK does (module
 * volwarp_cli.transforms._applykernels): the inner loops of `volwarp apply` and of the
 * transforms' point maps.
 *
 * Why C and not numba like the rest of volwarp: `volwarp apply` is a one-shot command of
 * about a second, and numba cost half of it before any work (its import, the LLVM
 * start-up and loading each cached kernel). Compiled when the package is installed, these
 * kernels load in a millisecond.
 *
 * Indices are (x, y, z) continuous voxel indices. ITK's rules, checked against SimpleITK:
 * a point is inside an image's buffer when -0.5 <= i < n - 0.5 on every axis; linear
 * interpolation clamps the neighbours beyond the last sample to it; cubic B-spline
 * interpolation reads coefficients mirrored at the edges (-i, 2 (n - 1) - i: the caller
 * pads them); nearest rounds half up. The trilinear and the cubic sums are one function
 * each (trilinear, cubic_sum), whatever the array they read.
 *
 * Plain loops over points: the callers split the points over volwarp's threads, and each
 * point is computed on its own, so the result does not depend on the split. Every
 * function takes buffers (numpy arrays; the callers are apply.py, model.py and fields.py),
 * checks their types, shapes and lengths, and every index it reads, itself (a wrong call
 * is a Python exception, never a stray read or write), and releases the GIL while it runs.
 *
 * The arithmetic is the numba kernels' it replaced, operation for operation (float64
 * intermediates, the same order): built with -ffp-contract=off (no fused multiply-adds),
 * the results are the same bits.
 */

#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

/* ---------------------------------------------------------------- buffers */

#include "../_buffers.h"

/* A small argument (a 3-vector of int64 or float64, a 3x3 float64 matrix; any strides)
 * copied into `out`; int64 ones within +-INDEX_LIMIT. */
static int get_small(PyObject *o, int kind, int ndim, void *out, const char *name)
{
    Py_buffer v;
    if (get_buf(o, &v, STRIDED, KIND(kind), ndim, name) < 0)
        return -1;
    if (v.shape[0] != 3 || (ndim == 2 && v.shape[1] != 3)) {
        PyErr_Format(PyExc_ValueError, "%s: expected %s", name, ndim == 2 ? "3x3" : "3 values");
        PyBuffer_Release(&v);
        return -1;
    }
    const int cols = ndim == 2 ? 3 : 1;
    for (Py_ssize_t r = 0; r < 3; r++)
        for (Py_ssize_t c = 0; c < cols; c++) {
            const char *at = (const char *)v.buf + r * v.strides[0] + c * v.strides[ndim - 1];
            memcpy((char *)out + (r * cols + c) * 8, at, 8);
        }
    PyBuffer_Release(&v);
    for (int k = 0; kind == I64 && k < 3; k++)
        if (((int64_t *)out)[k] <= -INDEX_LIMIT || ((int64_t *)out)[k] >= INDEX_LIMIT) {
            PyErr_Format(PyExc_ValueError, "%s: an index beyond any grid", name);
            return -1;
        }
    return 0;
}

/* The count of points (N, 3), or -1. */
static Py_ssize_t points(const Py_buffer *v, const char *name)
{
    if (v->shape[1] != 3) {
        PyErr_Format(PyExc_ValueError, "%s: expected (N, 3) points", name);
        return -1;
    }
    return v->shape[0];
}

static int same_count(Py_ssize_t n, Py_ssize_t m, const char *fn)
{
    if (n == m)
        return 0;
    PyErr_Format(PyExc_ValueError, "%s: %zd points but room for %zd", fn, n, m);
    return -1;
}

/* ---------------------------------------------------------------- ITK's rules */

/* The per-point helpers are inlined whatever GCC's size heuristics say: GCC called axis
 * and trilinear as functions from the one-loop-per-type macros, and a linear sample took
 * 1.25x as long (12.5 against 10 ns a point, 160^3). */
#define HOT static inline __attribute__((always_inline))

HOT int64_t clamp(int64_t v, int64_t lo, int64_t hi)
{
    return v < lo ? lo : (v > hi ? hi : v);
}

HOT int inside(double x, double y, double z, const int64_t n[3])
{
    return x >= -0.5 && x < (double)n[0] - 0.5 && y >= -0.5 && y < (double)n[1] - 0.5 &&
           z >= -0.5 && z < (double)n[2] - 0.5;
}

/* The lower neighbour, the upper one (both clamped) and the upper's weight. */
typedef struct {
    int64_t b0, b1;
    double d;
} Axis;

HOT Axis axis(double x, int64_t n)
{
    int64_t b = (int64_t)floor(x);
    Axis a = {clamp(b, 0, n - 1), clamp(b + 1, 0, n - 1), x - (double)b};
    return a;
}

/* The first of the four indices a cubic B-spline at x weighs; their weights into w. */
HOT int64_t cubic_support(double x, double w[4])
{
    int64_t b = (int64_t)floor(x) - 1;
    double t = x - (double)b - 1.0, s = 1.0 - t;
    w[0] = s * s * s / 6.0;
    w[1] = (3.0 * t * t * t - 6.0 * t * t + 4.0) / 6.0;
    w[2] = (-3.0 * t * t * t + 3.0 * t * t + 3.0 * t + 1.0) / 6.0;
    w[3] = t * t * t / 6.0;
    return b;
}

/* The 4x4x4 values of float64 `a` from (bz, by, bx) (strides in elements) weighed. */
HOT double cubic_sum(const double *a, Py_ssize_t sz, Py_ssize_t sy, Py_ssize_t sx, int64_t bz,
                     int64_t by, int64_t bx, const double wz[4], const double wy[4],
                     const double wx[4])
{
    double acc = 0.0;
    for (int k = 0; k < 4; k++) {
        double s_y = 0.0;
        for (int j = 0; j < 4; j++) {
            const double *row = a + (bz + k) * sz + (by + j) * sy + bx * sx;
            double s_x = 0.0;
            for (int m = 0; m < 4; m++)
                s_x += wx[m] * row[m * sx];
            s_y += wy[j] * s_x;
        }
        acc += wz[k] * s_y;
    }
    return acc;
}

/* The eight neighbours v[z][y][x] (as float64) blended by the upper ones' weights. */
HOT double trilinear(const double v[2][2][2], double fz, double fy, double fx)
{
    double lo = (v[0][0][0] * (1 - fx) + v[0][0][1] * fx) * (1 - fy) +
                (v[0][1][0] * (1 - fx) + v[0][1][1] * fx) * fy;
    double hi = (v[1][0][0] * (1 - fx) + v[1][0][1] * fx) * (1 - fy) +
                (v[1][1][0] * (1 - fx) + v[1][1][1] * fx) * fy;
    return lo * (1 - fz) + hi * fz;
}

/* ---------------------------------------------------------------- image samples */

/* The image region's sizes (x, y, z) and where it starts in the whole (lo); the whole's
 * sizes (n). */
typedef struct {
    Py_ssize_t nx, ny, nz;
    int64_t lo[3], n[3];
} Region;

/* Trilinear samples, one loop per image type: the index of the first point whose
 * neighbours are outside the region (nothing written from it on), or -1. */
#define SAMPLE_LINEAR_FN(NAME, T)                                                             \
    static Py_ssize_t NAME(const T *img, const Region *r, const double *idx, Py_ssize_t count, \
                           double background, double *out)                                    \
    {                                                                                         \
        for (Py_ssize_t i = 0; i < count; i++) {                                              \
            double x = idx[3 * i], y = idx[3 * i + 1], z = idx[3 * i + 2];                    \
            if (!inside(x, y, z, r->n)) {                                                     \
                out[i] = background;                                                          \
                continue;                                                                     \
            }                                                                                 \
            Axis ax = axis(x, r->n[0]), ay = axis(y, r->n[1]), az = axis(z, r->n[2]);         \
            int64_t x0 = ax.b0 - r->lo[0], x1 = ax.b1 - r->lo[0];                             \
            int64_t y0 = ay.b0 - r->lo[1], y1 = ay.b1 - r->lo[1];                             \
            int64_t z0 = az.b0 - r->lo[2], z1 = az.b1 - r->lo[2];                             \
            if (x0 < 0 || y0 < 0 || z0 < 0 || x1 >= r->nx || y1 >= r->ny || z1 >= r->nz)      \
                return i;                                                                     \
            const T *p0 = img + z0 * r->ny * r->nx, *p1 = img + z1 * r->ny * r->nx;           \
            const double v[2][2][2] = {                                                       \
                {{p0[y0 * r->nx + x0], p0[y0 * r->nx + x1]},                                  \
                 {p0[y1 * r->nx + x0], p0[y1 * r->nx + x1]}},                                 \
                {{p1[y0 * r->nx + x0], p1[y0 * r->nx + x1]},                                  \
                 {p1[y1 * r->nx + x0], p1[y1 * r->nx + x1]}}};                                \
            out[i] = trilinear(v, az.d, ay.d, ax.d);                                          \
        }                                                                                     \
        return -1;                                                                            \
    }

SAMPLE_LINEAR_FN(linear_i8, int8_t)
SAMPLE_LINEAR_FN(linear_u8, uint8_t)
SAMPLE_LINEAR_FN(linear_i16, int16_t)
SAMPLE_LINEAR_FN(linear_u16, uint16_t)
SAMPLE_LINEAR_FN(linear_i32, int32_t)
SAMPLE_LINEAR_FN(linear_u32, uint32_t)
SAMPLE_LINEAR_FN(linear_i64, int64_t)
SAMPLE_LINEAR_FN(linear_u64, uint64_t)
SAMPLE_LINEAR_FN(linear_f32, float)
SAMPLE_LINEAR_FN(linear_f64, double)

/* Nearest samples copy the image's items: one loop per item size (their bits, whatever
 * the type); as the linear loops otherwise. */
#define SAMPLE_NEAREST_FN(NAME, T)                                                            \
    static Py_ssize_t NAME(const T *img, const Region *r, const double *idx, Py_ssize_t count, \
                           T background, T *out)                                              \
    {                                                                                         \
        for (Py_ssize_t i = 0; i < count; i++) {                                              \
            double x = idx[3 * i], y = idx[3 * i + 1], z = idx[3 * i + 2];                    \
            if (!inside(x, y, z, r->n)) {                                                     \
                out[i] = background;                                                          \
                continue;                                                                     \
            }                                                                                 \
            int64_t ix = clamp((int64_t)floor(x + 0.5), 0, r->n[0] - 1) - r->lo[0];           \
            int64_t iy = clamp((int64_t)floor(y + 0.5), 0, r->n[1] - 1) - r->lo[1];           \
            int64_t iz = clamp((int64_t)floor(z + 0.5), 0, r->n[2] - 1) - r->lo[2];           \
            if (ix < 0 || iy < 0 || iz < 0 || ix >= r->nx || iy >= r->ny || iz >= r->nz)      \
                return i;                                                                     \
            out[i] = img[(iz * r->ny + iy) * r->nx + ix];                                     \
        }                                                                                     \
        return -1;                                                                            \
    }

SAMPLE_NEAREST_FN(nearest_8, uint8_t)
SAMPLE_NEAREST_FN(nearest_16, uint16_t)
SAMPLE_NEAREST_FN(nearest_32, uint32_t)
SAMPLE_NEAREST_FN(nearest_64, uint64_t)

/* Cubic B-spline samples from float64 coefficients padded by the caller: as the linear
 * loops. */
static Py_ssize_t cubic(const double *coef, const Region *r, const double *idx,
                        Py_ssize_t count, double background, double *out)
{
    double wx[4], wy[4], wz[4];
    for (Py_ssize_t i = 0; i < count; i++) {
        double x = idx[3 * i], y = idx[3 * i + 1], z = idx[3 * i + 2];
        if (!inside(x, y, z, r->n)) {
            out[i] = background;
            continue;
        }
        int64_t bx = cubic_support(x, wx) - r->lo[0];
        int64_t by = cubic_support(y, wy) - r->lo[1];
        int64_t bz = cubic_support(z, wz) - r->lo[2];
        if (bx < 0 || by < 0 || bz < 0 || bx + 3 >= r->nx || by + 3 >= r->ny || bz + 3 >= r->nz)
            return i;
        out[i] = cubic_sum(coef, r->ny * r->nx, r->nx, 1, bz, by, bx, wz, wy, wx);
    }
    return -1;
}

enum { LINEAR, NEAREST, CUBIC };

static const char *const sample_names[3] = {"sample_linear", "sample_nearest", "sample_cubic"};

/* sample_*(img, idx, lo, n, background, out): the three wrappers' checks, then the loop. */
static PyObject *sample(PyObject *args, int method)
{
    const char *fn = sample_names[method];
    PyObject *o_img, *o_idx, *o_lo, *o_n, *o_bg, *o_out;
    Py_buffer b[3], bg;
    int nb = 0;
    Region r;
    if (!PyArg_ParseTuple(args, "OOOOOO", &o_img, &o_idx, &o_lo, &o_n, &o_bg, &o_out))
        return NULL;
    int img_kinds = method == CUBIC ? KIND(F64) : ALL_KINDS;
    if (get_buf(o_img, &b[nb++], READ, img_kinds, 3, "img") < 0 ||
        get_buf(o_idx, &b[nb++], READ, KIND(F64), 2, "idx") < 0) {
        nb--;
        goto fail;
    }
    const int kind = buf_kind(&b[0]);
    const int out_kinds = method == NEAREST ? KIND(kind) : KIND(F64);
    if (get_buf(o_out, &b[nb++], WRITE, out_kinds, 1, "out") < 0) {
        nb--;
        goto fail;
    }
    Py_ssize_t count = points(&b[1], "idx");
    if (count < 0 || same_count(count, b[2].shape[0], fn) < 0 ||
        get_small(o_lo, I64, 1, r.lo, "lo") < 0 || get_small(o_n, I64, 1, r.n, "n") < 0)
        goto fail;
    r.nz = b[0].shape[0];
    r.ny = b[0].shape[1];
    r.nx = b[0].shape[2];
    double background = 0.0;
    union {
        uint8_t u8;
        uint16_t u16;
        uint32_t u32;
        uint64_t u64;
    } item = {0};
    if (method == NEAREST) { /* one item of the image's type */
        if (PyObject_GetBuffer(o_bg, &bg, PyBUF_STRIDES | PyBUF_FORMAT) < 0)
            goto fail;
        int same = buf_kind(&bg) == kind && bg.len == bg.itemsize;
        if (same)
            memcpy(&item, bg.buf, bg.itemsize);
        PyBuffer_Release(&bg);
        if (!same) {
            PyErr_Format(PyExc_TypeError, "%s: background: expected one %s", fn,
                         kind_name(kind));
            goto fail;
        }
    } else {
        background = PyFloat_AsDouble(o_bg);
        if (background == -1.0 && PyErr_Occurred())
            goto fail;
    }
    const void *img = b[0].buf;
    const double *idx = b[1].buf;
    void *out = b[2].buf;
    Py_ssize_t bad = -1;
    Py_BEGIN_ALLOW_THREADS
    if (method == CUBIC) {
        bad = cubic(img, &r, idx, count, background, out);
    } else if (method == NEAREST) {
        switch (b[0].itemsize) {
        case 1: bad = nearest_8(img, &r, idx, count, item.u8, out); break;
        case 2: bad = nearest_16(img, &r, idx, count, item.u16, out); break;
        case 4: bad = nearest_32(img, &r, idx, count, item.u32, out); break;
        default: bad = nearest_64(img, &r, idx, count, item.u64, out); break;
        }
    } else {
        switch (kind) {
        case I8: bad = linear_i8(img, &r, idx, count, background, out); break;
        case U8: bad = linear_u8(img, &r, idx, count, background, out); break;
        case I16: bad = linear_i16(img, &r, idx, count, background, out); break;
        case U16: bad = linear_u16(img, &r, idx, count, background, out); break;
        case I32: bad = linear_i32(img, &r, idx, count, background, out); break;
        case U32: bad = linear_u32(img, &r, idx, count, background, out); break;
        case I64: bad = linear_i64(img, &r, idx, count, background, out); break;
        case U64: bad = linear_u64(img, &r, idx, count, background, out); break;
        case F32: bad = linear_f32(img, &r, idx, count, background, out); break;
        default: bad = linear_f64(img, &r, idx, count, background, out); break;
        }
    }
    Py_END_ALLOW_THREADS
    if (bad >= 0) {
        PyErr_Format(PyExc_IndexError, "%s: point %zd reads outside the image's region", fn,
                     bad);
        goto fail;
    }
    release_all(b, nb);
    Py_RETURN_NONE;
fail:
    release_all(b, nb);
    return NULL;
}

static PyObject *py_sample_linear(PyObject *self, PyObject *args)
{
    return sample(args, LINEAR);
}

static PyObject *py_sample_nearest(PyObject *self, PyObject *args)
{
    return sample(args, NEAREST);
}

static PyObject *py_sample_cubic(PyObject *self, PyObject *args)
{
    return sample(args, CUBIC);
}

/* ---------------------------------------------------------------- transforms */

static PyObject *py_bspline_cubic(PyObject *self, PyObject *args)
{
    PyObject *o_coef, *o_idx, *o_out;
    Py_buffer b[3];
    int nb = 0;
    if (!PyArg_ParseTuple(args, "OOO", &o_coef, &o_idx, &o_out))
        return NULL;
    if (get_buf(o_coef, &b[nb++], READ, KIND(F64), 4, "coef") < 0 ||
        get_buf(o_idx, &b[nb++], READ, KIND(F64), 2, "idx") < 0 ||
        get_buf(o_out, &b[nb++], WRITE, KIND(F64), 2, "out") < 0) {
        nb--;
        goto fail;
    }
    Py_ssize_t count = points(&b[1], "idx");
    if (count < 0 || points(&b[2], "out") < 0 ||
        same_count(count, b[2].shape[0], "bspline_cubic") < 0)
        goto fail;
    if (b[0].shape[3] != 3) {
        PyErr_SetString(PyExc_ValueError, "bspline_cubic: coef: expected (z, y, x, 3)");
        goto fail;
    }
    const double *coef = b[0].buf, *idx = b[1].buf;
    double *out = b[2].buf;
    const Py_ssize_t nz = b[0].shape[0], ny = b[0].shape[1], nx = b[0].shape[2];
    Py_BEGIN_ALLOW_THREADS
    double wx[4], wy[4], wz[4];
    for (Py_ssize_t i = 0; i < count; i++) {
        double x = idx[3 * i], y = idx[3 * i + 1], z = idx[3 * i + 2];
        out[3 * i] = out[3 * i + 1] = out[3 * i + 2] = 0.0;
        /* ITK's valid region [1, n - 2): the 4x4x4 support lies in the grid */
        if (!(x >= 1.0 && x < (double)nx - 2.0 && y >= 1.0 && y < (double)ny - 2.0 &&
              z >= 1.0 && z < (double)nz - 2.0))
            continue;
        int64_t bx = cubic_support(x, wx), by = cubic_support(y, wy), bz = cubic_support(z, wz);
        for (int c = 0; c < 3; c++)
            out[3 * i + c] = cubic_sum(coef + c, 3 * ny * nx, 3 * nx, 3, bz, by, bx, wz, wy, wx);
    }
    Py_END_ALLOW_THREADS
    release_all(b, nb);
    Py_RETURN_NONE;
fail:
    release_all(b, nb);
    return NULL;
}

/* affine (about 0): out = m @ p + o; affine_about (about 1): out = m @ (p - o), in ITK's
 * order (ImageBase::TransformPhysicalPointToContinuousIndex: the origin off first, then
 * each row's products summed from the first, vnl's matrix times vector) */
static PyObject *affine_impl(PyObject *args, int about, const char *name)
{
    PyObject *o_p, *o_m, *o_o, *o_out;
    Py_buffer b[2];
    int nb = 0;
    double m[9], o[3];
    if (!PyArg_ParseTuple(args, "OOOO", &o_p, &o_m, &o_o, &o_out))
        return NULL;
    if (get_buf(o_p, &b[nb++], READ, KIND(F64), 2, "p") < 0 ||
        get_buf(o_out, &b[nb++], WRITE, KIND(F64), 2, "out") < 0) {
        nb--;
        goto fail;
    }
    Py_ssize_t count = points(&b[0], "p");
    if (count < 0 || points(&b[1], "out") < 0 || same_count(count, b[1].shape[0], name) < 0 ||
        get_small(o_m, F64, 2, m, "m") < 0 || get_small(o_o, F64, 1, o, about ? "c" : "o") < 0)
        goto fail;
    const double *p = b[0].buf;
    double *out = b[1].buf;
    Py_BEGIN_ALLOW_THREADS
    if (about) {
        for (Py_ssize_t i = 0; i < count; i++) {
            double x = p[3 * i] - o[0], y = p[3 * i + 1] - o[1], z = p[3 * i + 2] - o[2];
            for (int r = 0; r < 3; r++)
                out[3 * i + r] = m[3 * r] * x + m[3 * r + 1] * y + m[3 * r + 2] * z;
        }
    } else {
        for (Py_ssize_t i = 0; i < count; i++) {
            double x = p[3 * i], y = p[3 * i + 1], z = p[3 * i + 2];
            for (int r = 0; r < 3; r++)
                out[3 * i + r] = m[3 * r] * x + m[3 * r + 1] * y + m[3 * r + 2] * z + o[r];
        }
    }
    Py_END_ALLOW_THREADS
    release_all(b, nb);
    Py_RETURN_NONE;
fail:
    release_all(b, nb);
    return NULL;
}

static PyObject *py_affine(PyObject *self, PyObject *args)
{
    return affine_impl(args, 0, "affine");
}

static PyObject *py_affine_about(PyObject *self, PyObject *args)
{
    return affine_impl(args, 1, "affine_about");
}

static PyObject *py_grid_points(PyObject *self, PyObject *args)
{
    PyObject *o_lo, *o_hi, *o_m, *o_o, *o_out;
    Py_buffer out_buf;
    int64_t lo[3], hi[3];
    double m[9], o[3];
    if (!PyArg_ParseTuple(args, "OOOOO", &o_lo, &o_hi, &o_m, &o_o, &o_out))
        return NULL;
    if (get_small(o_lo, I64, 1, lo, "lo") < 0 || get_small(o_hi, I64, 1, hi, "hi") < 0 ||
        get_small(o_m, F64, 2, m, "m") < 0 || get_small(o_o, F64, 1, o, "o") < 0 ||
        get_buf(o_out, &out_buf, WRITE, KIND(F64), 2, "out") < 0)
        return NULL;
    /* the rows out needs: the sizes' product, compared by divisions (it may overflow) */
    int64_t size[3], rows = out_buf.shape[0];
    for (int k = 0; k < 3; k++)
        size[k] = hi[k] > lo[k] ? hi[k] - lo[k] : 0;
    int fits = size[0] && size[1] && size[2]
                   ? rows % size[0] == 0 && rows / size[0] % size[1] == 0 &&
                         rows / size[0] / size[1] == size[2]
                   : rows == 0;
    if (!fits) {
        char count[32];
        PyOS_snprintf(count, sizeof count, "%.0f",
                      (double)size[0] * (double)size[1] * (double)size[2]);
        PyErr_Format(PyExc_ValueError, "grid_points: %s points but room for %zd", count, rows);
    }
    if (!fits || points(&out_buf, "out") < 0) {
        PyBuffer_Release(&out_buf);
        return NULL;
    }
    double *out = out_buf.buf;
    Py_BEGIN_ALLOW_THREADS
    Py_ssize_t n = 0;
    for (int64_t k = lo[2]; k < hi[2]; k++)
        for (int64_t j = lo[1]; j < hi[1]; j++)
            for (int64_t i = lo[0]; i < hi[0]; i++, n++)
                /* ITK's order (ImageBase::TransformIndexToPhysicalPoint: the origin first):
                 * a point on an edge of a B-spline's valid region falls as in ITK */
                for (int r = 0; r < 3; r++)
                    out[3 * n + r] = o[r] + m[3 * r] * (double)i + m[3 * r + 1] * (double)j +
                                     m[3 * r + 2] * (double)k;
    Py_END_ALLOW_THREADS
    PyBuffer_Release(&out_buf);
    Py_RETURN_NONE;
}

/* ---------------------------------------------------------------- fields */

static PyObject *py_interleave(PyObject *self, PyObject *args)
{
    PyObject *o[4];
    Py_buffer b[4];
    int nb = 0;
    static const char *const names[4] = {"a", "b", "c", "out"};
    if (!PyArg_ParseTuple(args, "OOOO", &o[0], &o[1], &o[2], &o[3]))
        return NULL;
    for (; nb < 4; nb++)
        if (get_buf(o[nb], &b[nb], nb == 3 ? WRITE : READ, FLOATS, nb == 3 ? 4 : 3,
                    names[nb]) < 0)
            goto fail;
    int bad = b[3].shape[3] != 3;
    for (int k = 0; k < 3; k++) {
        bad |= buf_kind(&b[k]) != buf_kind(&b[3]);
        for (int d = 0; d < 3; d++)
            bad |= b[k].shape[d] != b[3].shape[d];
    }
    if (bad) {
        PyErr_SetString(PyExc_ValueError,
                        "interleave: expected three (z, y, x) planes and out (z, y, x, 3), "
                        "all of one type");
        goto fail;
    }
    const Py_ssize_t count = b[0].len / b[0].itemsize;
    Py_BEGIN_ALLOW_THREADS
    if (b[3].itemsize == 4) { /* (the items' bits, as they are) */
        const uint32_t *x = b[0].buf, *y = b[1].buf, *z = b[2].buf;
        uint32_t *out = b[3].buf;
        for (Py_ssize_t i = 0; i < count; i++) {
            out[3 * i] = x[i];
            out[3 * i + 1] = y[i];
            out[3 * i + 2] = z[i];
        }
    } else {
        const uint64_t *x = b[0].buf, *y = b[1].buf, *z = b[2].buf;
        uint64_t *out = b[3].buf;
        for (Py_ssize_t i = 0; i < count; i++) {
            out[3 * i] = x[i];
            out[3 * i + 1] = y[i];
            out[3 * i + 2] = z[i];
        }
    }
    Py_END_ALLOW_THREADS
    release_all(b, nb);
    Py_RETURN_NONE;
fail:
    release_all(b, nb);
    return NULL;
}

/* A field's vectors (z, y, x, 3) with any strides (in bytes). */
typedef struct {
    const char *base;
    Py_ssize_t nz, ny, nx;
    Py_ssize_t sz, sy, sx, sc;
} Vectors;

/* Component c of the vector at (z, y, x), as float64. */
#define AT(v, T, z, y, x, c)                                                                  \
    ((double)*(const T *)((v)->base + (z) * (v)->sz + (y) * (v)->sy + (x) * (v)->sx +         \
                          (c) * (v)->sc))

static void vectors_of(const Py_buffer *b, Vectors *v)
{
    v->base = b->buf;
    v->nz = b->shape[0];
    v->ny = b->shape[1];
    v->nx = b->shape[2];
    v->sz = b->strides[0];
    v->sy = b->strides[1];
    v->sx = b->strides[2];
    v->sc = b->strides[3];
}

/* A tile's extremes into tmin, tmax (3 components at `at`): lo..hi of component c, or
 * nothing where hi < lo (no number: every sample NaN, the lanes' start values kept). */
static inline void merge_range(double *tmin, double *tmax, Py_ssize_t at, const double lo[3],
                               const double hi[3])
{
    for (int c = 0; c < 3; c++)
        if (hi[c] >= lo[c]) {
            if (!(tmin[at + c] <= lo[c]))
                tmin[at + c] = lo[c];
            if (!(tmax[at + c] >= hi[c]))
                tmax[at + c] = hi[c];
        }
}

/* Per-tile extremes, NaN skipped. Vectors of interleaved rows (x, then c, contiguous):
 * each x-tile's 3 * tile samples of a row fold, lane by lane, into a row of lanes of its
 * own (`a < lo ? a : lo` skips a NaN a: the SIMD min's rule; the loops vectorise), and
 * the lanes fold into components as a row of tiles ends; 8x faster than a sample at a
 * time (which had a division and two stores per sample). Other strides: that way. */
#define TILE_RANGE_FN(NAME, T)                                                                \
    static int NAME(const Vectors *v, Py_ssize_t tile, Py_ssize_t ty_n, Py_ssize_t tx_n,      \
                    double *tmin, double *tmax)                                               \
    {                                                                                         \
        if (v->sc != (Py_ssize_t)sizeof(T) || v->sx != 3 * (Py_ssize_t)sizeof(T)) {           \
            for (Py_ssize_t z = 0; z < v->nz; z++)                                            \
                for (Py_ssize_t y = 0; y < v->ny; y++)                                        \
                    for (Py_ssize_t x = 0; x < v->nx; x++) {                                  \
                        const Py_ssize_t at =                                                 \
                            (((z / tile) * ty_n + y / tile) * tx_n + x / tile) * 3;           \
                        double lo[3], hi[3];                                                  \
                        for (int c = 0; c < 3; c++)                                           \
                            lo[c] = hi[c] = AT(v, T, z, y, x, c);                             \
                        merge_range(tmin, tmax, at, lo, hi); /* (NaN: hi < lo is false too) */ \
                    }                                                                         \
            return 0;                                                                         \
        }                                                                                     \
        if (tx_n == 0 || v->nz == 0 || v->ny == 0)                                            \
            return 0;                                                                         \
        /* a tile beyond every axis is one tile a grid: as the largest axis (the same tiles; \
         * the lanes, and the sums below, then stay within the grid's sizes) */              \
        const Py_ssize_t most = v->nz > v->ny ? (v->nz > v->nx ? v->nz : v->nx)              \
                                              : (v->ny > v->nx ? v->ny : v->nx);             \
        if (tile > most)                                                                      \
            tile = most;                                                                      \
        const Py_ssize_t lanes = 3 * tile;                                                    \
        T *lo = malloc(2 * (size_t)(tx_n * lanes) * sizeof(T));                               \
        if (!lo)                                                                              \
            return -1;                                                                        \
        T *hi = lo + tx_n * lanes;                                                            \
        for (Py_ssize_t z0 = 0; z0 < v->nz; z0 += tile)                                       \
            for (Py_ssize_t y0 = 0; y0 < v->ny; y0 += tile) {                                 \
                for (Py_ssize_t k = 0; k < tx_n * lanes; k++) {                               \
                    lo[k] = (T)INFINITY;                                                      \
                    hi[k] = -(T)INFINITY;                                                     \
                }                                                                             \
                for (Py_ssize_t z = z0; z < z0 + tile && z < v->nz; z++)                      \
                    for (Py_ssize_t y = y0; y < y0 + tile && y < v->ny; y++) {                \
                        const T *row = (const T *)(v->base + z * v->sz + y * v->sy);          \
                        for (Py_ssize_t t = 0; t < tx_n; t++) {                               \
                            const T *p = row + t * lanes;                                     \
                            T *l = lo + t * lanes, *h = hi + t * lanes;                       \
                            const Py_ssize_t n = t < tx_n - 1 ? lanes : 3 * v->nx - t * lanes; \
                            for (Py_ssize_t k = 0; k < n; k++) {                              \
                                const T a = p[k];                                             \
                                l[k] = a < l[k] ? a : l[k];                                   \
                                h[k] = a > h[k] ? a : h[k];                                   \
                            }                                                                 \
                        }                                                                     \
                    }                                                                         \
                const Py_ssize_t row = ((z0 / tile) * ty_n + y0 / tile) * tx_n;               \
                for (Py_ssize_t t = 0; t < tx_n; t++) {                                       \
                    double l3[3] = {INFINITY, INFINITY, INFINITY};                            \
                    double h3[3] = {-INFINITY, -INFINITY, -INFINITY};                         \
                    for (Py_ssize_t k = 0; k < lanes; k++) {                                  \
                        const double a = lo[t * lanes + k], b = hi[t * lanes + k];            \
                        l3[k % 3] = a < l3[k % 3] ? a : l3[k % 3];                            \
                        h3[k % 3] = b > h3[k % 3] ? b : h3[k % 3];                            \
                    }                                                                         \
                    merge_range(tmin, tmax, (row + t) * 3, l3, h3);                           \
                }                                                                             \
            }                                                                                 \
        free(lo);                                                                             \
        return 0;                                                                             \
    }

TILE_RANGE_FN(tile_range_f32, float)
TILE_RANGE_FN(tile_range_f64, double)

static PyObject *py_tile_range(PyObject *self, PyObject *args)
{
    PyObject *o_vec, *o_min, *o_max;
    Py_ssize_t tile;
    Py_buffer b[3];
    int nb = 0;
    if (!PyArg_ParseTuple(args, "OnOO", &o_vec, &tile, &o_min, &o_max))
        return NULL;
    if (get_buf(o_vec, &b[nb++], STRIDED, FLOATS, 4, "vec") < 0 ||
        get_buf(o_min, &b[nb++], WRITE, KIND(F64), 4, "tmin") < 0 ||
        get_buf(o_max, &b[nb++], WRITE, KIND(F64), 4, "tmax") < 0) {
        nb--;
        goto fail;
    }
    if (tile < 1) {
        PyErr_SetString(PyExc_ValueError, "tile_range: tile must be positive");
        goto fail;
    }
    int bad = b[0].shape[3] != 3;
    for (int d = 0; d < 4; d++) {
        Py_ssize_t tiles = d < 3 ? b[0].shape[d] / tile + (b[0].shape[d] % tile != 0) : 3;
        bad |= b[1].shape[d] != tiles || b[2].shape[d] != tiles;
    }
    if (bad) {
        PyErr_SetString(PyExc_ValueError,
                        "tile_range: expected vec (z, y, x, 3) and tmin, tmax (tiles z, y, x, 3)");
        goto fail;
    }
    Vectors v;
    vectors_of(&b[0], &v);
    const int f32 = buf_kind(&b[0]) == F32;
    int failed;
    Py_BEGIN_ALLOW_THREADS
    if (f32)
        failed = tile_range_f32(&v, tile, b[1].shape[1], b[1].shape[2], b[1].buf, b[2].buf);
    else
        failed = tile_range_f64(&v, tile, b[1].shape[1], b[1].shape[2], b[1].buf, b[2].buf);
    Py_END_ALLOW_THREADS
    release_all(b, nb);
    if (failed)
        return PyErr_NoMemory();
    Py_RETURN_NONE;
fail:
    release_all(b, nb);
    return NULL;
}

/* A point this near a node along an axis (in voxels) does not take a non-finite vector
 * from the node on the other side: a field's grid and the points' grid that are the same
 * grid, read back from headers of float32 numbers (a NIfTI's origin), lie up to about
 * 1e-5 voxel apart, and a NaN node (no preimage, as `warp --grid grow` exports) one voxel
 * beyond the finite ones took every point on that face to the background with a weight
 * of 1e-6. Finite neighbours are weighed as always (the same bytes). */
#define NEAR_NODE 1e-4

/* The corner values n8 where one is not finite: along each axis, a point within NEAR_NODE
 * of a node takes that side's values for both (the other side's weight is below it). */
static void near_nodes(double n8[2][2][2], double dz, double dy, double dx)
{
    for (int a = 0; a < 2; a++)
        for (int b = 0; b < 2; b++) {
            if (dx < NEAR_NODE)
                n8[a][b][1] = n8[a][b][0];
            else if (dx > 1 - NEAR_NODE)
                n8[a][b][0] = n8[a][b][1];
        }
    for (int a = 0; a < 2; a++)
        for (int c = 0; c < 2; c++) {
            if (dy < NEAR_NODE)
                n8[a][1][c] = n8[a][0][c];
            else if (dy > 1 - NEAR_NODE)
                n8[a][0][c] = n8[a][1][c];
        }
    for (int b = 0; b < 2; b++)
        for (int c = 0; c < 2; c++) {
            if (dz < NEAR_NODE)
                n8[1][b][c] = n8[0][b][c];
            else if (dz > 1 - NEAR_NODE)
                n8[0][b][c] = n8[1][b][c];
        }
}

/* The grid's map: world to index (inv, origin), the whole grid's sizes (n, x y z) and the
 * window's first index (offset). */
typedef struct {
    double inv[9], origin[3];
    int64_t offset[3], n[3];
} FieldFrame;

#define FIELD_MAP_FN(NAME, T)                                                                 \
    static Py_ssize_t NAME(const Vectors *v, const FieldFrame *f, const double *p,            \
                           Py_ssize_t count, double *out)                                     \
    {                                                                                         \
        const double *inv = f->inv;                                                           \
        Py_ssize_t first = -1;                                                                \
        for (Py_ssize_t i = 0; i < count; i++) {                                              \
            double px = p[3 * i], py = p[3 * i + 1], pz = p[3 * i + 2];                       \
            double dx = px - f->origin[0], dy = py - f->origin[1], dz = pz - f->origin[2];    \
            double x = inv[0] * dx + inv[1] * dy + inv[2] * dz;                               \
            double y = inv[3] * dx + inv[4] * dy + inv[5] * dz;                               \
            double z = inv[6] * dx + inv[7] * dy + inv[8] * dz;                               \
            if (!inside(x, y, z, f->n)) {                                                     \
                out[3 * i] = px;                                                              \
                out[3 * i + 1] = py;                                                          \
                out[3 * i + 2] = pz;                                                          \
                continue;                                                                     \
            }                                                                                 \
            Axis ax = axis(x, f->n[0]), ay = axis(y, f->n[1]), az = axis(z, f->n[2]);         \
            /* the whole grid's neighbours, clamped to the window */                          \
            int64_t x0 = clamp(ax.b0 - f->offset[0], 0, v->nx - 1);                          \
            int64_t x1 = clamp(ax.b1 - f->offset[0], 0, v->nx - 1);                          \
            int64_t y0 = clamp(ay.b0 - f->offset[1], 0, v->ny - 1);                          \
            int64_t y1 = clamp(ay.b1 - f->offset[1], 0, v->ny - 1);                          \
            int64_t z0 = clamp(az.b0 - f->offset[2], 0, v->nz - 1);                          \
            int64_t z1 = clamp(az.b1 - f->offset[2], 0, v->nz - 1);                          \
            double u[3];                                                                      \
            for (int c = 0; c < 3; c++) {                                                     \
                double n8[2][2][2] = {                                                        \
                    {{AT(v, T, z0, y0, x0, c), AT(v, T, z0, y0, x1, c)},                      \
                     {AT(v, T, z0, y1, x0, c), AT(v, T, z0, y1, x1, c)}},                     \
                    {{AT(v, T, z1, y0, x0, c), AT(v, T, z1, y0, x1, c)},                      \
                     {AT(v, T, z1, y1, x0, c), AT(v, T, z1, y1, x1, c)}}};                    \
                u[c] = trilinear(n8, az.d, ay.d, ax.d);                                       \
                if (!(fabs(u[c]) < INFINITY)) { /* a non-finite node: maybe one left out */   \
                    near_nodes(n8, az.d, ay.d, ax.d);                                         \
                    u[c] = trilinear(n8, az.d, ay.d, ax.d);                                   \
                }                                                                             \
            }                                                                                 \
            out[3 * i] = px + u[0];                                                           \
            out[3 * i + 1] = py + u[1];                                                       \
            out[3 * i + 2] = pz + u[2];                                                       \
            if (!(fabs(u[0] + u[1] + u[2]) < INFINITY) && first < 0) /* a NaN or an inf */    \
                first = i;                                                                    \
        }                                                                                     \
        return first;                                                                         \
    }

FIELD_MAP_FN(field_map_f32, float)
FIELD_MAP_FN(field_map_f64, double)

static PyObject *py_field_map(PyObject *self, PyObject *args)
{
    PyObject *o_vec, *o_p, *o_inv, *o_origin, *o_offset, *o_n, *o_out;
    Py_buffer b[3];
    int nb = 0;
    FieldFrame f;
    if (!PyArg_ParseTuple(args, "OOOOOOO", &o_vec, &o_p, &o_inv, &o_origin, &o_offset, &o_n,
                          &o_out))
        return NULL;
    if (get_buf(o_vec, &b[nb++], STRIDED, FLOATS, 4, "vec") < 0 ||
        get_buf(o_p, &b[nb++], READ, KIND(F64), 2, "p") < 0 ||
        get_buf(o_out, &b[nb++], WRITE, KIND(F64), 2, "out") < 0) {
        nb--;
        goto fail;
    }
    Py_ssize_t count = points(&b[1], "p");
    if (count < 0 || points(&b[2], "out") < 0 ||
        same_count(count, b[2].shape[0], "field_map") < 0 ||
        get_small(o_inv, F64, 2, f.inv, "inv") < 0 ||
        get_small(o_origin, F64, 1, f.origin, "origin") < 0 ||
        get_small(o_offset, I64, 1, f.offset, "offset") < 0 || get_small(o_n, I64, 1, f.n, "n") < 0)
        goto fail;
    if (b[0].shape[3] != 3 || b[0].shape[0] < 1 || b[0].shape[1] < 1 || b[0].shape[2] < 1) {
        PyErr_SetString(PyExc_ValueError, "field_map: vec: expected (z, y, x, 3), not empty");
        goto fail;
    }
    Vectors v;
    vectors_of(&b[0], &v);
    const int f32 = buf_kind(&b[0]) == F32;
    Py_ssize_t first;
    Py_BEGIN_ALLOW_THREADS
    if (f32)
        first = field_map_f32(&v, &f, b[1].buf, count, b[2].buf);
    else
        first = field_map_f64(&v, &f, b[1].buf, count, b[2].buf);
    Py_END_ALLOW_THREADS
    release_all(b, nb);
    return PyLong_FromSsize_t(first);
fail:
    release_all(b, nb);
    return NULL;
}

/* ---------------------------------------------------------------- module */

static PyMethodDef methods[] = {
    {"bspline_cubic", py_bspline_cubic, METH_VARARGS,
     "bspline_cubic(coef, idx, out): ITK's BSplineTransform displacement of coefficients "
     "coef (z, y, x, 3) at grid indices idx (N, 3) into out (N, 3); zero where an index is "
     "outside [1, n - 2) on some axis (ITK's valid region)."},
    {"sample_linear", py_sample_linear, METH_VARARGS,
     "sample_linear(img, idx, lo, n, background, out): trilinear samples (float64) of img, "
     "the region of the whole input from global index lo (x, y, z), at global indices idx "
     "(N, 3); n: the whole input's sizes (x, y, z), whose inside test and clamping apply."},
    {"sample_nearest", py_sample_nearest, METH_VARARGS,
     "sample_nearest(img, idx, lo, n, background, out): nearest samples, rounded half up, "
     "as sample_linear; background and out of img's type."},
    {"sample_cubic", py_sample_cubic, METH_VARARGS,
     "sample_cubic(coef, idx, lo, n, background, out): cubic B-spline samples from the "
     "prefiltered coefficients coef (float64) of the indices from lo on, mirrored beyond the "
     "input's edges where the points reach them (lo may be -2)."},
    {"affine", py_affine, METH_VARARGS, "affine(p, m, o, out): out = p @ m.T + o, points (N, 3)."},
    {"affine_about", py_affine_about, METH_VARARGS,
     "affine_about(p, m, c, out): out = m @ (p - c), points (N, 3), summed in ITK's order "
     "(the point less c, then each row from its first product); out may be p."},
    {"grid_points", py_grid_points, METH_VARARGS,
     "grid_points(lo, hi, m, o, out): world points o + m @ (i, j, k) of the grid indices in "
     "[lo, hi) (x, y, z), x fastest, summed in ITK's order (the origin first)."},
    {"interleave", py_interleave, METH_VARARGS,
     "interleave(a, b, c, out): out[..., 0], out[..., 1], out[..., 2] = a, b, c ((z, y, x) "
     "planes)."},
    {"tile_range", py_tile_range, METH_VARARGS,
     "tile_range(vec, tile, tmin, tmax): per-tile min and max of each component of vec "
     "(z, y, x, 3), NaN skipped, into tmin, tmax (tiles z, y, x, 3; the caller fills them "
     "with NaN: a tile of NaN only stays NaN)."},
    {"field_map", py_field_map, METH_VARARGS,
     "field_map(vec, p, inv, origin, offset, n, out) -> first: out = p + u(p), u the field "
     "on the grid of world-to-index inv (p - origin); vec holds its vectors (z, y, x, 3) "
     "from index offset (x, y, z) on (a window), n the whole grid's sizes (its inside test "
     "and clamping apply). Returns the first point whose displacement is not finite, or -1."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_applykernels",
    "Sampling images and vector grids at continuous indices, as ITK does, in C.", -1, methods,
    NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__applykernels(void)
{
    return PyModule_Create(&module);
}
