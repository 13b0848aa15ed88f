/* Clipped Chamfer distances of one class, compiled: the optional fast path of
 * bev_mapper_core.metrics.functional (which has the same results in numpy and OpenCV, and tests
 * that the two agree to the bit).
 *
 * distances(pred, truth, bit, H, W, reach, resolution, clip, out_p, out_g) -> (n_p, n_g)
 *
 *   pred, truth   H*W bytes each, row-major; a cell is in the set where (byte & bit) != 0 (the
 *                 packed layers of bev_mapper_core.metrics._packed, or 0/1 bool layers, bit 1)
 *   reach         cells: distances up to it are exact, the others are only known to be beyond
 *                 it (the caller's clip / resolution is at most reach cells, so they clip)
 *   out_p, out_g  writable float64 buffers of at least H*W entries: for each cell of pred (of
 *                 truth), row-major, min(sqrt(d2) * resolution, clip), d2 the squared distance
 *                 in cells to the nearest cell of the other set (0 inside it); clip for every
 *                 cell when the other set is empty
 *
 * The squared distance is exact (integers throughout): d2(i, j) = min over columns j' of
 * (j - j')^2 + v(i, j')^2, v the distance along column j' to the nearest cell of the set
 * (Meijster et al.'s two phases; the second one only at the cells asked for, and only as far as
 * the reach). sqrt is IEEE-correctly rounded, so the metres equal numpy's
 * np.minimum(np.sqrt(d2) * resolution, clip) to the bit. The GIL is released while it runs.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

/* v[(i - r0) * w + (j - c0)]: rows from (i, j) to the nearest cell of the set in column j inside
 * the box [r0, r1) x [c0, c1), capped at cap. Branch-free rows, so that the compiler vectorizes
 * them. */
static void column_distances(const uint8_t *set, uint8_t bit, Py_ssize_t W, Py_ssize_t r0,
                             Py_ssize_t r1, Py_ssize_t c0, Py_ssize_t c1, uint16_t cap, uint16_t *v)
{
    const Py_ssize_t w = c1 - c0;
    const uint8_t *s = set + r0 * W + c0;
    for (Py_ssize_t j = 0; j < w; j++)
        v[j] = (s[j] & bit) ? 0 : cap;
    for (Py_ssize_t i = 1; i < r1 - r0; i++) { /* downwards: from the nearest cell above */
        s = set + (r0 + i) * W + c0;
        uint16_t *row = v + i * w;
        const uint16_t *up = row - w;
        for (Py_ssize_t j = 0; j < w; j++) {
            uint16_t d = up[j] < cap ? (uint16_t)(up[j] + 1) : cap;
            row[j] = (s[j] & bit) ? 0 : d;
        }
    }
    for (Py_ssize_t i = r1 - r0 - 2; i >= 0; i--) { /* upwards: or from the nearest cell below */
        uint16_t *row = v + i * w;
        const uint16_t *down = row + w;
        for (Py_ssize_t j = 0; j < w; j++) {
            uint16_t d = (uint16_t)(down[j] + 1);
            row[j] = d < row[j] ? d : row[j];
        }
    }
}

/* 8 bytes from p (any alignment) */
static inline uint64_t load8(const uint8_t *p)
{
    uint64_t x;
    memcpy(&x, p, 8);
    return x;
}

/* Squared distance from (i, j) to the nearest cell of the set whose column distances are v
 * (box-relative), or beyond = r * r + 1 when none is within r cells. */
static int64_t nearest_d2(const uint16_t *v, Py_ssize_t w, Py_ssize_t i, Py_ssize_t j, int64_t r)
{
    const uint16_t *row = v + i * w;
    int64_t best = r * r + 1;
    for (int64_t dj = 0; dj <= r; dj++) {
        int64_t dj2 = dj * dj;
        if (dj2 >= best)
            break;
        if (j - dj >= 0) {
            int64_t h = row[j - dj];
            if (h <= r && dj2 + h * h < best)
                best = dj2 + h * h;
        }
        if (dj && j + dj < w) {
            int64_t h = row[j + dj];
            if (h <= r && dj2 + h * h < best)
                best = dj2 + h * h;
        }
    }
    return best;
}

/* The clipped distance (metres) of cell (i, j) (box-relative) of one set to the other set, whose
 * column distances are v: 0 inside it (in_other), else min(sqrt(d2) * res, clip). */
static inline double clipped(int in_other, const uint16_t *v, Py_ssize_t w, Py_ssize_t i, Py_ssize_t j,
                             int64_t r, double res, double clip)
{
    if (in_other)
        return 0.0;
    int64_t d2 = nearest_d2(v, w, i, j, r);
    if (d2 > r * r) /* none within r cells: beyond the clip */
        return clip;
    double d = sqrt((double)d2) * res;
    return d < clip ? d : clip;
}

typedef struct {
    const uint8_t *pred, *truth;
    uint8_t bit;
    Py_ssize_t H, W;
    int64_t r;
    double resolution, clip;
    double *out_p, *out_g;
    Py_ssize_t n_p, n_g;
    int failed; /* out of memory */
} Job;

static void run(Job *job)
{
    const uint8_t *pred = job->pred, *truth = job->truth;
    const uint8_t bit = job->bit;
    const Py_ssize_t H = job->H, W = job->W;
    /* the box around both sets, and their sizes */
    Py_ssize_t r0 = H, r1 = 0, c0 = W, c1 = 0, n_p = 0, n_g = 0;
    for (Py_ssize_t i = 0; i < H; i++) {
        const uint8_t *p = pred + i * W, *t = truth + i * W;
        Py_ssize_t cp = 0, cg = 0;
        for (Py_ssize_t j = 0; j < W; j++) { /* vectorized */
            cp += (p[j] & bit) != 0;
            cg += (t[j] & bit) != 0;
        }
        if (!(cp | cg))
            continue;
        n_p += cp;
        n_g += cg;
        Py_ssize_t first = 0, last = W - 1;
        while (!((p[first] | t[first]) & bit))
            first++;
        while (!((p[last] | t[last]) & bit))
            last--;
        if (i < r0)
            r0 = i;
        r1 = i + 1;
        if (first < c0)
            c0 = first;
        if (last + 1 > c1)
            c1 = last + 1;
    }
    job->n_p = n_p;
    job->n_g = n_g;
    if (!n_p && !n_g)
        return;
    const double clip = job->clip, res = job->resolution;
    if (!n_p || !n_g) { /* the distance to an empty set: clipped */
        double *out = n_p ? job->out_p : job->out_g;
        for (Py_ssize_t k = 0; k < n_p + n_g; k++)
            out[k] = clip;
        return;
    }
    const Py_ssize_t h = r1 - r0, w = c1 - c0;
    int64_t r = job->r;
    if (r > (int64_t)(h + w)) /* no two cells of the box are farther apart */
        r = (int64_t)(h + w);
    const uint16_t cap = (uint16_t)(r + 1);
    const size_t box = (size_t)h * (size_t)w;
    uint16_t *v_p = malloc(sizeof(uint16_t) * box), *v_g = malloc(sizeof(uint16_t) * box);
    if (!v_p || !v_g) {
        free(v_p);
        free(v_g);
        job->failed = 1;
        return;
    }
    column_distances(pred, bit, W, r0, r1, c0, c1, cap, v_p);
    column_distances(truth, bit, W, r0, r1, c0, c1, cap, v_g);
    const uint64_t bits8 = 0x0101010101010101ull * bit;
    Py_ssize_t kp = 0, kg = 0;
    for (Py_ssize_t i = r0; i < r1; i++) {
        const uint8_t *p = pred + i * W, *t = truth + i * W;
        for (Py_ssize_t j = c0; j < c1; j++) {
            if (j + 8 <= c1 && !((load8(p + j) | load8(t + j)) & bits8)) {
                j += 7; /* none of these 8 cells is in either set */
                continue;
            }
            int inp = (p[j] & bit) != 0, ing = (t[j] & bit) != 0;
            if (inp)
                job->out_p[kp++] = clipped(ing, v_g, w, i - r0, j - c0, r, res, clip);
            if (ing)
                job->out_g[kg++] = clipped(inp, v_p, w, i - r0, j - c0, r, res, clip);
        }
    }
    free(v_p);
    free(v_g);
}

static PyObject *distances(PyObject *self, PyObject *args)
{
    (void)self;
    Py_buffer pred, truth, out_p, out_g;
    int bit;
    Py_ssize_t H, W;
    long long reach;
    double resolution, clip;
    if (!PyArg_ParseTuple(args, "y*y*innLddw*w*", &pred, &truth, &bit, &H, &W, &reach, &resolution,
                          &clip, &out_p, &out_g))
        return NULL;
    PyObject *result = NULL;
    Py_ssize_t N = H * W;
    if (H < 0 || W < 0 || bit < 1 || bit > 255 || reach < 0 || (H + W) >= 65534) {
        PyErr_SetString(PyExc_ValueError, "distances: bad grid size, bit or reach");
    } else if (pred.len < N || truth.len < N || out_p.len < N * (Py_ssize_t)sizeof(double) ||
               out_g.len < N * (Py_ssize_t)sizeof(double)) {
        PyErr_SetString(PyExc_ValueError, "distances: a buffer is smaller than the grid");
    } else {
        Job job = {pred.buf, truth.buf, (uint8_t)bit, H, W, reach, resolution, clip, out_p.buf,
                   out_g.buf, 0, 0, 0};
        Py_BEGIN_ALLOW_THREADS
        run(&job);
        Py_END_ALLOW_THREADS
        if (job.failed)
            PyErr_NoMemory();
        else
            result = Py_BuildValue("nn", job.n_p, job.n_g);
    }
    PyBuffer_Release(&pred);
    PyBuffer_Release(&truth);
    PyBuffer_Release(&out_p);
    PyBuffer_Release(&out_g);
    return result;
}

static PyMethodDef methods[] = {
    {"distances", distances, METH_VARARGS,
     "distances(pred, truth, bit, H, W, reach, resolution, clip, out_p, out_g) -> (n_p, n_g): "
     "clipped Chamfer distances of one class (see the source's header)"},
    {NULL, NULL, 0, NULL}};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_chamfer", NULL, -1, methods, NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__chamfer(void) { return PyModule_Create(&module); }
