/* sumo.calls: a deployment step's per-vehicle calls (libsumo's compiled getters and
   setSpeed, a dictionary's look-up of each vehicle) made in one C loop each, the results
   written straight into a numpy array or a list.

   Why: np.fromiter(map(getter, ids), float, n) and list(map(getter, ids)) pay, per
   vehicle and besides the getter itself, map's step (~60 instructions), a fresh argument
   tuple for the SWIG wrapper (~80) and numpy's conversion of the Python value (~150,
   PyArray_Pack): on Bremen's policy run some 1,000 such items a step, ~5% of its
   instructions (callgrind, stop 48). Here the argument tuple is reused while no one else
   holds it, and a value is written as the double or int64 it is.

   The same calls in the same order with the same arguments, so the same values: what
   SUMO answers does not depend on how it is asked. Where an operand or a value is not
   of the form numpy's path takes for granted (an exact list or tuple of items, an exact
   float or int answered, a float64 or int64 C-contiguous output of the right length),
   the function answers False and the caller's numpy path answers instead; an exception
   raised by a call propagates as it would from map. Optional: setup.py builds it where a
   C compiler is found (as road/kernels.c). */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stdint.h>
#include <string.h>

/* A writable C-contiguous buffer of itemsize 8, float64 ("d") or int64 ("l", "q"), of
   1 or 2 dimensions (at most ndim). 0: not that form (no buffer held). */
static int output(PyObject *obj, Py_buffer *v, char kind, int ndim) {
    if (!PyObject_CheckBuffer(obj) ||
        PyObject_GetBuffer(obj, v, PyBUF_FORMAT | PyBUF_ND | PyBUF_WRITABLE) < 0) {
        PyErr_Clear();
        return 0;
    }
    const char *f = v->format;
    int ok = f != NULL && v->ndim >= 1 && v->ndim <= ndim && v->itemsize == 8 &&
             (kind == 'd' ? strcmp(f, "d") == 0 : strcmp(f, "l") == 0 || strcmp(f, "q") == 0);
    if (!ok) PyBuffer_Release(v);
    return ok;
}

/* One argument tuple for a run of calls, reused while the callee keeps no reference to
   it (a SWIG wrapper keeps none); otherwise a fresh one for the next call. */
typedef struct {
    PyObject *tuple;
    Py_ssize_t size;
} argbox;

/* f(args...) with box's tuple holding the (borrowed) arguments during the call. */
static PyObject *call(PyObject *f, argbox *box, PyObject *const *args) {
    if (box->tuple == NULL) {
        box->tuple = PyTuple_New(box->size);
        if (box->tuple == NULL) return NULL;
    }
    PyObject *t = box->tuple;
    for (Py_ssize_t k = 0; k < box->size; k++) {
        Py_INCREF(args[k]);
        PyTuple_SET_ITEM(t, k, args[k]);
    }
    PyObject *r = PyObject_Call(f, t, NULL);
    if (Py_REFCNT(t) == 1) { /* ours alone: emptied for the next call */
        for (Py_ssize_t k = 0; k < box->size; k++) {
            PyTuple_SET_ITEM(t, k, NULL);
            Py_DECREF(args[k]);
        }
    } else { /* the callee kept it: it keeps its items, the next call gets a new one */
        Py_DECREF(t);
        box->tuple = NULL;
    }
    return r;
}

static void done(argbox *box) { Py_XDECREF(box->tuple); } /* NULL items: tupledealloc's XDECREF */

/* The items of an exact list or tuple (NULL: not one; no error set). */
static PyObject **items_of(PyObject *seq, Py_ssize_t *n) {
    if (PyList_CheckExact(seq)) {
        *n = PyList_GET_SIZE(seq);
        return ((PyListObject *)seq)->ob_item;
    }
    if (PyTuple_CheckExact(seq)) {
        *n = PyTuple_GET_SIZE(seq);
        return ((PyTupleObject *)seq)->ob_item;
    }
    return NULL;
}

/* floats(getters, items, out) -> bool: out[k, i] = getters[k](items[i]) for an exact
   tuple of k getters, out float64 (k, n) C-contiguous (or (n,) where k is 1), the calls
   item by item (each item's k getters, then the next item's). False where a form does
   not fit or a getter answers other than an exact float (out then partly written: the
   caller computes it afresh); an exception from a getter propagates. A list item is
   read anew each call, so a getter that changes the list cannot read past its end. */
static PyObject *floats(PyObject *self, PyObject *args) {
    PyObject *fs, *seq, *obj;
    if (!PyArg_UnpackTuple(args, "floats", 3, 3, &fs, &seq, &obj)) return NULL;
    Py_ssize_t n, k = PyTuple_CheckExact(fs) ? PyTuple_GET_SIZE(fs) : 0;
    if (k == 0 || items_of(seq, &n) == NULL) Py_RETURN_FALSE;
    Py_buffer out;
    if (!output(obj, &out, 'd', 2)) Py_RETURN_FALSE;
    int fits = out.ndim == 1 ? k == 1 && out.shape[0] == n : out.shape[0] == k && out.shape[1] == n;
    if (!fits) {
        PyBuffer_Release(&out);
        Py_RETURN_FALSE;
    }
    double *o = out.buf;
    argbox box = {NULL, 1};
    int ok = 1, failed = 0;
    Py_INCREF(seq); /* held: a getter may drop the caller's last reference */
    for (Py_ssize_t i = 0; ok && !failed && i < n; i++) {
        Py_ssize_t now = 0;
        PyObject **item = items_of(seq, &now);
        if (i >= now) { /* shortened by a call: map would stop, numpy would refuse */
            ok = 0;
            break;
        }
        PyObject *x = item[i];
        Py_INCREF(x);
        for (Py_ssize_t j = 0; j < k; j++) {
            PyObject *r = call(PyTuple_GET_ITEM(fs, j), &box, &x);
            if (r == NULL) {
                failed = 1;
                break;
            }
            if (!PyFloat_CheckExact(r)) {
                Py_DECREF(r);
                ok = 0;
                break;
            }
            o[j * n + i] = PyFloat_AS_DOUBLE(r);
            Py_DECREF(r);
        }
        Py_DECREF(x);
    }
    Py_DECREF(seq);
    done(&box);
    PyBuffer_Release(&out);
    if (failed) return NULL;
    if (ok) Py_RETURN_TRUE;
    Py_RETURN_FALSE;
}

/* objects(f, items[, arg]) -> list: [f(x) for x in items] (or f(x, arg)), as
   list(map(f, items[, repeat(arg)])); None where items is not an exact list or tuple; an
   exception from f propagates. */
static PyObject *objects(PyObject *self, PyObject *args) {
    PyObject *f, *seq, *arg = NULL;
    if (!PyArg_UnpackTuple(args, "objects", 2, 3, &f, &seq, &arg)) return NULL;
    Py_ssize_t n;
    if (items_of(seq, &n) == NULL) Py_RETURN_NONE;
    PyObject *got = PyList_New(0);
    if (got == NULL) return NULL;
    argbox box = {NULL, arg == NULL ? 1 : 2};
    Py_INCREF(seq);
    for (Py_ssize_t i = 0;; i++) {
        Py_ssize_t now = 0;
        PyObject **item = items_of(seq, &now);
        if (i >= now) break; /* map stops where the items end */
        PyObject *pair[2] = {item[i], arg};
        Py_INCREF(pair[0]);
        PyObject *r = call(f, &box, pair);
        Py_DECREF(pair[0]);
        if (r == NULL || PyList_Append(got, r) < 0) {
            Py_XDECREF(r);
            Py_CLEAR(got);
            break;
        }
        Py_DECREF(r);
    }
    Py_DECREF(seq);
    done(&box);
    return got;
}

/* send(f, items, values) -> bool: f(items[i], float(values[i])) for each i, their
   answers dropped, as list(map(f, items, values.tolist())); values float64 (n,)
   C-contiguous with n = len(items). False (nothing called) where a form does not fit;
   an exception from f propagates (the calls before it made, as map makes them). */
static PyObject *send(PyObject *self, PyObject *args) {
    PyObject *f, *seq, *obj;
    if (!PyArg_UnpackTuple(args, "send", 3, 3, &f, &seq, &obj)) return NULL;
    Py_ssize_t n;
    if (items_of(seq, &n) == NULL) Py_RETURN_FALSE;
    Py_buffer v;
    if (!PyObject_CheckBuffer(obj) || PyObject_GetBuffer(obj, &v, PyBUF_FORMAT | PyBUF_ND) < 0) {
        PyErr_Clear();
        Py_RETURN_FALSE;
    }
    if (v.format == NULL || strcmp(v.format, "d") != 0 || v.itemsize != 8 || v.ndim != 1 ||
        v.shape[0] != n) {
        PyBuffer_Release(&v);
        Py_RETURN_FALSE;
    }
    /* A copy of the values: a call cannot change what the later calls send. */
    double *vals = PyMem_Malloc(n > 0 ? n * sizeof(double) : 1);
    if (vals == NULL) {
        PyBuffer_Release(&v);
        return PyErr_NoMemory();
    }
    memcpy(vals, v.buf, n * sizeof(double));
    PyBuffer_Release(&v);
    argbox box = {NULL, 2};
    int failed = 0;
    Py_INCREF(seq);
    for (Py_ssize_t i = 0; i < n; i++) {
        Py_ssize_t now = 0;
        PyObject **item = items_of(seq, &now);
        if (i >= now) break; /* map stops where the items end */
        PyObject *pair[2] = {item[i], PyFloat_FromDouble(vals[i])};
        if (pair[1] == NULL) {
            failed = 1;
            break;
        }
        Py_INCREF(pair[0]);
        PyObject *r = call(f, &box, pair);
        Py_DECREF(pair[0]);
        Py_DECREF(pair[1]);
        if (r == NULL) {
            failed = 1;
            break;
        }
        Py_DECREF(r);
    }
    Py_DECREF(seq);
    done(&box);
    PyMem_Free(vals);
    if (failed) return NULL;
    Py_RETURN_TRUE;
}

/* lookup(mapping, keys, default, out) -> bool: out[i] = mapping.get(keys[i], default),
   as np.fromiter(map(mapping.get, keys, repeat(default)), np.int64, n); default None:
   mapping[keys[i]], a missing key raising KeyError(key) as dict.__getitem__ does.
   mapping an exact dict, out int64 (n,) C-contiguous. False where a form does not fit or
   a value is not an exact int in int64's range (out then partly written); an error of a
   key's hash or comparison propagates. */
static PyObject *lookup(PyObject *self, PyObject *args) {
    PyObject *d, *seq, *dflt, *obj;
    if (!PyArg_UnpackTuple(args, "lookup", 4, 4, &d, &seq, &dflt, &obj)) return NULL;
    Py_ssize_t n;
    if (!PyDict_CheckExact(d) || items_of(seq, &n) == NULL) Py_RETURN_FALSE;
    if (dflt != Py_None && !PyLong_CheckExact(dflt)) Py_RETURN_FALSE;
    Py_buffer out;
    if (!output(obj, &out, 'i', 1)) Py_RETURN_FALSE;
    if (out.shape[0] != n) {
        PyBuffer_Release(&out);
        Py_RETURN_FALSE;
    }
    int64_t *o = out.buf;
    int ok = 1, failed = 0;
    Py_INCREF(d);
    Py_INCREF(seq);
    for (Py_ssize_t i = 0; ok && i < n; i++) {
        Py_ssize_t now = 0;
        PyObject **item = items_of(seq, &now);
        if (i >= now) {
            ok = 0;
            break;
        }
        PyObject *key = item[i];
        Py_INCREF(key);
        PyObject *v = PyDict_GetItemWithError(d, key); /* borrowed */
        if (v == NULL) {
            if (PyErr_Occurred()) {
                failed = 1;
            } else if (dflt == Py_None) { /* KeyError(key), as dict.__getitem__ raises it */
                PyObject *one = PyTuple_Pack(1, key);
                if (one != NULL) {
                    PyErr_SetObject(PyExc_KeyError, one);
                    Py_DECREF(one);
                }
                failed = 1;
            } else {
                v = dflt;
            }
        }
        if (v != NULL) {
            if (!PyLong_CheckExact(v)) {
                ok = 0;
            } else {
                int overflow;
                long long x = PyLong_AsLongLongAndOverflow(v, &overflow);
                if (overflow || (x == -1 && PyErr_Occurred())) {
                    PyErr_Clear();
                    ok = 0;
                } else {
                    o[i] = (int64_t)x;
                }
            }
        }
        Py_DECREF(key);
        if (failed) break;
    }
    Py_DECREF(seq);
    Py_DECREF(d);
    PyBuffer_Release(&out);
    if (failed) return NULL;
    if (ok) Py_RETURN_TRUE;
    Py_RETURN_FALSE;
}

/* pairs(leaders, index, codes, gap, row, shape) -> bool: of each (leader ID, gap) pair
   of leaders (Simulation.leaders' list), gap[i] = its gap, row[i] = index.get(ID, -1) and
   shape[i] = codes.get(ID, 0): deploy.observe.observe_rows' zip(*leaders), np.fromiter of
   the gaps and the two look-ups in one loop. leaders an exact list or tuple of exact
   2-tuples (str, float), index and codes exact dicts of exact ints, gap float64 and row,
   shape int64 (n,) C-contiguous. False where a form does not fit (outputs partly
   written); an error of a key's hash or comparison propagates. */
static PyObject *pairs(PyObject *self, PyObject *args) {
    PyObject *seq, *d[2], *o[3];
    if (!PyArg_UnpackTuple(args, "pairs", 6, 6, &seq, &d[0], &d[1], &o[0], &o[1], &o[2]))
        return NULL;
    Py_ssize_t n;
    if (!PyDict_CheckExact(d[0]) || !PyDict_CheckExact(d[1]) || items_of(seq, &n) == NULL)
        Py_RETURN_FALSE;
    Py_buffer v[3];
    int got = 0, ok = 1, failed = 0;
    for (; got < 3; got++) {
        if (!output(o[got], &v[got], got == 0 ? 'd' : 'i', 1)) {
            ok = 0;
            break;
        }
        if (v[got].shape[0] != n) {
            PyBuffer_Release(&v[got]);
            ok = 0;
            break;
        }
    }
    static const int64_t missing[2] = {-1, 0};
    Py_INCREF(seq);
    Py_INCREF(d[0]);
    Py_INCREF(d[1]);
    for (Py_ssize_t i = 0; ok && i < n; i++) {
        Py_ssize_t now = 0;
        PyObject **item = items_of(seq, &now);
        if (i >= now) {
            ok = 0;
            break;
        }
        PyObject *pair = item[i];
        if (!PyTuple_CheckExact(pair) || PyTuple_GET_SIZE(pair) != 2 ||
            !PyFloat_CheckExact(PyTuple_GET_ITEM(pair, 1))) {
            ok = 0;
            break;
        }
        Py_INCREF(pair);
        PyObject *key = PyTuple_GET_ITEM(pair, 0);
        ((double *)v[0].buf)[i] = PyFloat_AS_DOUBLE(PyTuple_GET_ITEM(pair, 1));
        for (int k = 0; ok && k < 2; k++) {
            PyObject *x = PyDict_GetItemWithError(d[k], key); /* borrowed */
            int64_t value = missing[k];
            if (x == NULL && PyErr_Occurred()) {
                failed = 1;
                break;
            }
            if (x != NULL) {
                int overflow = 0;
                long long y = PyLong_CheckExact(x) ? PyLong_AsLongLongAndOverflow(x, &overflow) : 0;
                if (!PyLong_CheckExact(x) || overflow || (y == -1 && PyErr_Occurred())) {
                    PyErr_Clear();
                    ok = 0;
                    break;
                }
                value = (int64_t)y;
            }
            ((int64_t *)v[1 + k].buf)[i] = value;
        }
        Py_DECREF(pair);
        if (failed) break;
    }
    Py_DECREF(d[1]);
    Py_DECREF(d[0]);
    Py_DECREF(seq);
    for (int i = 0; i < got; i++) PyBuffer_Release(&v[i]);
    if (failed) return NULL;
    if (ok) Py_RETURN_TRUE;
    Py_RETURN_FALSE;
}

static PyMethodDef methods[] = {
    {"pairs", pairs, METH_VARARGS,
     "observe_rows' leader gaps, rows and shape codes in one loop; False where numpy must "
     "answer."},
    {"floats", floats, METH_VARARGS,
     "out[k, i] = getters[k](items[i]), item by item; False where numpy must answer."},
    {"objects", objects, METH_VARARGS,
     "list(map(f, items[, repeat(arg)])); None where items is not an exact list or tuple."},
    {"send", send, METH_VARARGS,
     "f(items[i], float(values[i])) for each i; False where map must answer."},
    {"lookup", lookup, METH_VARARGS,
     "out[i] = mapping.get(keys[i], default) (None: mapping[keys[i]]); False where numpy "
     "must answer."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "calls", "sumo's per-vehicle calls in one C loop each.", -1, methods,
};

PyMODINIT_FUNC PyInit_calls(void) { return PyModule_Create(&module); }
