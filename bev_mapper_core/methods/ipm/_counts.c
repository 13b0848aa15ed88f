/* IPM's per-cell counting, compiled: the optional fast path of
 * bev_mapper_core.methods.ipm.mapper.IpmMapper.map (whose numpy path gives the same maps; the
 * tests check the two agree to the bit).
 *
 * add(counts, S, cells, ids, table, hidden)
 *   counts  writable uint8 (N, S), S a multiple of 8: per cell its fields (each class's count,
 *           then the cameras'), zero-padded to S bytes
 *   cells   int64 (n,): the cells one camera sees (unique), flat indices < N
 *   ids     uint8 (n,): the label id of each of those cells' pixels
 *   table   uint8 (256, S): what a label id adds to the fields (class indicators, then 1)
 *   hidden  int64 (k,): increasing indices into cells / ids that add nothing (hidden from the
 *           camera)
 *   A field counts at most every camera, and the caller checks the rig has fewer than 256: no
 *   byte ever carries, so 8 fields add as one uint64.
 *
 * divide(counts, S, C, probs, known)
 *   probs   writable float32 (C, N): field f < C of each cell over its camera count (field C;
 *           1 where it is 0)
 *   known   writable uint8 (N,): 1 where a camera counts the cell
 *   Each quotient is float32's (as numpy's acc / np.maximum(count, 1) of float32 arrays), taken
 *   from a table of a / d for the camera counts d that occur.
 *
 * The GIL is released while either runs.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

static PyObject *add(PyObject *self, PyObject *args)
{
    (void)self;
    Py_buffer counts, cells, ids, table, hidden;
    Py_ssize_t S;
    if (!PyArg_ParseTuple(args, "w*ny*y*y*y*", &counts, &S, &cells, &ids, &table, &hidden))
        return NULL;
    PyObject *result = NULL;
    const Py_ssize_t n = ids.len, k = hidden.len / 8;
    const Py_ssize_t N = S > 0 ? counts.len / S : 0, words = S / 8;
    if (S < 8 || S % 8 || counts.len % S || cells.len != n * 8 || table.len != 256 * S || hidden.len % 8) {
        PyErr_SetString(PyExc_ValueError, "add: buffers of mismatched sizes");
    } else {
        const int64_t *c = cells.buf, *h = hidden.buf;
        const uint8_t *id = ids.buf, *t = table.buf;
        uint8_t *acc = counts.buf;
        int bad = 0;
        Py_BEGIN_ALLOW_THREADS
        Py_ssize_t next = 0; /* the next hidden index */
        for (Py_ssize_t i = 0; i < n; i++) {
            if (next < k && h[next] == i) {
                next++;
                continue;
            }
            if (c[i] < 0 || c[i] >= N) {
                bad = 1;
                break;
            }
            uint8_t *cell = acc + c[i] * S;
            const uint8_t *row = t + (Py_ssize_t)id[i] * S;
            for (Py_ssize_t w = 0; w < words; w++) {
                uint64_t x, y;
                memcpy(&x, cell + 8 * w, 8);
                memcpy(&y, row + 8 * w, 8);
                x += y; /* bytewise: no field carries */
                memcpy(cell + 8 * w, &x, 8);
            }
        }
        Py_END_ALLOW_THREADS
        if (bad)
            PyErr_SetString(PyExc_IndexError, "add: a cell index is outside the grid");
        else
            result = Py_NewRef(Py_None);
    }
    PyBuffer_Release(&counts);
    PyBuffer_Release(&cells);
    PyBuffer_Release(&ids);
    PyBuffer_Release(&table);
    PyBuffer_Release(&hidden);
    return result;
}

static PyObject *divide(PyObject *self, PyObject *args)
{
    (void)self;
    Py_buffer counts, probs, known;
    Py_ssize_t S, C;
    if (!PyArg_ParseTuple(args, "y*nnw*w*", &counts, &S, &C, &probs, &known))
        return NULL;
    PyObject *result = NULL;
    const Py_ssize_t N = known.len;
    float *quotients = NULL;
    if (C < 1 || S <= C || counts.len != N * S || probs.len != (Py_ssize_t)sizeof(float) * C * N) {
        PyErr_SetString(PyExc_ValueError, "divide: buffers of mismatched sizes");
    } else if (!(quotients = malloc(sizeof(float) * 256 * 256))) {
        PyErr_NoMemory();
    } else {
        const uint8_t *acc = counts.buf;
        float *p = probs.buf;
        uint8_t *kn = known.buf;
        Py_BEGIN_ALLOW_THREADS
        uint8_t most = 0; /* the largest camera count: the quotients' rows 0..most */
        for (Py_ssize_t i = 0; i < N; i++) {
            uint8_t cams = acc[i * S + C];
            kn[i] = cams > 0;
            most = cams > most ? cams : most;
        }
        for (int d = 0; d <= most; d++) {
            float div = d > 0 ? (float)d : 1.0f;
            for (int a = 0; a < 256; a++)
                quotients[d * 256 + a] = (float)a / div;
        }
        for (Py_ssize_t i = 0; i < N; i++) {
            const uint8_t *cell = acc + i * S;
            const float *q = quotients + 256 * (Py_ssize_t)cell[C];
            for (Py_ssize_t f = 0; f < C; f++)
                p[f * N + i] = q[cell[f]];
        }
        Py_END_ALLOW_THREADS
        result = Py_NewRef(Py_None);
    }
    free(quotients);
    PyBuffer_Release(&counts);
    PyBuffer_Release(&probs);
    PyBuffer_Release(&known);
    return result;
}

static PyMethodDef methods[] = {
    {"add", add, METH_VARARGS,
     "add(counts, S, cells, ids, table, hidden): one camera's label ids into the per-cell counts"},
    {"divide", divide, METH_VARARGS,
     "divide(counts, S, C, probs, known): the counts over each cell's camera count, and the known cells"},
    {NULL, NULL, 0, NULL}};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_counts", NULL, -1, methods, NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__counts(void) { return PyModule_Create(&module); }
