/* The exact signed Euclidean distance's three passes, compiled ahead of time
 * (module volwarp_cli.distance._edtkernels; the algorithm, the field's sign and what
 * the passes leave between them are told in distance/exact.py).
 *
 * Why C and not numba like the other metrics: `volwarp distance` is a one-shot
 * command of about a second, and numba cost about half of it before any work (its
 * import, the LLVM start-up and loading each cached kernel: 0.5 s and 0.57 s on the
 * project's machine). These three passes are all the exact field needs; compiled at
 * install, they load in a millisecond. The sub-voxel feature transform
 * (distance/subvoxel.py) keeps its numba lower envelope (`add_parabola`): this file's
 * is the same algorithm, operation for operation, and the tests compare both with
 * scipy's transform.
 *
 * Arrays come as buffers with any strides; each function checks their types and
 * shapes itself (a wrong call is a Python exception, never a stray write) and releases
 * the GIL while it runs, so the callers' threads share the blocks. Built with
 * -ffp-contract=off: no fused multiply-adds, so a voxel's value is the same on every
 * machine, whatever block it is computed in.
 */

#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "../_buffers.h"

/* A 3-D buffer: its first byte, shape and strides in bytes. */
typedef struct {
    char *p;
    Py_ssize_t n[3], s[3];
} grid3;

#define AT(a, T, z, y, x) (*(T *)((a).p + (z) * (a).s[0] + (y) * (a).s[1] + (x) * (a).s[2]))

/* A buffer of 3 dimensions, float32 ('f') or uint8 ('B'/'?') in the machine's byte order,
 * with any strides. */
static int get_grid(PyObject *o, Py_buffer *b, grid3 *g, int writable, char kind, const char *name)
{
    if (get_buf(o, b, STRIDED | (writable ? WRITE : READ), KIND(kind == 'f' ? F32 : U8), 3,
                name) < 0)
        return -1;
    g->p = b->buf;
    for (int k = 0; k < 3; k++) {
        g->n[k] = b->shape[k];
        g->s[k] = b->strides[k];
    }
    return 0;
}

static int same_shape(const grid3 *a, const grid3 *b, const char *what)
{
    if (a->n[0] == b->n[0] && a->n[1] == b->n[1] && a->n[2] == b->n[2])
        return 1;
    PyErr_Format(PyExc_ValueError, "%s: shapes differ", what);
    return 0;
}

/* ---------------------------------------------------------- lower envelopes */

/* The working arrays of the lines of one plane, n samples long. */
typedef struct {
    double *f, *tmp, *g, *zb;
    Py_ssize_t *v;
    uint8_t *lab;
} lines;

static void free_lines(lines *w)
{
    free(w->f);
    free(w->tmp);
    free(w->g);
    free(w->zb);
    free(w->v);
    free(w->lab);
}

static int alloc_lines(lines *w, Py_ssize_t n)
{
    size_t m = (size_t)(n > 0 ? n : 1);
    w->f = malloc(m * sizeof(double));
    w->tmp = malloc(m * sizeof(double));
    w->g = malloc(m * sizeof(double));
    w->zb = malloc((m + 1) * sizeof(double));
    w->v = malloc(m * sizeof(Py_ssize_t));
    w->lab = malloc(m);
    if (w->f && w->tmp && w->g && w->zb && w->v && w->lab)
        return 0;
    free_lines(w);
    PyErr_NoMemory();
    return -1;
}

/* Add the parabola h2 (p - q)^2 + gq to the envelope of parabolas 0..k (k = -1: none),
 * sites in v, heights in g, breakpoints in zb (Felzenszwalb & Huttenlocher 2012,
 * algorithm DT(f)); its new last index. distance/subvoxel.py's add_parabola. */
static Py_ssize_t add_parabola(Py_ssize_t k, Py_ssize_t q, double gq, double h2, Py_ssize_t *v,
                               double *g, double *zb)
{
    if (k < 0) {
        v[0] = q;
        g[0] = gq;
        zb[0] = -INFINITY;
        zb[1] = INFINITY;
        return 0;
    }
    double s = 0.0;
    for (;;) {
        Py_ssize_t r = v[k];
        s = ((gq + h2 * (double)q * (double)q) - (g[k] + h2 * (double)r * (double)r)) /
            (2.0 * h2 * (double)(q - r));
        if (s <= zb[k]) {
            k -= 1;
            if (k < 0)
                break;
        } else {
            break;
        }
    }
    k += 1;
    v[k] = q;
    g[k] = gq;
    zb[k] = k == 0 ? -INFINITY : s;
    zb[k + 1] = INFINITY;
    return k;
}

/* The lower envelope of the parabolas h2 (p - q)^2 + g(q), g(q) = f[q] where
 * label[q] == want, else 0 (a voxel of the other label is at distance 0 from it),
 * evaluated into out at the positions p with label[p] == want. A zero site inside a
 * run of zero sites is never the nearest one for such a p (its run's ends are
 * nearer), and infinite sites never win: both are skipped. */
static void envelope(lines *w, uint8_t want, Py_ssize_t n, double h2)
{
    const double *f = w->f;
    const uint8_t *label = w->lab;
    Py_ssize_t p = 0, k = -1;
    while (p < n && label[p] != want)
        p++;
    if (p == n)
        return;
    for (Py_ssize_t q = 0; q < n; q++) {
        double gq;
        if (label[q] == want) {
            gq = f[q];
            if (gq == INFINITY)
                continue;
        } else {
            if (0 < q && q < n - 1 && label[q - 1] != want && label[q + 1] != want)
                continue;
            gq = 0.0;
        }
        k = add_parabola(k, q, gq, h2, w->v, w->g, w->zb);
    }
    if (k < 0) {
        for (p = 0; p < n; p++)
            if (label[p] == want)
                w->tmp[p] = INFINITY;
        return;
    }
    Py_ssize_t j = 0;
    for (p = 0; p < n; p++) {
        if (label[p] != want)
            continue;
        while (w->zb[j + 1] < (double)p)
            j += 1;
        Py_ssize_t r = w->v[j];
        w->tmp[p] = h2 * (double)(p - r) * (double)(p - r) + w->g[j];
    }
}

enum { SQUARED = 2, SIGNED_ROOT = 1 };

/* Both envelopes along the n rows of each of the m columns of a plane of float32
 * values (row stride ps_row, column stride ps_col bytes) whose labels (0 or 1) are at
 * lab_p: in place, as squared distances negated inside (SQUARED) or their signed
 * square roots (SIGNED_ROOT). */
static void plane_pass(char *plane, Py_ssize_t ps_row, Py_ssize_t ps_col, const char *lab_p,
                       Py_ssize_t ls_row, Py_ssize_t ls_col, Py_ssize_t m, Py_ssize_t n,
                       double h2, int sign, lines *w)
{
    for (Py_ssize_t c = 0; c < m; c++) {
        char *col = plane + c * ps_col;
        const char *lcol = lab_p + c * ls_col;
        for (Py_ssize_t i = 0; i < n; i++) {
            w->f[i] = *(float *)(col + i * ps_row);
            w->lab[i] = *(const uint8_t *)(lcol + i * ls_row);
        }
        envelope(w, 1, n, h2);
        envelope(w, 0, n, h2);
        for (Py_ssize_t i = 0; i < n; i++) {
            double d = sign == SIGNED_ROOT ? sqrt(w->tmp[i]) : w->tmp[i];
            *(float *)(col + i * ps_row) = (float)(w->lab[i] ? -d : d);
        }
    }
}

/* ------------------------------------------------------------------ passes */

static PyObject *py_x_pass(PyObject *self, PyObject *args)
{
    PyObject *om, *oo;
    double hx;
    Py_buffer bm, bo;
    grid3 m, o;
    if (!PyArg_ParseTuple(args, "OdO", &om, &hx, &oo))
        return NULL;
    if (get_grid(om, &bm, &m, 0, 'B', "x_pass mask") < 0)
        return NULL;
    if (get_grid(oo, &bo, &o, 1, 'f', "x_pass out") < 0) {
        PyBuffer_Release(&bm);
        return NULL;
    }
    if (same_shape(&m, &o, "x_pass mask and out")) {
        double hx2 = hx * hx;
        Py_ssize_t nx = m.n[2];
        Py_BEGIN_ALLOW_THREADS
        for (Py_ssize_t z = 0; z < m.n[0]; z++) {
            for (Py_ssize_t y = 0; y < m.n[1]; y++) {
                Py_ssize_t last = -1;
                for (Py_ssize_t x = 0; x < nx; x++) {
                    if (x > 0 && AT(m, uint8_t, z, y, x) != AT(m, uint8_t, z, y, x - 1))
                        last = x - 1;
                    AT(o, float, z, y, x) =
                        last < 0 ? INFINITY : (float)(hx2 * (double)(x - last) * (double)(x - last));
                }
                last = -1;
                for (Py_ssize_t x = nx - 1; x >= 0; x--) {
                    if (x < nx - 1 && AT(m, uint8_t, z, y, x) != AT(m, uint8_t, z, y, x + 1))
                        last = x + 1;
                    if (last >= 0) {
                        double d = hx2 * (double)(last - x) * (double)(last - x);
                        if (d < (double)AT(o, float, z, y, x))
                            AT(o, float, z, y, x) = (float)d;
                    }
                }
            }
        }
        Py_END_ALLOW_THREADS
    }
    PyBuffer_Release(&bm);
    PyBuffer_Release(&bo);
    if (PyErr_Occurred())
        return NULL;
    Py_RETURN_NONE;
}

static PyObject *py_y_pass(PyObject *self, PyObject *args)
{
    PyObject *of, *om;
    double hy;
    Py_buffer bf, bm;
    grid3 f, m;
    lines w;
    if (!PyArg_ParseTuple(args, "OOd", &of, &om, &hy))
        return NULL;
    if (get_grid(of, &bf, &f, 1, 'f', "y_pass field") < 0)
        return NULL;
    if (get_grid(om, &bm, &m, 0, 'B', "y_pass mask") < 0) {
        PyBuffer_Release(&bf);
        return NULL;
    }
    if (same_shape(&f, &m, "y_pass field and mask") && alloc_lines(&w, f.n[1]) == 0) {
        Py_BEGIN_ALLOW_THREADS
        for (Py_ssize_t z = 0; z < f.n[0]; z++)
            plane_pass(f.p + z * f.s[0], f.s[1], f.s[2], m.p + z * m.s[0], m.s[1], m.s[2],
                       f.n[2], f.n[1], hy * hy, SQUARED, &w);
        Py_END_ALLOW_THREADS
        free_lines(&w);
    }
    PyBuffer_Release(&bf);
    PyBuffer_Release(&bm);
    if (PyErr_Occurred())
        return NULL;
    Py_RETURN_NONE;
}

static PyObject *py_z_pass(PyObject *self, PyObject *args)
{
    PyObject *of;
    double hz;
    Py_buffer bf;
    grid3 f;
    lines w;
    if (!PyArg_ParseTuple(args, "Od", &of, &hz))
        return NULL;
    if (get_grid(of, &bf, &f, 1, 'f', "z_pass field") < 0)
        return NULL;
    Py_ssize_t nz = f.n[0], nx = f.n[2];
    /* each (z, x) plane of one y, copied out (its x rows contiguous), its labels taken
     * from the sign, processed in cache and written back as the signed root */
    size_t cells = (size_t)(nz > 0 ? nz : 1) * (size_t)(nx > 0 ? nx : 1);
    float *plane = malloc(cells * sizeof(float));
    uint8_t *labels = malloc(cells);
    if (!plane || !labels) {
        PyErr_NoMemory();
    } else if (alloc_lines(&w, nz) == 0) {
        double hz2 = hz * hz;
        Py_BEGIN_ALLOW_THREADS
        for (Py_ssize_t y = 0; y < f.n[1]; y++) {
            for (Py_ssize_t z = 0; z < nz; z++) {
                for (Py_ssize_t x = 0; x < nx; x++) {
                    float v = AT(f, float, z, y, x);
                    labels[z * nx + x] = v < 0;
                    plane[z * nx + x] = v < 0 ? -v : v;
                }
            }
            plane_pass((char *)plane, nx * (Py_ssize_t)sizeof(float), sizeof(float),
                       (const char *)labels, nx, 1, nx, nz, hz2, SIGNED_ROOT, &w);
            for (Py_ssize_t z = 0; z < nz; z++)
                for (Py_ssize_t x = 0; x < nx; x++)
                    AT(f, float, z, y, x) = plane[z * nx + x];
        }
        Py_END_ALLOW_THREADS
        free_lines(&w);
    }
    free(plane);
    free(labels);
    PyBuffer_Release(&bf);
    if (PyErr_Occurred())
        return NULL;
    Py_RETURN_NONE;
}

static PyMethodDef methods[] = {
    {"x_pass", py_x_pass, METH_VARARGS,
     "x_pass(mask, hx, out): pass 1 (x) of a (Z, Y, X) uint8 block of whole x rows into "
     "out (float32): the squared distance along the row to the nearest voxel of the other "
     "label, inf where the row has none."},
    {"y_pass", py_y_pass, METH_VARARGS,
     "y_pass(field, mask, hy): pass 2 (y), in place, on a float32 block of whole y "
     "columns: squared distances, negated inside (mask 1)."},
    {"z_pass", py_z_pass, METH_VARARGS,
     "z_pass(field, hz): pass 3 (z) and the signed square root, in place, on a float32 "
     "block of whole z lines whose values are y_pass's."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_edtkernels",
    "The exact signed Euclidean distance's three passes (lower envelopes of parabolas) in C.",
    -1, methods, NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__edtkernels(void) { return PyModule_Create(&module); }
