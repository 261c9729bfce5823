/* A SIGBUS handler for inputs read through a memory map.
 *
 * `volwarp warp` maps its NRRD input instead of copying it. If another program
 * truncates the file meanwhile (`cp new.nrrd in.nrrd` truncates, then writes),
 * touching a page past the new end raises SIGBUS, in whichever thread touches
 * it, and the process died with no message and its temporary output left
 * behind. Python cannot handle that signal (its handler only sets a flag; the
 * faulting load would run again, forever), so this one, in C, does what the
 * contract asks with async-signal-safe calls only: remove the temporary
 * outputs it was told about, write one line naming the input, and _exit(1).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <signal.h>
#include <string.h>
#include <unistd.h>

#define MAX_PATHS 64
#define MAX_PATH_BYTES 4096

static char paths[MAX_PATHS][MAX_PATH_BYTES];
static volatile sig_atomic_t n_paths = 0;
static char message[MAX_PATH_BYTES + 256];
static size_t message_len = 0;

static volatile int fired = 0;

static void on_sigbus(int signum) {
    (void)signum;
    if (__sync_lock_test_and_set(&fired, 1)) {
        for (;;) {
            pause(); /* another thread faulted first: it ends the process */
        }
    }
    int n = n_paths;
    for (int i = 0; i < n; i++) {
        unlink(paths[i]);
    }
    if (message_len) {
        ssize_t ignored = write(2, message, message_len);
        (void)ignored;
    }
    _exit(1);
}

/* install(message): the line to print (with its newline) when a mapped input faults */
static PyObject *install(PyObject *self, PyObject *args) {
    const char *text;
    Py_ssize_t len;
    if (!PyArg_ParseTuple(args, "s#", &text, &len)) {
        return NULL;
    }
    if ((size_t)len >= sizeof(message)) {
        len = sizeof(message) - 1;
    }
    memcpy(message, text, (size_t)len);
    message_len = (size_t)len;
    struct sigaction sa;
    memset(&sa, 0, sizeof(sa));
    sa.sa_handler = on_sigbus;
    sigemptyset(&sa.sa_mask);
    if (sigaction(SIGBUS, &sa, NULL) != 0) {
        return PyErr_SetFromErrno(PyExc_OSError);
    }
    Py_RETURN_NONE;
}

/* set_temporaries(list of str or bytes): the temporary outputs to remove on a fault. A str
 * is encoded as the file system's name (os.fsencode: a name that is not UTF-8 keeps its
 * bytes, where UTF-8 could not encode its surrogate escapes). */
static PyObject *set_temporaries(PyObject *self, PyObject *arg) {
    PyObject *seq = PySequence_Fast(arg, "set_temporaries takes a sequence of paths");
    if (seq == NULL) {
        return NULL;
    }
    Py_ssize_t n = PySequence_Fast_GET_SIZE(seq);
    n_paths = 0; /* the handler sees no half-written entry */
    int kept = 0;
    for (Py_ssize_t i = 0; i < n && kept < MAX_PATHS; i++) {
        PyObject *item = PySequence_Fast_GET_ITEM(seq, i);
        PyObject *encoded = PyUnicode_Check(item) ? PyUnicode_EncodeFSDefault(item)
                                                  : PyBytes_FromObject(item);
        char *text;
        Py_ssize_t len;
        if (encoded == NULL || PyBytes_AsStringAndSize(encoded, &text, &len) < 0) {
            Py_XDECREF(encoded);
            Py_DECREF(seq);
            return NULL;
        }
        if (len < MAX_PATH_BYTES) {
            memcpy(paths[kept], text, (size_t)len);
            paths[kept][len] = '\0';
            kept++;
        }
        Py_DECREF(encoded);
    }
    n_paths = kept;
    Py_DECREF(seq);
    Py_RETURN_NONE;
}

static PyMethodDef methods[] = {
    {"install", install, METH_VARARGS, "Handle SIGBUS: remove temporaries, one line, exit 1."},
    {"set_temporaries", set_temporaries, METH_O, "The temporary outputs to remove on SIGBUS."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_mapguard",
    "SIGBUS handling for memory-mapped inputs (see the source's header).", -1, methods,
};

PyMODINIT_FUNC PyInit__mapguard(void) { return PyModule_Create(&module); }
