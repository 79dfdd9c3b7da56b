/* road.kernels: road.physics.safe_speed as one compiled pass over the vehicles, with the
   same IEEE float64 operations in the same order as its numpy form, so the same values to
   the bit (compiled with -ffp-contract=off: no fused multiply-add). Why: a deployment's
   step calls it on ~40 vehicles, where numpy's ~28 calls cost ~0.5-2 us each and the
   arithmetic itself well under 1 us (scripts/bench_instructions.py). Optional: setup.py
   builds it where a C compiler is found, road.physics falls back to numpy elsewhere. */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <string.h>

/* np.maximum on float64: NaN in either operand gives NaN, else a if a >= b. */
static inline double np_maximum(double a, double b) {
    if (a != a) return a;
    if (b != b) return b;
    return a >= b ? a : b;
}

/* An operand: a float64 buffer of 0 or 1 dimension (a 0-d array, a length-1 or length-n
   vector), or a Python float; step 0 broadcasts one value. */
typedef struct {
    Py_buffer view;
    int held;
    double value;
    const char *data;
    Py_ssize_t step;
} operand;

/* 1: read; 0: not a form this kernel takes (numpy's path answers). */
static int take(PyObject *obj, Py_ssize_t n, operand *op, int writable) {
    op->held = 0;
    if (!writable && PyFloat_CheckExact(obj)) {
        op->value = PyFloat_AS_DOUBLE(obj);
        op->data = (const char *)&op->value;
        op->step = 0;
        return 1;
    }
    int flags = PyBUF_FORMAT | PyBUF_STRIDES | (writable ? PyBUF_WRITABLE : 0);
    if (!PyObject_CheckBuffer(obj) || PyObject_GetBuffer(obj, &op->view, flags) < 0) {
        PyErr_Clear();
        return 0;
    }
    op->held = 1;
    Py_buffer *v = &op->view;
    if (v->itemsize != 8 || v->format == NULL || strcmp(v->format, "d") != 0 || v->ndim > 1)
        return 0;
    op->data = (const char *)v->buf;
    if (v->ndim == 0) {
        op->step = 0;
        return !writable;
    }
    if (v->shape[0] == n || n < 0) { /* n < 0: any length (the output, which sets n) */
        op->step = v->strides[0];
        return 1;
    }
    if (v->shape[0] == 1 && !writable) {
        op->step = 0;
        return 1;
    }
    return 0;
}

static void release(operand *ops, int count) {
    for (int i = 0; i < count; i++)
        if (ops[i].held) PyBuffer_Release(&ops[i].view);
}

#define AT(op, i) (*(const double *)((op).data + (i) * (op).step))

/* safe_speed(gap, leader_speed, decel, leader_decel, dt, dt2, out[, no_gap]) -> bool: out
   (a writable float64 vector of n) filled with road.physics.safe_speed's values, dt and
   dt2 its step_constants; with no_gap (a float64 0-d or Python float), inf where not gap <
   no_gap (deploy.safety.leader_safe_speed's no leader, NaN included); False (out
   untouched) where an operand is not a float64 0-d or 1-d of n or 1, or a Python float:
   numpy broadcasts those, this kernel does not. */
static PyObject *safe_speed(PyObject *self, PyObject *args) {
    PyObject *obj[8] = {NULL};
    if (!PyArg_UnpackTuple(args, "safe_speed", 7, 8, &obj[0], &obj[1], &obj[2], &obj[3],
                           &obj[4], &obj[5], &obj[6], &obj[7]))
        return NULL;
    operand ops[7];
    int got = 0;
    double no_gap = 0.0;
    const int mark = obj[7] != NULL;
    if (mark) {
        operand op;
        const int ok = take(obj[7], 1, &op, 0) && op.step == 0;
        if (ok) no_gap = AT(op, 0);
        release(&op, 1);
        if (!ok) Py_RETURN_FALSE;
    }
    if (!take(obj[6], -1, &ops[6], 1) || ops[6].view.ndim != 1) {
        release(&ops[6], 1);
        Py_RETURN_FALSE;
    }
    Py_ssize_t n = ops[6].view.shape[0];
    for (; got < 6; got++) {
        if (!take(obj[got], n, &ops[got], 0)) {
            got++;
            release(ops, got);
            release(&ops[6], 1);
            Py_RETURN_FALSE;
        }
    }
    const double dt = AT(ops[4], 0), dt2 = AT(ops[5], 0);
    char *out = ops[6].view.buf;
    const Py_ssize_t out_step = ops[6].view.strides[0];
    for (Py_ssize_t i = 0; i < n; i++) {
        const double gap = AT(ops[0], i), v_l = AT(ops[1], i);
        const double b = AT(ops[2], i), b_l = AT(ops[3], i);
        /* brake_gap(v_l, max(b, b_l), dt) */
        const double reduction = np_maximum(b, b_l) * dt;
        const double steps = floor(v_l / reduction);
        const double lead_gap = dt * (steps * v_l - reduction * steps * (steps + 1.0) / 2.0);
        const double room = np_maximum(gap, 0.0) + lead_gap;
        const double bdt2 = b * dt2;
        const double k = floor((-1.0 + sqrt(1.0 + 8.0 * room / bdt2)) / 2.0);
        const double k1 = k + 1.0;
        *(double *)(out + i * out_step) =
            mark && !(gap < no_gap) ? INFINITY : (room + bdt2 * k * k1 / 2.0) / (dt * k1);
    }
    release(ops, 6);
    release(&ops[6], 1);
    Py_RETURN_TRUE;
}

/* np.minimum on float64: NaN in either operand gives NaN, else a if a <= b. */
static inline double np_minimum(double a, double b) {
    if (a != a) return a;
    if (b != b) return b;
    return a <= b ? a : b;
}

/* krauss_prior(obs, speed_factor, floor, accel, relax, length, min_gap, bt2, decel2,
   minus_bt, dt, least, out) -> bool: deploy.policy_batch.krauss_batch's prior of
   observations obs (a float64 2-D buffer of n rows, >= 4 columns: speed, limit, spacing,
   delta v) into out (a writable float64 vector of n), its constants float64 0-d arrays
   or Python floats; False (out untouched) for any other form. */
static PyObject *krauss_prior(PyObject *self, PyObject *args) {
    enum { NC = 11 };
    PyObject *obs_obj, *out_obj, *c[NC];
    if (!PyArg_UnpackTuple(args, "krauss_prior", NC + 2, NC + 2, &obs_obj, &c[0], &c[1],
                           &c[2], &c[3], &c[4], &c[5], &c[6], &c[7], &c[8], &c[9], &c[10],
                           &out_obj))
        return NULL;
    operand out;
    if (!take(out_obj, -1, &out, 1) || out.view.ndim != 1) {
        release(&out, 1);
        Py_RETURN_FALSE;
    }
    const Py_ssize_t n = out.view.shape[0];
    Py_buffer obs;
    if (PyObject_GetBuffer(obs_obj, &obs, PyBUF_FORMAT | PyBUF_STRIDES) < 0) {
        PyErr_Clear();
        release(&out, 1);
        Py_RETURN_FALSE;
    }
    double k[NC];
    int ok = obs.itemsize == 8 && obs.format != NULL && strcmp(obs.format, "d") == 0 &&
             obs.ndim == 2 && obs.shape[0] == n && obs.shape[1] >= 4;
    for (int i = 0; ok && i < NC; i++) {
        operand op;
        ok = take(c[i], 1, &op, 0) && op.step == 0;
        if (ok) k[i] = AT(op, 0);
        release(&op, 1);
    }
    if (!ok) {
        PyBuffer_Release(&obs);
        release(&out, 1);
        Py_RETURN_FALSE;
    }
    const double speed_factor = k[0], floor_ = k[1], accel = k[2], relax = k[3];
    const double length = k[4], min_gap = k[5], bt2 = k[6], decel2 = k[7];
    const double minus_bt = k[8], dt = k[9], least = k[10];
    const char *row = obs.buf;
    const Py_ssize_t rs = obs.strides[0], cs = obs.strides[1];
    char *o = out.view.buf;
    const Py_ssize_t os = out.view.strides[0];
    for (Py_ssize_t i = 0; i < n; i++, row += rs) {
        const double v = *(const double *)row, limit = *(const double *)(row + cs);
        const double spacing = *(const double *)(row + 2 * cs);
        const double delta_v = *(const double *)(row + 3 * cs);
        const double free = np_minimum(accel, (np_maximum(speed_factor * limit, floor_) - v) / relax);
        const double gap = np_maximum(spacing - length - min_gap, 0.0);
        const double v_leader = np_maximum(v - delta_v, 0.0);
        const double safe = minus_bt + sqrt(bt2 + v_leader * v_leader + decel2 * gap);
        *(double *)(o + i * os) = np_maximum(np_minimum(free, (safe - v) / dt), least);
    }
    PyBuffer_Release(&obs);
    release(&out, 1);
    Py_RETURN_TRUE;
}

/* A buffer of itemsize 8, 1-d, float64 ("d") or int64 ("l", "q"), or bool ("?", 1-d);
   its element count in *n. 0: not that form. */
static int vector(PyObject *obj, Py_buffer *v, char kind, int writable, Py_ssize_t *n) {
    int flags = PyBUF_FORMAT | PyBUF_ND | (writable ? PyBUF_WRITABLE : 0); /* C-contiguous */
    if (!PyObject_CheckBuffer(obj) || PyObject_GetBuffer(obj, v, flags) < 0) {
        PyErr_Clear();
        return 0;
    }
    const char *f = v->format;
    int ok = f != NULL && v->ndim == 1 &&
             (kind == 'd'   ? v->itemsize == 8 && strcmp(f, "d") == 0
              : kind == 'i' ? v->itemsize == 8 && (strcmp(f, "l") == 0 || strcmp(f, "q") == 0)
                            : v->itemsize == 1 && strcmp(f, "?") == 0);
    if (!ok) {
        PyBuffer_Release(v);
        return 0;
    }
    *n = v->shape[0];
    return 1;
}

/* leader_columns(gap, lead_row, rows, shape, speeds, length, min_gap, decel, driven,
   no_gap, stop_decel, out, index, ok) -> bool: deploy.observe.observe_rows' columns of
   SUMO's leaders, before any standing leader (stop line, lane end): per driven vehicle i
   of n (row rows[i] of the step's speeds, leader at row lead_row[i], -1: none; SUMO's gap
   gap[i]; own and leader's shape codes shape[i], shape[n + i] into the length, min_gap
   and decel columns), with a leader where it is on the road and spacing < no_gap:
   out (7, n) = spacing, leader's speed (own where none), leader's decel (stop_decel),
   own length, own minGap, leader's length, bumper gap (no_gap where none); gap made
   SUMO's gap (no_gap where none); index = the leader's index among the driven (-1); ok =
   has a leader. driven: observe's buffer of -1 longer than the speeds, left as found.
   False (nothing written) for any other form or an index out of range. */
static PyObject *leader_columns(PyObject *self, PyObject *args) {
    enum { NV = 9, NO = 3 };
    PyObject *o[NV + 2 + NO];
    if (!PyArg_UnpackTuple(args, "leader_columns", 14, 14, &o[0], &o[1], &o[2], &o[3], &o[4],
                           &o[5], &o[6], &o[7], &o[8], &o[9], &o[10], &o[11], &o[12], &o[13]))
        return NULL;
    static const char kinds[NV] = {'d', 'i', 'i', 'i', 'd', 'd', 'd', 'd', 'i'};
    Py_buffer v[NV], out, index, okv;
    Py_ssize_t len[NV], n_out = 0, n_index = 0, n_ok = 0;
    int got = 0, have_out = 0, have_index = 0, have_ok = 0, ok = 1;
    for (; ok && got < NV; got++)
        if (!vector(o[got], &v[got], kinds[got], got == 0 || got == 8, &len[got])) {
            ok = 0;
            break;
        }
    double no_gap = 0.0, stop_decel = 0.0;
    if (ok) {
        no_gap = PyFloat_AsDouble(o[9]);
        stop_decel = PyFloat_AsDouble(o[10]);
        if (PyErr_Occurred()) {
            PyErr_Clear();
            ok = 0;
        }
    }
    if (ok && PyObject_GetBuffer(o[11], &out, PyBUF_FORMAT | PyBUF_ND | PyBUF_WRITABLE) == 0) {
        have_out = 1;
        n_out = out.ndim == 2 && out.itemsize == 8 && strcmp(out.format, "d") == 0
                    && out.shape[0] == 7 ? out.shape[1] : -1;
    } else
        PyErr_Clear();
    if (ok && have_out) have_index = vector(o[12], &index, 'i', 1, &n_index);
    if (ok && have_index) have_ok = vector(o[13], &okv, '?', 1, &n_ok);
    const Py_ssize_t n = len[0];
    const Py_ssize_t N = ok ? len[4] : 0;
    ok = ok && have_ok && n_out == n && n_index == n && n_ok == n && len[1] == n &&
         len[2] == n && len[3] == 2 * n && len[5] == len[6] && len[6] == len[7] &&
         len[8] > N;
    if (ok) {
        const int64_t *lead_row = v[1].buf, *rows = v[2].buf, *shape = v[3].buf;
        const Py_ssize_t n_shapes = len[5];
        for (Py_ssize_t i = 0; ok && i < n; i++)
            ok = rows[i] >= 0 && rows[i] < N && lead_row[i] >= -1 && lead_row[i] < N &&
                 shape[i] >= 0 && shape[i] < n_shapes && shape[n + i] >= 0 &&
                 shape[n + i] < n_shapes;
    }
    if (ok) {
        double *gap = v[0].buf;
        const int64_t *lead_row = v[1].buf, *rows = v[2].buf, *shape = v[3].buf;
        const double *speed = v[4].buf, *length = v[5].buf, *min_gap = v[6].buf;
        const double *decel = v[7].buf;
        int64_t *driven = v[8].buf;
        double *spacing = out.buf, *lead_v = spacing + n, *lead_decel = lead_v + n;
        double *own_length = lead_decel + n, *own_min_gap = own_length + n;
        double *lead_length = own_min_gap + n, *bumper = lead_length + n;
        int64_t *lead_index = index.buf;
        char *has = okv.buf;
        for (Py_ssize_t i = 0; i < n; i++) driven[rows[i]] = (int64_t)i;
        for (Py_ssize_t i = 0; i < n; i++) {
            const double mg = min_gap[shape[i]], ll = length[shape[n + i]];
            const double sp = gap[i] + mg + ll; /* (gap + minGap) + the leader's length */
            const int64_t r = lead_row[i];
            const int with = r >= 0 && sp < no_gap;
            own_length[i] = length[shape[i]];
            own_min_gap[i] = mg;
            lead_length[i] = ll;
            has[i] = (char)with;
            if (with) {
                spacing[i] = sp;
                lead_v[i] = speed[r];
                lead_decel[i] = decel[shape[n + i]];
                lead_index[i] = driven[r];
                bumper[i] = sp - ll;
            } else {
                spacing[i] = no_gap;
                lead_v[i] = speed[rows[i]];
                lead_decel[i] = stop_decel;
                lead_index[i] = -1;
                bumper[i] = no_gap;
                gap[i] = no_gap;
            }
        }
        for (Py_ssize_t i = 0; i < n; i++) driven[rows[i]] = -1;
    }
    for (int i = 0; i < got; i++) PyBuffer_Release(&v[i]);
    if (have_out) PyBuffer_Release(&out);
    if (have_index) PyBuffer_Release(&index);
    if (have_ok) PyBuffer_Release(&okv);
    if (ok) Py_RETURN_TRUE;
    Py_RETURN_FALSE;
}

/* lane_due(lane, again, slots, lanes, step, out) -> int: deploy.slots.LaneCache.due's
   indices into out (a writable int64 vector of at least n): the i of n (ascending) where
   lane[slots[i]] != lanes[i] or again[slots[i]] <= step (a Python int, compared as the
   float64 numpy makes of it); their count. -1 (out untouched) where a form does not fit
   or a slot is outside the cache (numpy raises or wraps it there). */
static PyObject *lane_due(PyObject *self, PyObject *args) {
    PyObject *o[6];
    if (!PyArg_UnpackTuple(args, "lane_due", 6, 6, &o[0], &o[1], &o[2], &o[3], &o[4], &o[5]))
        return NULL;
    if (!PyLong_CheckExact(o[4])) return PyLong_FromLong(-1);
    const double step = PyLong_AsDouble(o[4]); /* correctly rounded, as numpy converts it */
    if (step == -1.0 && PyErr_Occurred()) {
        PyErr_Clear();
        return PyLong_FromLong(-1);
    }
    static const char kinds[5] = {'i', 'd', 'i', 'i', 'i'};
    Py_buffer v[5];
    Py_ssize_t len[5];
    int got = 0, ok = 1;
    for (; got < 5; got++)
        if (!vector(o[got < 4 ? got : 5], &v[got], kinds[got], got == 4, &len[got])) {
            ok = 0;
            break;
        }
    const Py_ssize_t n = ok ? len[2] : 0, cap = ok ? len[0] : 0;
    ok = ok && len[1] == cap && len[3] == n && len[4] >= n;
    Py_ssize_t count = -1;
    if (ok) {
        const int64_t *lane = v[0].buf, *slots = v[2].buf, *lanes = v[3].buf;
        const double *again = v[1].buf;
        for (Py_ssize_t i = 0; ok && i < n; i++) ok = slots[i] >= 0 && slots[i] < cap;
        if (ok) {
            int64_t *out = v[4].buf;
            count = 0;
            for (Py_ssize_t i = 0; i < n; i++) {
                const int64_t s = slots[i];
                if (lane[s] != lanes[i] || again[s] <= step) out[count++] = (int64_t)i;
            }
        }
    }
    for (int i = 0; i < got; i++) PyBuffer_Release(&v[i]);
    return PyLong_FromSsize_t(count);
}

/* own_columns(obs, rows, codes, speeds, pos, lead_v, arc_per_m, arc0, lookahead) -> bool:
   deploy.observe.observe_rows' own columns of n driven vehicles (rows rows of the step's
   speeds and positions, lane codes codes): obs[i, 0] = v = speeds[rows[i]], obs[i, 3] =
   v - lead_v[i], and with the look-ahead (lookahead true) obs[i, 5] -= arc_per_m[c] *
   pos[rows[i]] + arc0[c] (an open section's arc: numpy's arc, its products and sums in
   that order). obs a writable C-contiguous float64 (n, >= 4, or >= 6 with the look-ahead).
   False (nothing written) for any other form or an index out of range. */
static PyObject *own_columns(PyObject *self, PyObject *args) {
    PyObject *o[9];
    if (!PyArg_UnpackTuple(args, "own_columns", 9, 9, &o[0], &o[1], &o[2], &o[3], &o[4], &o[5],
                           &o[6], &o[7], &o[8]))
        return NULL;
    const int lookahead = PyObject_IsTrue(o[8]);
    if (lookahead < 0) {
        PyErr_Clear();
        Py_RETURN_FALSE;
    }
    Py_buffer obs;
    if (!PyObject_CheckBuffer(o[0]) ||
        PyObject_GetBuffer(o[0], &obs, PyBUF_FORMAT | PyBUF_ND | PyBUF_WRITABLE) < 0) {
        PyErr_Clear();
        Py_RETURN_FALSE;
    }
    int ok = obs.itemsize == 8 && obs.format != NULL && strcmp(obs.format, "d") == 0 &&
             obs.ndim == 2 && obs.shape[1] >= (lookahead ? 6 : 4);
    static const char kinds[7] = {'i', 'i', 'd', 'd', 'd', 'd', 'd'};
    Py_buffer v[7];
    Py_ssize_t len[7];
    int got = 0;
    for (; ok && got < 7; got++)
        if (!vector(o[1 + got], &v[got], kinds[got], 0, &len[got])) {
            ok = 0;
            break;
        }
    const Py_ssize_t n = ok ? obs.shape[0] : 0, f = ok ? obs.shape[1] : 0;
    const Py_ssize_t N = ok ? len[2] : 0, lanes = ok ? len[5] : 0;
    ok = ok && len[0] == n && len[1] == n && len[3] == N && len[4] == n && len[6] == lanes;
    if (ok) {
        const int64_t *rows = v[0].buf, *codes = v[1].buf;
        for (Py_ssize_t i = 0; ok && i < n; i++)
            ok = rows[i] >= 0 && rows[i] < N && codes[i] >= 0 && codes[i] < lanes;
    }
    if (ok) {
        const int64_t *rows = v[0].buf, *codes = v[1].buf;
        const double *speeds = v[2].buf, *pos = v[3].buf, *lead_v = v[4].buf;
        const double *arc_per_m = v[5].buf, *arc0 = v[6].buf;
        double *row = obs.buf;
        for (Py_ssize_t i = 0; i < n; i++, row += f) {
            const double speed = speeds[rows[i]];
            row[0] = speed;
            row[3] = speed - lead_v[i];
            if (lookahead) {
                const double arc = arc_per_m[codes[i]] * pos[rows[i]] + arc0[codes[i]];
                row[5] = row[5] - arc;
            }
        }
    }
    for (int i = 0; i < got; i++) PyBuffer_Release(&v[i]);
    PyBuffer_Release(&obs);
    if (ok) Py_RETURN_TRUE;
    Py_RETURN_FALSE;
}

/* command_speeds(v, accel, dt, a_min, a_max, vmax, out) -> bool: road.vtype.command_speeds
   into out (a writable float64 vector of n): min(max(0, v + min(max(accel, a_min), a_max)
   dt), vmax), accel a float64 vector of n, the rest float64 0-d or 1-d of n or 1, or
   Python floats; False (out untouched) for any other form. */
static PyObject *command_speeds(PyObject *self, PyObject *args) {
    PyObject *obj[7];
    if (!PyArg_UnpackTuple(args, "command_speeds", 7, 7, &obj[0], &obj[1], &obj[2], &obj[3],
                           &obj[4], &obj[5], &obj[6]))
        return NULL;
    operand ops[7];
    int got = 0;
    if (!take(obj[6], -1, &ops[6], 1) || ops[6].view.ndim != 1) {
        release(&ops[6], 1);
        Py_RETURN_FALSE;
    }
    const Py_ssize_t n = ops[6].view.shape[0];
    for (; got < 6; got++) {
        if (!take(obj[got], n, &ops[got], 0) || (got == 1 && ops[1].step == 0 && n != 1)) {
            got++;
            release(ops, got);
            release(&ops[6], 1);
            Py_RETURN_FALSE;
        }
    }
    const double dt = AT(ops[2], 0);
    char *out = ops[6].view.buf;
    const Py_ssize_t out_step = ops[6].view.strides[0];
    for (Py_ssize_t i = 0; i < n; i++) {
        const double a = np_minimum(np_maximum(AT(ops[1], i), AT(ops[3], i)), AT(ops[4], i));
        const double v = np_maximum(0.0, AT(ops[0], i) + a * dt);
        *(double *)(out + i * out_step) = np_minimum(v, AT(ops[5], i));
    }
    release(ops, 6);
    release(&ops[6], 1);
    Py_RETURN_TRUE;
}

/* safety_cap(cmd, v, limit, safe, floor_safe, a_max, dt, share, vmax, start_accel,
   start_factor, start_on, decel, lead_decel, lead, lead_speed, margin, tol, out)
   -> (lowered, raised) | None: deploy.safety.safety_cap into out (a writable float64
   vector of n) where behind_commands' test finds no driven leader commanded below what
   safe_speed assumed (the common step): capped at safe, floored, start-dawdled
   (start_accel None: off; start_on None: all; start_factor 1 - sigma dt / 2), and the
   counts numpy makes. floor_safe None: safe alone. lead an int64 vector of n (-1: none),
   start_on a bool vector of n. None (out scribbled) where a driven leader may lower a
   command (numpy's loop answers), a leader index is out of [-1, n), or any form does not
   fit. */
enum { SC_CMD, SC_V, SC_LIMIT, SC_SAFE, SC_FLOOR_SAFE, SC_AMAX, SC_DT, SC_SHARE, SC_VMAX,
       SC_START_ACCEL, SC_START_FACTOR, SC_START_ON, SC_DECEL, SC_LEAD_DECEL, SC_LEAD,
       SC_LEAD_SPEED, SC_MARGIN, SC_TOL, SC_OUT, SC_N };

static PyObject *safety_cap(PyObject *self, PyObject *args) {
    if (!PyTuple_CheckExact(args) || PyTuple_GET_SIZE(args) != SC_N) {
        PyErr_SetString(PyExc_TypeError, "safety_cap takes 19 arguments");
        return NULL;
    }
    PyObject *o[SC_N];
    for (int i = 0; i < SC_N; i++) o[i] = PyTuple_GET_ITEM(args, i);
    operand ops[SC_N];
    for (int i = 0; i < SC_N; i++) ops[i].held = 0;
    Py_buffer lead_v, on_v;
    int have_lead = 0, have_on = 0, ok = take(o[SC_OUT], -1, &ops[SC_OUT], 1) &&
                                         ops[SC_OUT].view.ndim == 1;
    const Py_ssize_t n = ok ? ops[SC_OUT].view.shape[0] : 0;
    const int floor_safe = o[SC_FLOOR_SAFE] != Py_None, start = o[SC_START_ACCEL] != Py_None;
    const int on = o[SC_START_ON] != Py_None;
    for (int i = 0; ok && i < SC_OUT; i++) {
        if (i == SC_LEAD || i == SC_START_ON) continue;
        if ((i == SC_FLOOR_SAFE && !floor_safe) || (i == SC_START_ACCEL && !start)) continue;
        ok = take(o[i], n, &ops[i], 0);
        /* the vectors numpy's result takes its length from: of n, not broadcast */
        if (ok && (i == SC_CMD || i == SC_V || i == SC_SAFE || i == SC_LEAD_SPEED))
            ok = ops[i].step != 0 || n == 1;
    }
    Py_ssize_t len = 0;
    if (ok) ok = have_lead = vector(o[SC_LEAD], &lead_v, 'i', 0, &len);
    ok = ok && len == n;
    if (ok && on) ok = have_on = vector(o[SC_START_ON], &on_v, '?', 0, &len);
    ok = ok && len == n;
    PyObject *result = NULL;
    if (ok) {
        const double dt = AT(ops[SC_DT], 0), margin = AT(ops[SC_MARGIN], 0);
        const double tol = AT(ops[SC_TOL], 0);
        const double factor = start ? AT(ops[SC_START_FACTOR], 0) : 1.0;
        const int64_t *lead = lead_v.buf;
        const char *on_b = have_on ? on_v.buf : NULL;
        double *out = ops[SC_OUT].view.buf; /* written at its strides below */
        const Py_ssize_t os = ops[SC_OUT].view.strides[0];
#define OUT(i) (*(double *)((char *)out + (i) * os))
        Py_ssize_t raised = 0, lowered = 0;
        int chained = 0;
        for (Py_ssize_t i = 0; i < n; i++) {
            const double v = AT(ops[SC_V], i), safe = AT(ops[SC_SAFE], i);
            const double under =
                floor_safe ? np_minimum(safe, AT(ops[SC_FLOOR_SAFE], i)) : safe;
            const double reach = v + AT(ops[SC_AMAX], i) * dt;
            const double share = AT(ops[SC_SHARE], i) * AT(ops[SC_LIMIT], i);
            double fl = np_minimum(under, np_minimum(reach, share));
            fl = np_minimum(fl, AT(ops[SC_VMAX], i));
            const double capped = np_minimum(AT(ops[SC_CMD], i), safe);
            raised += fl > capped + tol;
            OUT(i) = np_maximum(capped, fl);
        }
        /* start_dawdled on out and on cmd: each changed only where some vehicle is low */
        int out_low = 0, cmd_low = 0;
        if (start) {
            for (Py_ssize_t i = 0; i < n; i++) {
                if (on_b != NULL && !on_b[i]) continue;
                const double a = AT(ops[SC_START_ACCEL], i);
                out_low |= OUT(i) < a;
                cmd_low |= AT(ops[SC_CMD], i) < a;
            }
        }
        for (Py_ssize_t i = 0; i < n && !chained; i++) {
            const int64_t j = lead[i];
            if (j < -1 || j >= n) chained = 1; /* numpy raises or wraps: its to answer */
        }
        for (Py_ssize_t i = 0; i < n; i++) {
            const double c = AT(ops[SC_CMD], i);
            double cmd_d = c;
            if (out_low || cmd_low) {
                const int here = on_b == NULL || on_b[i];
                const double a = AT(ops[SC_START_ACCEL], i);
                const double least = AT(ops[SC_V], i) - AT(ops[SC_DECEL], i) * dt;
                if (out_low && here && OUT(i) < a)
                    OUT(i) = np_maximum(OUT(i) * factor, np_minimum(OUT(i), least));
                if (cmd_low && here && c < a)
                    cmd_d = np_maximum(c * factor, np_minimum(c, least));
            }
            lowered += OUT(i) < cmd_d - tol;
        }
        /* behind_commands' test: a driven leader commanded below max(v_l - max(b, b_l) dt,
           0) + margin may lower its follower's command: numpy's loop answers then. */
        for (Py_ssize_t i = 0; i < n && !chained; i++) {
            const int64_t j = lead[i];
            if (j < 0) continue;
            const double brake = np_maximum(AT(ops[SC_DECEL], i), AT(ops[SC_LEAD_DECEL], i)) * dt;
            const double least = np_maximum(AT(ops[SC_LEAD_SPEED], i) - brake, 0.0) + margin;
            chained = OUT(j) < least;
        }
#undef OUT
        if (chained) {
            result = Py_None;
            Py_INCREF(result);
        } else {
            result = Py_BuildValue("(nn)", lowered, raised);
        }
    } else {
        result = Py_None;
        Py_INCREF(result);
    }
    release(ops, SC_N);
    if (have_lead) PyBuffer_Release(&lead_v);
    if (have_on) PyBuffer_Release(&on_v);
    return result;
}

static PyMethodDef methods[] = {
    {"own_columns", own_columns, METH_VARARGS,
     "deploy.observe.observe_rows' own columns (speed, delta v, the look-ahead's distance), "
     "bit for bit; False where numpy must answer."},
    {"lane_due", lane_due, METH_VARARGS,
     "deploy.slots.LaneCache.due's indices into out, their count; -1 where numpy must answer."},
    {"leader_columns", leader_columns, METH_VARARGS,
     "deploy.observe.observe_rows' leader columns, bit for bit; False where numpy must answer."},
    {"krauss_prior", krauss_prior, METH_VARARGS,
     "deploy.policy_batch's Krauss prior into out, bit for bit; False where numpy must answer."},
    {"command_speeds", command_speeds, METH_VARARGS,
     "road.vtype.command_speeds into out, bit for bit; False where numpy must answer."},
    {"safety_cap", safety_cap, METH_VARARGS,
     "deploy.safety.safety_cap's commands into out and (lowered, raised); None where numpy "
     "must answer."},
    {"leader_safe_speed", safe_speed, METH_VARARGS,
     "safe_speed with no_gap: deploy.safety.leader_safe_speed into out, bit for bit; False "
     "where numpy must answer."},
    {"safe_speed", safe_speed, METH_VARARGS,
     "road.physics.safe_speed into out, bit for bit; False where numpy must answer."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "kernels", "road.physics' hot arithmetic, compiled.", -1, methods,
};

PyMODINIT_FUNC PyInit_kernels(void) { return PyModule_Create(&module); }
