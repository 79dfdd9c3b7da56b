/* sumo.libsumo_cxx: a deployment step's per-vehicle libsumo calls (the state read's ID list
   and four getters, getLeader, getSpeedWithoutTraCI and setSpeed) made on libsumo's C++ functions
   themselves, not through their SWIG wrappers.

   Why: per call the wrapper parses its argument tuple (PyArg_ParseTupleAndKeywords, ~245
   instructions), copies the ID into a fresh heap string (~150, then ~95 to free it) and
   wraps the call in its exception handler: some 500-700 instructions on top of a getter
   whose own work is ~600 (a Bremen policy run, 1,440 steps: ~450,000 such calls, ~5% of its
   instructions; callgrind, stop 49). Here the ID is a string on the stack (no heap for an
   ID of up to 15 bytes), the answer written straight into the numpy array or list.

   The same libsumo functions with the same arguments in the same order, so the same values
   and the same state of SUMO after: a getter's double is the double the wrapper makes a
   Python float of, a string answer decoded as the wrapper decodes it. Where anything does
   not fit (an ID not an exact str or not UTF-8, an output of another form, a C++ exception
   such as an unknown vehicle's), the function answers False or None with no Python error
   set and the caller asks through the wrappers again, which give the answer or raise as
   before (getters have no side effects; setSpeed given the same speeds again leaves the
   same state). The functions are found at import in the libsumo module already loaded
   (dlopen RTLD_NOLOAD, dlsym of their C++ names); where one is missing ``available()`` is
   False and nothing here is used. Optional: setup.py builds it where a C++ compiler is
   found. */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <dlfcn.h>

#include <cstdlib>
#include <cstring>
#include <string>
#include <unordered_map>
#include <utility>
#include <vector>

namespace {

typedef double (*getter_t)(const std::string &);
typedef std::string (*text_t)(const std::string &);
typedef std::pair<std::string, double> (*leader_t)(const std::string &, double);
typedef void (*setter_t)(const std::string &, double);
typedef std::vector<std::string> (*list_t)();

// libsumo::Vehicle's functions (their Itanium C++ names, std::string of the C++11 ABI).
#define STR "RKNSt7__cxx1112basic_stringIcSt11char_traitsIcESaIcEEE"
const char *const NAMES[8] = {
    "_ZN7libsumo7Vehicle15getLanePositionE" STR,
    "_ZN7libsumo7Vehicle8getSpeedE" STR,
    "_ZN7libsumo7Vehicle15getAccelerationE" STR,
    "_ZN7libsumo7Vehicle20getSpeedWithoutTraCIE" STR,
    "_ZN7libsumo7Vehicle9getLaneIDE" STR,
    "_ZN7libsumo7Vehicle9getLeaderE" STR "d",
    "_ZN7libsumo7Vehicle8setSpeedE" STR "d",
    "_ZN7libsumo7Vehicle9getIDListB5cxx11Ev",
};
#undef STR
// The getters ``floats`` takes, by letter: p lane position, s speed, a acceleration, o
// speed without TraCI (SUMO's own).
const char GETTER_CODES[] = "psao";
getter_t getters[4] = {nullptr, nullptr, nullptr, nullptr};
text_t get_lane = nullptr;
leader_t get_leader = nullptr;
setter_t set_speed = nullptr;
list_t get_ids = nullptr;
bool found = false;

// The ID as the wrapper passes it: an exact str, UTF-8 (false: not that form, no error).
bool id_of(PyObject *obj, std::string &out) {
    if (!PyUnicode_CheckExact(obj)) return false;
    Py_ssize_t size = 0;
    const char *s = PyUnicode_AsUTF8AndSize(obj, &size);
    if (s == nullptr) {
        PyErr_Clear();
        return false;
    }
    out.assign(s, static_cast<size_t>(size));
    return true;
}

// A string answer as SWIG's std::string typemap makes it (UTF-8, surrogateescape).
PyObject *text(const std::string &s) {
    return PyUnicode_DecodeUTF8(s.data(), static_cast<Py_ssize_t>(s.size()), "surrogateescape");
}

// ``text`` of the vehicle, lane and leader IDs answered, one str object per ID met: a step answers
// the same few lanes and vehicles again and again, and the str kept has its hash cached,
// so each dictionary look-up of it downstream (the section's lanes, the lane codes, the
// rows) skips hashing it. Equal strings either way: the same values. At most CACHED IDs
// kept (dropped all at once past that: a long run meets vehicles by the thousand).
constexpr size_t CACHED = 1 << 14;
std::unordered_map<std::string, PyObject *> kept;

PyObject *kept_text(const std::string &s) {
    auto it = kept.find(s);
    if (it != kept.end()) {
        Py_INCREF(it->second);
        return it->second;
    }
    PyObject *got = text(s);
    if (got == nullptr) return nullptr;
    if (kept.size() >= CACHED) {
        for (auto &k : kept) Py_DECREF(k.second);
        kept.clear();
    }
    Py_INCREF(got);
    kept.emplace(s, got);
    return got;
}

// A list or tuple's items (borrowed) and their number; false: neither.
bool items(PyObject *ids, PyObject *const **out, Py_ssize_t *n) {
    if (PyList_CheckExact(ids)) {
        *out = reinterpret_cast<PyObject *const *>(&PyList_GET_ITEM(ids, 0));
        *n = PyList_GET_SIZE(ids);
        return true;
    }
    if (PyTuple_CheckExact(ids)) {
        *out = reinterpret_cast<PyObject *const *>(&PyTuple_GET_ITEM(ids, 0));
        *n = PyTuple_GET_SIZE(ids);
        return true;
    }
    return false;
}

// A writable C-contiguous float64 buffer of ndim dimensions (0: not that form, none held).
bool float_buffer(PyObject *obj, Py_buffer *v, int ndim) {
    if (!PyObject_CheckBuffer(obj) ||
        PyObject_GetBuffer(obj, v, PyBUF_FORMAT | PyBUF_C_CONTIGUOUS | PyBUF_WRITABLE) < 0) {
        PyErr_Clear();
        return false;
    }
    bool ok = v->format != nullptr && std::strcmp(v->format, "d") == 0 && v->ndim == ndim &&
              v->itemsize == 8;
    if (!ok) PyBuffer_Release(v);
    return ok;
}

PyObject *available(PyObject *, PyObject *) { return PyBool_FromLong(found); }

/* floats(codes, ids, out): out (k, n) float64, row j the getter of codes[j] (one of
   "psao") of each vehicle, vehicle by vehicle (its k values, then the next one's, as
   sumo/calls.c's floats). True where written; False: not that form, or a C++ exception. */
PyObject *floats(PyObject *, PyObject *args) {
    const char *codes;
    Py_ssize_t k;
    PyObject *ids, *out;
    if (!found || !PyArg_ParseTuple(args, "s#OO", &codes, &k, &ids, &out)) {
        if (PyErr_Occurred()) return nullptr;
        Py_RETURN_FALSE;
    }
    getter_t use[4];
    if (k < 1 || k > 4) Py_RETURN_FALSE;
    for (Py_ssize_t j = 0; j < k; j++) {
        const char *at = std::strchr(GETTER_CODES, codes[j]);
        if (codes[j] == '\0' || at == nullptr) Py_RETURN_FALSE;
        use[j] = getters[at - GETTER_CODES];
    }
    PyObject *const *id;
    Py_ssize_t n;
    if (!items(ids, &id, &n)) Py_RETURN_FALSE;
    Py_buffer v;
    if (!float_buffer(out, &v, 2)) Py_RETURN_FALSE;
    bool ok = v.shape[0] == k && v.shape[1] == n;
    double *o = static_cast<double *>(v.buf);
    std::string s;
    try {
        for (Py_ssize_t i = 0; ok && i < n; i++) {
            if (!id_of(id[i], s)) {
                ok = false;
                break;
            }
            for (Py_ssize_t j = 0; j < k; j++) o[j * n + i] = use[j](s);
        }
    } catch (...) {
        ok = false;
    }
    PyBuffer_Release(&v);
    return PyBool_FromLong(ok);
}

/* lanes(ids): [getLaneID(id) for id in ids]; None: not that form, or a C++ exception. */
PyObject *lanes(PyObject *, PyObject *ids) {
    PyObject *const *id;
    Py_ssize_t n;
    if (!found || !items(ids, &id, &n)) Py_RETURN_NONE;
    PyObject *got = PyList_New(n);
    if (got == nullptr) return nullptr;
    std::string s;
    for (Py_ssize_t i = 0; i < n; i++) {
        PyObject *item = nullptr;
        if (!id_of(id[i], s)) break;
        try {
            item = kept_text(get_lane(s));
        } catch (...) {
            break;
        }
        if (item == nullptr) {  // not decodable: the wrapper says what it says
            PyErr_Clear();
            break;
        }
        PyList_SET_ITEM(got, i, item);
        if (i == n - 1) return got;
    }
    if (n == 0) return got;
    Py_DECREF(got);
    Py_RETURN_NONE;
}

/* ids(): getIDList() as the compiled wrapper answers it (a tuple of str, SUMO's order);
   None: a C++ exception (no simulation) or a string it cannot decode. */
PyObject *ids(PyObject *, PyObject *) {
    if (!found) Py_RETURN_NONE;
    std::vector<std::string> got;
    try {
        got = get_ids();
    } catch (...) {
        Py_RETURN_NONE;
    }
    PyObject *out = PyTuple_New(static_cast<Py_ssize_t>(got.size()));
    if (out == nullptr) return nullptr;
    for (size_t i = 0; i < got.size(); i++) {
        PyObject *item = nullptr;
        try {
            item = kept_text(got[i]);
        } catch (...) {
        }
        if (item == nullptr) {
            PyErr_Clear();
            Py_DECREF(out);
            Py_RETURN_NONE;
        }
        PyTuple_SET_ITEM(out, static_cast<Py_ssize_t>(i), item);
    }
    return out;
}

/* leaders(ids, dist): [getLeader(id, dist) for id in ids], each (leader ID, gap) as the
   compiled wrapper answers (("", -1.0): none); None: not that form, or an exception. */
PyObject *leaders(PyObject *, PyObject *args) {
    PyObject *ids;
    double dist;
    if (!found || !PyArg_ParseTuple(args, "Od", &ids, &dist)) {
        if (PyErr_Occurred()) return nullptr;
        Py_RETURN_NONE;
    }
    PyObject *const *id;
    Py_ssize_t n;
    if (!items(ids, &id, &n)) Py_RETURN_NONE;
    PyObject *got = PyList_New(n);
    if (got == nullptr) return nullptr;
    std::string s;
    for (Py_ssize_t i = 0; i < n; i++) {
        PyObject *name = nullptr;
        double gap = 0.0;
        if (!id_of(id[i], s)) break;
        try {
            std::pair<std::string, double> r = get_leader(s, dist);
            name = kept_text(r.first);  // the wrapper's tuple: its string typemap, a float
            gap = r.second;
        } catch (...) {
            break;
        }
        if (name == nullptr) {
            PyErr_Clear();
            break;
        }
        PyObject *g = PyFloat_FromDouble(gap);
        PyObject *pair = g == nullptr ? nullptr : PyTuple_Pack(2, name, g);
        Py_DECREF(name);
        Py_XDECREF(g);
        if (pair == nullptr) {
            Py_DECREF(got);
            return nullptr;
        }
        PyList_SET_ITEM(got, i, pair);
        if (i == n - 1) return got;
    }
    if (n == 0) return got;
    Py_DECREF(got);
    Py_RETURN_NONE;
}

/* send(ids, values): setSpeed(id, value) for each vehicle, values float64 as long. True
   where all were sent; False: not that form, or a C++ exception (the caller sends all
   again through the wrapper: the same speeds, the same state). */
PyObject *send(PyObject *, PyObject *args) {
    PyObject *ids, *values;
    if (!found || !PyArg_ParseTuple(args, "OO", &ids, &values)) {
        if (PyErr_Occurred()) return nullptr;
        Py_RETURN_FALSE;
    }
    PyObject *const *id;
    Py_ssize_t n;
    if (!items(ids, &id, &n)) Py_RETURN_FALSE;
    Py_buffer v;
    if (!PyObject_CheckBuffer(values) ||
        PyObject_GetBuffer(values, &v, PyBUF_FORMAT | PyBUF_C_CONTIGUOUS) < 0) {
        PyErr_Clear();
        Py_RETURN_FALSE;
    }
    bool ok = v.format != nullptr && std::strcmp(v.format, "d") == 0 && v.ndim == 1 &&
              v.itemsize == 8 && v.shape[0] == n;
    const double *x = static_cast<const double *>(v.buf);
    std::string s;
    try {
        for (Py_ssize_t i = 0; ok && i < n; i++) {
            if (!id_of(id[i], s)) {
                ok = false;
                break;
            }
            set_speed(s, x[i]);
        }
    } catch (...) {
        ok = false;
    }
    PyBuffer_Release(&v);
    return PyBool_FromLong(ok);
}

PyMethodDef METHODS[] = {
    {"available", available, METH_NOARGS, "Whether libsumo's functions were all found."},
    {"floats", floats, METH_VARARGS, "floats(codes, ids, out) -> bool"},
    {"lanes", lanes, METH_O, "lanes(ids) -> list | None"},
    {"ids", ids, METH_NOARGS, "ids() -> tuple | None"},
    {"leaders", leaders, METH_VARARGS, "leaders(ids, dist) -> list | None"},
    {"send", send, METH_VARARGS, "send(ids, values) -> bool"},
    {nullptr, nullptr, 0, nullptr},
};

PyModuleDef MODULE = {PyModuleDef_HEAD_INIT, "libsumo_cxx", nullptr, -1, METHODS,
                      nullptr, nullptr, nullptr, nullptr};

// Whether libsumo is of a release whose signatures these are (the getters' double,
// getLaneID's std::string, getLeader's std::pair<std::string, double>: 1.20 to 1.28, the
// releases pyproject admits up to the one tested): a C++ name says the arguments, not what
// a function returns, so a later release is asked through its wrappers until checked.
bool known_version() {
    PyObject *pkg = PyImport_ImportModule("libsumo");
    PyObject *v = pkg == nullptr ? nullptr : PyObject_GetAttrString(pkg, "__version__");
    const char *s = v == nullptr || !PyUnicode_Check(v) ? nullptr : PyUnicode_AsUTF8(v);
    bool ok = false;
    if (s != nullptr && std::strncmp(s, "1.", 2) == 0) {
        char *end = nullptr;
        long minor = std::strtol(s + 2, &end, 10);
        ok = end != s + 2 && minor >= 20 && minor <= 28;
    }
    Py_XDECREF(v);
    Py_XDECREF(pkg);
    PyErr_Clear();
    return ok;
}

// libsumo's functions in the libsumo module Python loaded (none loaded: found stays false).
void find() {
    if (!known_version()) return;
    PyObject *mod = PyImport_ImportModule("libsumo._libsumo");
    if (mod == nullptr) {
        PyErr_Clear();
        return;
    }
    PyObject *file = PyObject_GetAttrString(mod, "__file__");
    Py_DECREF(mod);
    const char *path = file == nullptr ? nullptr : PyUnicode_AsUTF8(file);
    void *lib = path == nullptr ? nullptr : dlopen(path, RTLD_LAZY | RTLD_NOLOAD);
    Py_XDECREF(file);
    PyErr_Clear();
    if (lib == nullptr) return;
    void *f[8];
    for (int i = 0; i < 8; i++) {
        f[i] = dlsym(lib, NAMES[i]);
        if (f[i] == nullptr) return;  // the handle stays: the library stays loaded anyway
    }
    for (int i = 0; i < 4; i++) getters[i] = reinterpret_cast<getter_t>(f[i]);
    get_lane = reinterpret_cast<text_t>(f[4]);
    get_leader = reinterpret_cast<leader_t>(f[5]);
    set_speed = reinterpret_cast<setter_t>(f[6]);
    get_ids = reinterpret_cast<list_t>(f[7]);
    found = true;
}

}  // namespace

PyMODINIT_FUNC PyInit_libsumo_cxx(void) {
    find();
    return PyModule_Create(&MODULE);
}
