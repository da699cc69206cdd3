/* The lidar among many circles, compiled: what `sim.geometry.add_circles_to_scan` computes, per
 * world and per circle in a loop instead of over numpy's arrays of (world, circle, beam) pairs.
 *
 * BARN's worlds hold 180-365 cylinders, and numpy spends about 50 ns on each (circle, beam)
 * pair; a loop spends a few. The arithmetic is the numpy version's, operation for operation
 * (IEEE double: the same sums, products and square roots give the same bits), so both give the
 * same ranges; only a beam exactly at a circle's tangent may fall the other way, where the
 * libraries' atan2 or asin differ in their last bit (tests/sim/test_raycast.py).
 *
 * Optional: `pip install` builds it where a C compiler is at hand, and the simulator falls back
 * to the numpy version where it is not (sim/raycast.py).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>

/* atan2 to within 1e-5 rad (Abramowitz & Stegun 4.4.49 on [0, 1] and the octants'
 * symmetries), and asin by its series where the circle is small in view (r / d <= 0.3: within
 * 1e-6 rad), libm's elsewhere: only used to bound which beams a circle may cover. */
#define ANGLE_ERROR 2e-5
static double approx_atan2(double y, double x) {
    const double ax = fabs(x), ay = fabs(y);
    const double big = ax > ay ? ax : ay, small = ax > ay ? ay : ax;
    if (big == 0.0) return 0.0;
    const double a = small / big, s = a * a;
    double r = a * (0.9998660 + s * (-0.3302995 + s * (0.1801410 + s * (-0.0851330 +
                                                                     s * 0.0208351))));
    if (ay > ax) r = 1.57079632679489662 - r;
    if (x < 0.0) r = 3.14159265358979324 - r;
    return y < 0.0 ? -r : r;
}

static double approx_asin(double x) {
    if (x > 0.3) return asin(x < 1.0 ? x : 1.0);
    const double s = x * x;
    return x * (1.0 + s * (1.0 / 6.0 + s * (3.0 / 40.0 + s * (5.0 / 112.0))));
}

/* Lower scan[k] for beams low <= k < high to where each meets a circle at (ahead, left) from
 * the sensor (square: its distance squared less its radius squared), when it does within
 * max_range. Branch-free, so the compiler may vectorise it. */
static inline void hit_beams(float *scan, const double *bc, const double *bs, long low, long high,
                             double ahead, double left, double square, double max_range,
                             double scale) {
    for (long k = low; k < high; k++) {
        const double along = ahead * bc[k] + left * bs[k];
        const double disc = along * along - square;
        const double near = along - sqrt(disc > 0.0 ? disc : 0.0);
        const int hit = (disc >= 0.0) & (near >= 0.0) & (near <= max_range);
        const float value = hit ? (float)(scale == 1.0 ? near : near / scale) : INFINITY;
        scan[k] = value < scan[k] ? value : scan[k];
    }
}

/* cast_circles(pose, centres, radius, beam_cos, beam_sin, increment, max_range, scale,
 *              ranges, clearance, n, m, b)
 *
 * pose (n, 3) float64; centres (n, m, 2) float64; beam_cos, beam_sin (b,) float64;
 * ranges (n, b) float32, lowered in place to each beam's nearest hit / scale;
 * clearance (n,) float64, lowered in place to the distance to each world's nearest surface.
 */
static PyObject *cast_circles(PyObject *self, PyObject *args) {
    Py_buffer pose, centres, beam_cos, beam_sin, ranges, clearance;
    double radius, increment, max_range, scale;
    Py_ssize_t n, m, b;
    if (!PyArg_ParseTuple(args, "y*y*dy*y*dddw*w*nnn", &pose, &centres, &radius, &beam_cos,
                          &beam_sin, &increment, &max_range, &scale, &ranges, &clearance, &n,
                          &m, &b)) {
        return NULL;
    }
    PyObject *result = NULL;
    if (pose.len != n * 3 * (Py_ssize_t)sizeof(double) ||
        centres.len != n * m * 2 * (Py_ssize_t)sizeof(double) ||
        beam_cos.len != b * (Py_ssize_t)sizeof(double) ||
        beam_sin.len != b * (Py_ssize_t)sizeof(double) ||
        ranges.len != n * b * (Py_ssize_t)sizeof(float) ||
        clearance.len != n * (Py_ssize_t)sizeof(double)) {
        PyErr_SetString(PyExc_ValueError, "cast_circles: buffer sizes do not match n, m, b");
        goto done;
    }
    const double *p = pose.buf, *c = centres.buf, *bc = beam_cos.buf, *bs = beam_sin.buf;
    float *out = ranges.buf;
    double *gap = clearance.buf;
    const double r2 = radius * radius;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t w = 0; w < n; w++) {
        const double x = p[3 * w], y = p[3 * w + 1], h = p[3 * w + 2];
        const double cos_h = cos(h), sin_h = sin(h);
        float *scan = out + w * b;
        double nearest_sq = INFINITY;
        for (Py_ssize_t j = 0; j < m; j++) {
            const double ox = c[2 * (w * m + j)] - x, oy = c[2 * (w * m + j) + 1] - y;
            const double ahead = cos_h * ox + sin_h * oy;
            const double left = -sin_h * ox + cos_h * oy;
            const double d2 = ahead * ahead + left * left;
            /* The clearance from the room-frame offsets, as numpy's circles_clearance sums them. */
            const double room_d2 = ox * ox + oy * oy;
            if (room_d2 < nearest_sq) nearest_sq = room_d2;
            if (d2 <= r2) { /* the sensor inside a circle touches its surface: range 0 */
                for (Py_ssize_t k = 0; k < b; k++) scan[k] = 0.0f;
                continue;
            }
            const double d = sqrt(d2);
            if (d - radius > max_range) continue; /* every beam's hit lies beyond the range */
            /* The beams the circle covers, within ANGLE_ERROR of its edges: each then gets
             * the exact test, so beams near an edge that it wrongly adds miss, and none it
             * covers is left out. */
            const double half = approx_asin(radius / d) + ANGLE_ERROR;
            const double bearing = approx_atan2(left, ahead);
            long first = (long)ceil((bearing - half) / increment);
            long last = (long)floor((bearing + half) / increment);
            if (last - first + 1 > b) last = first + b - 1;
            const double square = d2 - r2;
            long low = first % (long)b;
            if (low < 0) low += b;
            const long count = last - first + 1;
            const long tail = low + count > b ? low + count - b : 0; /* beams past the wrap */
            hit_beams(scan, bc, bs, low, low + count - tail, ahead, left, square, max_range, scale);
            hit_beams(scan, bc, bs, 0, tail, ahead, left, square, max_range, scale);
        }
        const double surface = sqrt(nearest_sq) - radius;
        if (surface < gap[w]) gap[w] = surface;
    }
    Py_END_ALLOW_THREADS
    result = Py_None;
    Py_INCREF(result);
done:
    PyBuffer_Release(&pose);
    PyBuffer_Release(&centres);
    PyBuffer_Release(&beam_cos);
    PyBuffer_Release(&beam_sin);
    PyBuffer_Release(&ranges);
    PyBuffer_Release(&clearance);
    return result;
}

static PyMethodDef methods[] = {
    {"cast_circles", cast_circles, METH_VARARGS,
     "Lower ranges (n, b) float32 to each beam's nearest circle and clearance (n,) to each "
     "world's nearest circle surface, in place."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_raycast",
                                    "The lidar among many circles, compiled.", -1, methods};

PyMODINIT_FUNC PyInit__raycast(void) { return PyModule_Create(&module); }
