/* Numpy arrays as C buffers, checked: the argument handling every compiled kernel module of
 * volwarp shares (bspline/_warpkernels.c, distance/_edtkernels.c, sweep/_sweepkernels.c,
 * transforms/_applykernels.c include it).
 *
 * A kernel takes each array through get_buf, which refuses (a Python exception, the buffer
 * released) a sample type it was not written for, a byte order not the machine's, another
 * number of dimensions, a layout it cannot walk (not C-contiguous unless STRIDED) and an
 * item not at a multiple of its size (unless the module says BUFFERS_UNALIGNED_OK): a wrong
 * call is an error, never a stray read.
 */

#ifndef VOLWARP_BUFFERS_H
#define VOLWARP_BUFFERS_H

/* A module whose loops read samples wherever they lie defines this as 1 before the include
 * (the warp's: a memory-mapped NRRD's samples start wherever its header ends). */
#ifndef BUFFERS_UNALIGNED_OK
#define BUFFERS_UNALIGNED_OK 0
#endif

#include <Python.h> /* (after the module's #define PY_SSIZE_T_CLEAN) */
#include <stdint.h>

/* Sample types, and sets of them as bits (KIND(F32) | KIND(F64)). */
enum { I8, U8, I16, U16, I32, U32, I64, U64, F32, F64, KINDS };
#define KIND(k) (1 << (k))
#define FLOATS (KIND(F32) | KIND(F64))
#define ALL_KINDS ((1 << KINDS) - 1)

static inline const char *kind_name(int kind)
{
    static const char *const names[KINDS] = {"int8",   "uint8",  "int16",   "uint16",
                                             "int32",  "uint32", "int64",   "uint64",
                                             "float32", "float64"};
    return kind >= 0 && kind < KINDS ? names[kind] : "?";
}

/* The sample type of a buffer in the machine's byte order, or -1 (a bool is a uint8). */
static inline int buf_kind(const Py_buffer *v)
{
    const char *f = v->format ? v->format : "B";
#if PY_LITTLE_ENDIAN
    if (*f == '@' || *f == '=' || *f == '<')
#else
    if (*f == '@' || *f == '=' || *f == '>' || *f == '!')
#endif
        f++;
    if (!f[0] || f[1])
        return -1;
    switch (f[0]) {
    case 'b': return v->itemsize == 1 ? I8 : -1;
    case 'B': case '?': return v->itemsize == 1 ? U8 : -1;
    case 'h': return v->itemsize == 2 ? I16 : -1;
    case 'H': return v->itemsize == 2 ? U16 : -1;
    case 'i': return v->itemsize == 4 ? I32 : -1;
    case 'I': return v->itemsize == 4 ? U32 : -1;
    case 'l': case 'q': return v->itemsize == 8 ? I64 : v->itemsize == 4 ? I32 : -1;
    case 'L': case 'Q': return v->itemsize == 8 ? U64 : v->itemsize == 4 ? U32 : -1;
    case 'f': return v->itemsize == 4 ? F32 : -1;
    case 'd': return v->itemsize == 8 ? F64 : -1;
    default: return -1;
    }
}

/* How get_buf takes a buffer: read (C-contiguous), WRITE, and STRIDED (any strides). */
enum { READ = 0, WRITE = 1, STRIDED = 2 };

/* Whether every item lies at a multiple of its size (the loops read them as their type). */
static inline int buf_aligned(const Py_buffer *v)
{
    int ok = (uintptr_t)v->buf % v->itemsize == 0;
    for (int d = 0; d < v->ndim && v->strides; d++)
        ok &= v->strides[d] % v->itemsize == 0;
    return ok;
}

/* Argument `name` as a buffer of one of `kinds` with `ndim` dimensions, C-contiguous
 * unless `how` has STRIDED (then any strides), writable if it has WRITE. On failure the
 * buffer is released and a Python exception set: TypeError for the sample type, else
 * ValueError (numpy's own for a read-only array asked to be written). */
static inline int get_buf(PyObject *o, Py_buffer *v, int how, int kinds, int ndim,
                          const char *name)
{
    int flags = PyBUF_STRIDES | PyBUF_FORMAT | (how & WRITE ? PyBUF_WRITABLE : 0);
    if (PyObject_GetBuffer(o, v, flags) < 0)
        return -1;
    int kind = buf_kind(v);
    if (kind < 0 || !(kinds & KIND(kind))) {
        char want[128] = ""; /* the accepted types (all ten names fit: 106 characters) */
        size_t n = 0;
        for (int k = 0; k < KINDS; k++)
            if (kinds & KIND(k))
                n += (size_t)snprintf(want + n, sizeof want - n, "%s%s", n ? " or " : "",
                                      kind_name(k));
        PyErr_Format(PyExc_TypeError, "%s: unexpected sample type '%s' (expected %s)", name,
                     v->format ? v->format : "B", kinds == ALL_KINDS ? "a number" : want);
    } else if (v->ndim != ndim) {
        PyErr_Format(PyExc_ValueError, "%s: expected %d dimensions, got %d", name, ndim,
                     v->ndim);
    } else if (!(how & STRIDED) && !PyBuffer_IsContiguous(v, 'C')) {
        PyErr_Format(PyExc_ValueError, "%s: expected a C-contiguous array", name);
    } else if (!BUFFERS_UNALIGNED_OK && !buf_aligned(v)) {
        PyErr_Format(PyExc_ValueError, "%s: expected an aligned array", name);
    } else {
        return 0;
    }
    PyBuffer_Release(v);
    return -1;
}

static inline void release_all(Py_buffer *b, int n)
{
    for (int k = 0; k < n; k++)
        PyBuffer_Release(&b[k]);
}

/* Indices and sizes beyond any grid: the loops' integer arithmetic would overflow. */
#define INDEX_LIMIT ((int64_t)1 << 62)

static inline int within_limit(int64_t v)
{
    return v > -INDEX_LIMIT && v < INDEX_LIMIT;
}

#endif
