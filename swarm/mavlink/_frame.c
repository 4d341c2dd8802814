/* MAVLink 2 framing of one unsigned message, compiled (issue 16): swarm.mavlink.parse.FastFrame.
 *
 *   frame_v2    header, payload (its trailing zero bytes dropped, one byte kept) and the
 *               CRC-16/MCRF4XX checksum over everything after the magic byte plus the
 *               message's CRC extra: the bytes pymavlink's MAVLink.send writes unsigned
 *   payload_v2  the reverse: the payload of one frame, zero-padded back to its full size, and
 *               who sent it; None for anything that is not exactly one unsigned MAVLink 2
 *               frame of that message with a valid checksum
 *
 * The payload itself is packed and unpacked in Python with pymavlink's own struct format of the
 * message (FastFrame), so the field layout has one source. tests/mavlink/test_parse.py binds
 * both functions to pymavlink's frames byte for byte (random fields, sequence numbers and ids,
 * every corruption of a valid frame).
 *
 * Why C: these run for every setpoint and every position sample, at each agent and at each of
 * the world's vehicles (~100 frames per 20 ms step at N = 24). In Python they were about ten
 * small calls each (struct headers, bytearray joins, the CRC object), ~2 µs hot but 18-29 µs in
 * a realtime swarm where 25 processes share two cores and every step starts cold.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stdint.h>
#include <string.h>

#define MAGIC_V2 0xFD
#define HEADER_SIZE 10 /* magic, len, incompat, compat, seq, sysid, compid, msgid (3 bytes) */
#define CHECKSUM_SIZE 2
#define MAX_PAYLOAD 255

/* CRC-16/MCRF4XX (MAVLink's X.25 checksum), byte by byte as MAVLink's checksum.h does. */
static uint16_t
crc_accumulate(uint8_t byte, uint16_t crc)
{
    uint8_t tmp = byte ^ (uint8_t)(crc & 0xFF);
    tmp ^= (uint8_t)(tmp << 4);
    return (uint16_t)((crc >> 8) ^ ((uint16_t)tmp << 8) ^ ((uint16_t)tmp << 3) ^ (tmp >> 4));
}

static uint16_t
frame_checksum(const uint8_t *after_magic, Py_ssize_t size, uint8_t crc_extra)
{
    uint16_t crc = 0xFFFF;
    for (Py_ssize_t i = 0; i < size; i++) crc = crc_accumulate(after_magic[i], crc);
    return crc_accumulate(crc_extra, crc);
}

static int
check_nargs(Py_ssize_t nargs, Py_ssize_t expected, const char *name)
{
    if (nargs == expected) return 0;
    PyErr_Format(PyExc_TypeError, "%s takes %zd arguments, got %zd", name, expected, nargs);
    return -1;
}

static int
read_long(PyObject *arg, const char *name, long lower, long upper, long *out)
{
    long value = PyLong_AsLong(arg);
    if (value == -1 && PyErr_Occurred()) return -1;
    if (value < lower || value > upper) {
        PyErr_Format(PyExc_ValueError, "%s must be in [%ld, %ld], got %ld", name, lower, upper,
                     value);
        return -1;
    }
    *out = value;
    return 0;
}

PyDoc_STRVAR(frame_v2_doc,
"frame_v2(payload, seq, system_id, component_id, message_id, crc_extra) -> bytes\n\n"
"The unsigned MAVLink 2 frame of a packed payload (at most 255 bytes), as pymavlink sends it.");

static PyObject *
py_frame_v2(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    if (check_nargs(nargs, 6, "frame_v2")) return NULL;
    Py_buffer payload;
    if (PyObject_GetBuffer(args[0], &payload, PyBUF_SIMPLE) < 0) return NULL;
    long seq, system, component, message, extra;
    PyObject *frame = NULL;
    if (payload.len < 1 || payload.len > MAX_PAYLOAD) {
        PyErr_Format(PyExc_ValueError, "a payload holds 1 to %d bytes, got %zd", MAX_PAYLOAD,
                     payload.len);
        goto done;
    }
    if (read_long(args[1], "seq", 0, 255, &seq) < 0
            || read_long(args[2], "system_id", 0, 255, &system) < 0
            || read_long(args[3], "component_id", 0, 255, &component) < 0
            || read_long(args[4], "message_id", 0, 0xFFFFFF, &message) < 0
            || read_long(args[5], "crc_extra", 0, 255, &extra) < 0)
        goto done;
    const uint8_t *data = payload.buf;
    Py_ssize_t length = payload.len;
    while (length > 1 && data[length - 1] == 0) length--; /* MAVLink 2 payload truncation */
    frame = PyBytes_FromStringAndSize(NULL, HEADER_SIZE + length + CHECKSUM_SIZE);
    if (frame == NULL) goto done;
    uint8_t *out = (uint8_t *)PyBytes_AS_STRING(frame);
    out[0] = MAGIC_V2;
    out[1] = (uint8_t)length;
    out[2] = 0; /* incompat flags: unsigned */
    out[3] = 0; /* compat flags */
    out[4] = (uint8_t)seq;
    out[5] = (uint8_t)system;
    out[6] = (uint8_t)component;
    out[7] = (uint8_t)(message & 0xFF);
    out[8] = (uint8_t)((message >> 8) & 0xFF);
    out[9] = (uint8_t)((message >> 16) & 0xFF);
    memcpy(out + HEADER_SIZE, data, (size_t)length);
    uint16_t crc = frame_checksum(out + 1, HEADER_SIZE - 1 + length, (uint8_t)extra);
    out[HEADER_SIZE + length] = (uint8_t)(crc & 0xFF);
    out[HEADER_SIZE + length + 1] = (uint8_t)(crc >> 8);
done:
    PyBuffer_Release(&payload);
    return frame;
}

PyDoc_STRVAR(payload_v2_doc,
"payload_v2(data, message_id, crc_extra, payload_size) -> (system_id, component_id, payload)\n"
"or None\n\n"
"The payload of ``data`` zero-padded to ``payload_size`` bytes when ``data`` is exactly one\n"
"unsigned MAVLink 2 frame of message ``message_id`` with a valid checksum; None otherwise.");

static PyObject *
py_payload_v2(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    if (check_nargs(nargs, 4, "payload_v2")) return NULL;
    long message, extra, size;
    if (read_long(args[1], "message_id", 0, 0xFFFFFF, &message) < 0
            || read_long(args[2], "crc_extra", 0, 255, &extra) < 0
            || read_long(args[3], "payload_size", 1, MAX_PAYLOAD, &size) < 0)
        return NULL;
    Py_buffer view;
    if (PyObject_GetBuffer(args[0], &view, PyBUF_SIMPLE) < 0) return NULL;
    PyObject *result = NULL;
    const uint8_t *data = view.buf;
    Py_ssize_t total = view.len;
    if (total < HEADER_SIZE + CHECKSUM_SIZE || data[0] != MAGIC_V2 || data[2] != 0) goto none;
    Py_ssize_t length = data[1];
    if (total != HEADER_SIZE + length + CHECKSUM_SIZE || length > size) goto none;
    long id = (long)data[7] | ((long)data[8] << 8) | ((long)data[9] << 16);
    if (id != message) goto none;
    uint16_t crc = frame_checksum(data + 1, HEADER_SIZE - 1 + length, (uint8_t)extra);
    uint16_t sent = (uint16_t)(data[HEADER_SIZE + length] | (data[HEADER_SIZE + length + 1] << 8));
    if (crc != sent) goto none;
    PyObject *payload = PyBytes_FromStringAndSize(NULL, size);
    if (payload == NULL) goto done;
    uint8_t *out = (uint8_t *)PyBytes_AS_STRING(payload);
    memcpy(out, data + HEADER_SIZE, (size_t)length);
    memset(out + length, 0, (size_t)(size - length));
    result = Py_BuildValue("(iiN)", (int)data[5], (int)data[6], payload);
    goto done;
none:
    result = Py_NewRef(Py_None);
done:
    PyBuffer_Release(&view);
    return result;
}

static PyMethodDef methods[] = {
    {"frame_v2", (PyCFunction)(void (*)(void))py_frame_v2, METH_FASTCALL, frame_v2_doc},
    {"payload_v2", (PyCFunction)(void (*)(void))py_payload_v2, METH_FASTCALL, payload_v2_doc},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT,
    .m_name = "swarm.mavlink._frame",
    .m_doc = "MAVLink 2 framing of one unsigned message, compiled (see the source's header).",
    .m_size = -1,
    .m_methods = methods,
};

PyMODINIT_FUNC
PyInit__frame(void)
{
    return PyModule_Create(&module);
}
