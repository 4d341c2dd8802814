/* The exchange's per-step pass over the other drones, compiled (swarm.agent.nearby):
 *
 *   nearby  the other drones a step can use, their relayed beacons carried forward
 *           (swarm.agent.exchange: Vicinity, RealtimeExchange.beacons)
 *
 * Why C: a step runs it over all N drones, so that the step's Python work grows with the
 * drones around it, not with N. It reads BeaconRelayWire rows by the wire's columns
 * (swarm/messages/relay_row.h, the one statement of them) and exports the order of its carry
 * (CARRY_FIELDS). tests/agent/test_nearby.py and tests/agent/test_exchange.py bind it to each
 * relayed beacon's carry-forward formula computed alone, bit for bit, and to the QP rows the
 * core builds from every drone.
 */
#include "../compiled.h"

#include "../messages/relay_row.h"

/* carry: the relay's age, the own sample's age a_i, the own velocity last sent (3), the
 * longest a beacon is carried forward (the vehicles' failsafe timeout). */
enum { CARRY_RELAY_AGE, CARRY_SAMPLE_AGE, CARRY_FLYING, CARRY_HOLD = CARRY_FLYING + 3,
       N_CARRY };

static const Field carry_fields[] = {
    {"relay_age", CARRY_RELAY_AGE}, {"sample_age", CARRY_SAMPLE_AGE},
    {"flying", CARRY_FLYING}, {"hold", CARRY_HOLD},
};

PyDoc_STRVAR(nearby_doc,
"nearby(rows, width, ids, skip, carry, around, radius, always) -> dict\n--\n\n"
"{id: [x, y, z]} of the other drones a step can use (exchange.Vicinity). Row k of rows\n"
"(n x width float64) is drone ids[k]'s (ids None: drone k), its position in columns 0-2\n"
"(with carry: the relay row's position columns).\n"
"carry None, or CARRY_FIELDS [relay age, own sample age a_i, flying (3), hold] with width\n"
"RELAY_WIDTH (the BeaconRelayWire columns): each position carried forward as\n"
"p + min(a_j + (relay age + held_j), hold) v - a_i flying (RealtimeExchange.beacons).\n"
"Drone skip is left out; with around = [x, y, z], so is each drone farther than radius from\n"
"it that always (bytes, by id; past its end: unmarked) does not mark. A position that is\n"
"not finite is kept (the core counts it).");

static PyObject *
py_nearby(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    if (check_nargs(nargs, 8, "nearby")) return NULL;
    Py_ssize_t width = PyLong_AsSsize_t(args[1]), skip = PyLong_AsSsize_t(args[3]);
    double radius = PyFloat_AsDouble(args[6]);
    if (PyErr_Occurred()) return NULL;
    double carry[N_CARRY], around[3];
    int carried = args[4] != Py_None, centred = args[5] != Py_None;
    if ((carried && float_sequence(args[4], carry, N_CARRY, "carry"))
        || (centred && float_sequence(args[5], around, 3, "around")))
        return NULL;
    if (width < 3 || (carried && width != RELAY_WIDTH)) {
        PyErr_Format(PyExc_ValueError, "nearby: width %zd: expected >= 3 (%d with carry)",
                     width, (int)RELAY_WIDTH);
        return NULL;
    }
    PyObject *ids = args[2], *always = args[7];
    if (!PyBytes_Check(always)) {
        PyErr_Format(PyExc_TypeError, "nearby: always: expected bytes, got %s",
                     Py_TYPE(always)->tp_name);
        return NULL;
    }
    Py_buffer rows;
    if (float64_buffer(args[0], &rows, 0, -1, "rows")) return NULL;
    Py_ssize_t n = rows.len / 8 / width;
    PyObject *out = NULL;
    if (n * width * 8 != rows.len) {
        PyErr_Format(PyExc_ValueError, "nearby: rows: %zd floats are not rows of %zd",
                     rows.len / 8, width);
        goto done;
    }
    if (ids != Py_None && (!PyList_Check(ids) || PyList_GET_SIZE(ids) != n)) {
        PyErr_Format(PyExc_ValueError, "nearby: ids: expected None or a list of %zd ints", n);
        goto done;
    }
    const unsigned char *marked = (const unsigned char *)PyBytes_AS_STRING(always);
    Py_ssize_t n_marked = PyBytes_GET_SIZE(always);
    const double limit = radius * radius;
    const int at = carried ? RELAY_POSITION : 0;  /* where a row's position starts */
    out = PyDict_New();
    for (Py_ssize_t k = 0; out != NULL && k < n; k++) {
        Py_ssize_t id = k;
        if (ids != Py_None) {
            id = PyLong_AsSsize_t(PyList_GET_ITEM(ids, k));
            if (id == -1 && PyErr_Occurred()) goto fail;
        }
        if (id == skip) continue;
        if (id < 0) {
            PyErr_Format(PyExc_ValueError, "nearby: ids[%zd]: drone %zd is negative", k, id);
            goto fail;
        }
        const double *row = (const double *)rows.buf + k * width;
        double p[3] = {row[at], row[at + 1], row[at + 2]};
        if (carried) {
            double lead = row[RELAY_SAMPLE_AGE] + (carry[CARRY_RELAY_AGE] + row[RELAY_HELD]);
            if (lead > carry[CARRY_HOLD]) lead = carry[CARRY_HOLD];  /* np.minimum: NaN stays */
            for (int i = 0; i < 3; i++)
                p[i] = p[i] + lead * row[RELAY_VELOCITY + i]
                       - carry[CARRY_SAMPLE_AGE] * carry[CARRY_FLYING + i];
        }
        if (centred && !(id < n_marked && marked[id])) {
            double dx = p[0] - around[0], dy = p[1] - around[1], dz = p[2] - around[2];
            if (dx * dx + dy * dy + dz * dz > limit) continue;  /* NaN: kept */
        }
        PyObject *key = PyLong_FromSsize_t(id), *value = float_list(p, 3);
        int failed = key == NULL || value == NULL || PyDict_SetItem(out, key, value) != 0;
        Py_XDECREF(key);
        Py_XDECREF(value);
        if (failed) goto fail;
    }
    goto done;
fail:
    Py_CLEAR(out);
done:
    PyBuffer_Release(&rows);
    return out;
}

static PyMethodDef methods[] = {
    {"nearby", (PyCFunction)(void (*)(void))py_nearby, METH_FASTCALL, nearby_doc},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT,
    .m_name = "swarm.agent._exchange",
    .m_doc = "The exchange's pass over the other drones, compiled (see the source's header).",
    .m_size = -1,
    .m_methods = methods,
};

PyMODINIT_FUNC
PyInit__exchange(void)
{
    PyObject *mod = PyModule_Create(&module);
    if (mod == NULL) return NULL;
    if (add_fields(mod, "CARRY_FIELDS", carry_fields, COUNT(carry_fields), N_CARRY) < 0) {
        Py_DECREF(mod);
        return NULL;
    }
    return mod;
}
