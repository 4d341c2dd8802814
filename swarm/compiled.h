/* What the project's C extensions share (swarm.core._kernels, swarm.messages._wire,
 * swarm.agent._exchange): their arguments read with one-line errors, and the layouts they
 * export to Python, so that Python reads each offset and each constant order from the module
 * that uses it instead of writing it again (swarm.compiled reads them: field_index,
 * field_slice, in_order).
 *
 * Included by each source (#include "../compiled.h"); static inline, so a source that uses
 * only some of these compiles without warnings.
 */
#ifndef SWARM_COMPILED_H
#define SWARM_COMPILED_H

#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <string.h>

static inline int
check_nargs(Py_ssize_t nargs, Py_ssize_t expected, const char *name)
{
    if (nargs != expected) {
        PyErr_Format(PyExc_TypeError, "%s() takes %zd arguments (%zd given)", name, expected,
                     nargs);
        return -1;
    }
    return 0;
}

static inline void
length_error(const Py_buffer *view, Py_ssize_t length, const char *what)
{
    PyErr_Format(PyExc_ValueError, "%s: expected %zd float64 values, got %zd", what, length,
                 view->len / 8);
}

/* A C-contiguous float64 buffer of exactly `length` items (`length` < 0: any), writable if
 * asked. Sets a one-line ValueError/TypeError naming `what` otherwise. */
static inline int
float64_buffer(PyObject *obj, Py_buffer *view, int writable, Py_ssize_t length,
               const char *what)
{
    int flags = PyBUF_FORMAT | PyBUF_C_CONTIGUOUS | (writable ? PyBUF_WRITABLE : 0);
    if (PyObject_GetBuffer(obj, view, flags) != 0) {
        PyErr_Clear();
        PyErr_Format(PyExc_TypeError, "%s: expected a %sC-contiguous float64 array, got %s",
                     what, writable ? "writable " : "", Py_TYPE(obj)->tp_name);
        return -1;
    }
    const char *format = view->format ? view->format : "B";
    if (view->itemsize != 8 || !(strcmp(format, "d") == 0 || strcmp(format, "<d") == 0
                                 || strcmp(format, "=d") == 0)) {
        PyErr_Format(PyExc_TypeError, "%s: expected float64 items, got format '%s'", what,
                     format);
        PyBuffer_Release(view);
        return -1;
    }
    if (length >= 0 && view->len / 8 != length) {
        length_error(view, length, what);
        PyBuffer_Release(view);
        return -1;
    }
    return 0;
}

/* The numbers of a list or tuple of `length` floats (or ints) into out; -1 with a one-line
 * error naming `what` otherwise. Reads the values only: no Python code runs, so the sequence
 * cannot change under it. */
static inline int
float_sequence(PyObject *seq, double *out, Py_ssize_t length, const char *what)
{
    if (!PyList_Check(seq) && !PyTuple_Check(seq)) {
        PyErr_Format(PyExc_TypeError, "%s: expected a list or tuple of floats, got %s", what,
                     Py_TYPE(seq)->tp_name);
        return -1;
    }
    if (PySequence_Fast_GET_SIZE(seq) != length) {
        PyErr_Format(PyExc_ValueError, "%s: expected %zd floats, got %zd", what, length,
                     PySequence_Fast_GET_SIZE(seq));
        return -1;
    }
    PyObject **items = PySequence_Fast_ITEMS(seq);
    for (Py_ssize_t i = 0; i < length; i++) {
        PyObject *item = items[i];
        if (PyFloat_Check(item)) {
            out[i] = PyFloat_AS_DOUBLE(item);
        } else if (PyLong_Check(item) && !PyBool_Check(item)) {
            out[i] = PyLong_AsDouble(item);
            if (out[i] == -1.0 && PyErr_Occurred()) return -1;
        } else {
            PyErr_Format(PyExc_TypeError, "%s[%zd]: expected a float, got %s", what, i,
                         Py_TYPE(item)->tp_name);
            return -1;
        }
    }
    return 0;
}

/* A new list of the n floats at values; NULL (error set) if Python runs out of memory. */
static inline PyObject *
float_list(const double *values, Py_ssize_t n)
{
    PyObject *list = PyList_New(n);
    if (list == NULL) return NULL;
    for (Py_ssize_t i = 0; i < n; i++) {
        PyObject *item = PyFloat_FromDouble(values[i]);
        if (item == NULL) {
            Py_DECREF(list);
            return NULL;
        }
        PyList_SET_ITEM(list, i, item);
    }
    return list;
}

/* The number of entries of an array. */
#define COUNT(array) ((int)(sizeof(array) / sizeof((array)[0])))

/* -- layouts exported to Python ------------------------------------------------------------ */

/* One field of a row that a kernel writes or reads: its name and its first index (an enum
 * value of the source). Its end is the next field's start, or the row's size. */
typedef struct {
    const char *name;
    int start;
} Field;

/* mod.<attribute> = ((name, start, stop), ...) of `count` fields in a row of `size` floats.
 * -1 (error set) if the starts do not increase or the last one is not inside the row: the
 * table is then wrong, and the module is not made. */
static inline int
add_fields(PyObject *mod, const char *attribute, const Field *fields, int count, int size)
{
    PyObject *tuple = PyTuple_New(count);
    if (tuple == NULL) return -1;
    for (int i = 0; i < count; i++) {
        int stop = i + 1 < count ? fields[i + 1].start : size;
        if (stop <= fields[i].start) {
            PyErr_Format(PyExc_SystemError, "%s: field %s starts at %d, not before %d",
                         attribute, fields[i].name, fields[i].start, stop);
            Py_DECREF(tuple);
            return -1;
        }
        PyObject *item = Py_BuildValue("(sii)", fields[i].name, fields[i].start, stop);
        if (item == NULL) {
            Py_DECREF(tuple);
            return -1;
        }
        PyTuple_SET_ITEM(tuple, i, item);
    }
    int status = PyModule_AddObjectRef(mod, attribute, tuple);
    Py_DECREF(tuple);
    return status;
}

/* mod.<attribute> = the `count` names in order (a constant order: names[i] is what position
 * i holds); -1 (error set) if one is missing. */
static inline int
add_names(PyObject *mod, const char *attribute, const char *const *names, int count)
{
    PyObject *tuple = PyTuple_New(count);
    if (tuple == NULL) return -1;
    for (int i = 0; i < count; i++) {
        PyObject *item = names[i] == NULL ? NULL : PyUnicode_FromString(names[i]);
        if (item == NULL) {
            if (!PyErr_Occurred())
                PyErr_Format(PyExc_SystemError, "%s: no name for position %d", attribute, i);
            Py_DECREF(tuple);
            return -1;
        }
        PyTuple_SET_ITEM(tuple, i, item);
    }
    int status = PyModule_AddObjectRef(mod, attribute, tuple);
    Py_DECREF(tuple);
    return status;
}

#endif
