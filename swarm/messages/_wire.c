/* The wire's per-message work on float64 bytes, compiled (swarm.messages.native):
 *
 *   native_finite  np.isfinite(...).all() of native float64 bytes: the wire rules' check of
 *                  every float a peer sends (swarm.messages.rules, swarm.messages.wire)
 *   join_native    b"".join(a.tobytes() ...) of native float64 arrays of given shapes, None
 *                  if one is not: the telemetry's packing of a step's arrays
 *
 * and the columns of a relayed beacon's row (relay_row.h), exported as RELAY_FIELDS and
 * RELAY_WIDTH: BeaconRelayWire's layout, which the exchange's nearby reads.
 * tests/messages/test_native.py binds both functions to their numpy forms.
 */
#include "../compiled.h"
#include <math.h>

#include "relay_row.h"

PyDoc_STRVAR(native_finite_doc,
"native_finite(*parts) -> bool\n--\n\n"
"Whether every float64 (native byte order) in the bytes-like parts is finite; each part's\n"
"length must be a multiple of 8. The parts are read as they are, unaligned or not.");

static PyObject *
py_native_finite(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    for (Py_ssize_t i = 0; i < nargs; i++) {
        Py_buffer view;
        if (PyObject_GetBuffer(args[i], &view, PyBUF_SIMPLE) != 0) {
            PyErr_Clear();
            PyErr_Format(PyExc_TypeError, "native_finite: part %zd is not bytes-like (%s)", i,
                         Py_TYPE(args[i])->tp_name);
            return NULL;
        }
        if (view.len % 8) {
            PyErr_Format(PyExc_ValueError, "native_finite: part %zd holds %zd bytes, not a "
                         "whole number of float64", i, view.len);
            PyBuffer_Release(&view);
            return NULL;
        }
        const char *bytes = view.buf;
        int finite = 1;
        for (Py_ssize_t k = 0; k < view.len && finite; k += 8) {
            double value;
            memcpy(&value, bytes + k, sizeof value);
            finite = isfinite(value);
        }
        PyBuffer_Release(&view);
        if (!finite) Py_RETURN_FALSE;
    }
    Py_RETURN_TRUE;
}

PyDoc_STRVAR(join_native_doc,
"join_native(arrays, shapes) -> bytes or None\n--\n\n"
"b''.join(a.tobytes() for a in arrays) when every array is a C-contiguous native float64\n"
"buffer of its shape in ``shapes`` (tuples of ints, one per array); None otherwise (the\n"
"caller converts, and names what does not fit). The wire's packing of a step's arrays.");

static PyObject *
py_join_native(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    if (check_nargs(nargs, 2, "join_native")) return NULL;
    PyObject *arrays = args[0], *shapes = args[1];
    if (!PyTuple_Check(arrays) || !PyTuple_Check(shapes)
            || PyTuple_GET_SIZE(arrays) != PyTuple_GET_SIZE(shapes)) {
        PyErr_SetString(PyExc_TypeError, "join_native: arrays and shapes must be tuples of "
                        "the same length");
        return NULL;
    }
    enum { MAX_PARTS = 32 };
    Py_ssize_t parts = PyTuple_GET_SIZE(arrays);
    if (parts > MAX_PARTS) {
        PyErr_Format(PyExc_ValueError, "join_native: at most %d arrays, got %zd", MAX_PARTS,
                     parts);
        return NULL;
    }
    Py_buffer views[MAX_PARTS];
    Py_ssize_t held = 0, total = 0;
    PyObject *result = NULL;
    int native = 1;
    for (Py_ssize_t i = 0; i < parts && native; i++) {
        PyObject *shape = PyTuple_GET_ITEM(shapes, i);
        if (!PyTuple_Check(shape)) {
            PyErr_Format(PyExc_TypeError, "join_native: shape %zd is not a tuple", i);
            goto done;
        }
        if (PyObject_GetBuffer(PyTuple_GET_ITEM(arrays, i), &views[held],
                               PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) != 0) {
            PyErr_Clear(); /* not a buffer, or not contiguous: the caller converts */
            native = 0;
            break;
        }
        Py_buffer *view = &views[held++];
        native = view->format != NULL && strcmp(view->format, "d") == 0
                 && view->itemsize == 8 && view->ndim == PyTuple_GET_SIZE(shape);
        for (int d = 0; native && d < view->ndim; d++) {
            Py_ssize_t expected = PyLong_AsSsize_t(PyTuple_GET_ITEM(shape, d));
            if (expected == -1 && PyErr_Occurred()) goto done;
            native = view->shape[d] == expected;
        }
        total += view->len;
    }
    if (!native) {
        result = Py_NewRef(Py_None);
        goto done;
    }
    result = PyBytes_FromStringAndSize(NULL, total);
    if (result == NULL) goto done;
    char *out = PyBytes_AS_STRING(result);
    for (Py_ssize_t i = 0; i < held; i++) {
        memcpy(out, views[i].buf, (size_t)views[i].len);
        out += views[i].len;
    }
done:
    for (Py_ssize_t i = 0; i < held; i++) PyBuffer_Release(&views[i]);
    return result;
}

static PyMethodDef methods[] = {
    {"native_finite", (PyCFunction)(void (*)(void))py_native_finite, METH_FASTCALL,
     native_finite_doc},
    {"join_native", (PyCFunction)(void (*)(void))py_join_native, METH_FASTCALL,
     join_native_doc},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT,
    .m_name = "swarm.messages._wire",
    .m_doc = "The wire's checks and packing of float64 bytes, compiled (see the source's "
             "header).",
    .m_size = -1,
    .m_methods = methods,
};

/* BeaconRelayWire's row, by relay_row.h. */
static const Field relay_fields[] = {
    {"position", RELAY_POSITION}, {"velocity", RELAY_VELOCITY},
    {"sample_age", RELAY_SAMPLE_AGE}, {"held", RELAY_HELD},
};

PyMODINIT_FUNC
PyInit__wire(void)
{
    PyObject *mod = PyModule_Create(&module);
    if (mod == NULL) return NULL;
    if (add_fields(mod, "RELAY_FIELDS", relay_fields, COUNT(relay_fields), RELAY_WIDTH) < 0
            || PyModule_AddIntConstant(mod, "RELAY_WIDTH", RELAY_WIDTH) < 0) {
        Py_DECREF(mod);
        return NULL;
    }
    return mod;
}
