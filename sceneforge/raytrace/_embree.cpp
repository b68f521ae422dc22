// sceneforge.raytrace._embree: every hit of a ray in one Embree traversal, collected in C++.
//
// The Python side (embree_backend.py) owns the interface; this module only traces. It
// mirrors what sceneforge/raytrace/__init__.py does in numpy after an engine has answered,
// operation for operation, so that both give bit-identical hits:
//
//   * one Embree geometry per house instance, robust scenes, float32 vertices and rays
//     shifted to the house centre (the float32 triangles and rays the Open3D engine feeds
//     Embree, which splits instances into more geometries);
//   * a filter callback that rejects every hit (so the traversal goes on) after recording
//     it with its float64 plane distance `(offset - n.o) / (n.d)`, each dot product summed
//     x, y, z, as `_plane_distance` computes it (build with -ffp-contract=off: no FMA);
//   * every crossing Embree reports is kept (the Open3D engine lays its geometries out so
//     that its list rule drops none; see open3d_backend.py): what is kept of a ray's hits
//     then depends only on the set of triangles it crosses, never on the order in which a
//     traversal meets them (which differs between Embree builds and CPUs);
//   * the traversal stops at `cutoff + margin` (the ray's closing hit, found by a
//     first-hit pass, plus slack), and hits beyond `cutoff` are dropped;
//   * per ray, hits are sorted by the same float key `_order_by_ray_and_distance` uses,
//     then by face, and same-instance repeats are dropped as `_same_instance_repeats` does;
//   * the CSR arrays of `Hits` are written directly;
//   * first hits (closing passes, D5): of the triangles crossed within float32 rounding of
//     the nearest distance, the one of smallest float64 plane distance, exact ties by face
//     index (lower instance, then lower triangle; see nearest_face), in ray packets that
//     name the faces ray-by-ray tracing names (see nearest_faces_packed).
//   * the first K hits of each ray (docs/spec.md §4.7, the ray-intersection layers): the
//     nearest hits kept in the filter as the traversal meets them, the traversal stopped
//     where no farther one can be among them, in ray packets, and written as a view's
//     layers (engine_nearest, engine_nearest_surfaces); with the frontal query's object
//     hits taken from the same traversal (engine_frontal_nearest).
//
// Rays are traced in fixed blocks, each block's output kept apart and joined in block
// order: the result does not depend on the thread count.
//
// Kernels that read no scene live here too, as the one compiled part of sceneforge: the
// layer rules of docs/spec.md §4 (sceneforge.layers.apply_rules), the depth -> triangles block rule
// and compaction (sceneforge.depth_mesh.grid_faces, compact, and both fused with the
// pixels' points in depth_surface) and the frustum's per-vertex and per-face tests and the
// renumbering of the kept faces (sceneforge.frustum._vertex_codes, _face_classes,
// _weld_pieces). Each repeats its numpy reference operation for operation; the tests hold
// them equal bit for bit.

#define PY_SSIZE_T_CLEAN
#include <Python.h>

// setup.py defines SF_EMBREE4 when it builds against Embree 4 (its headers and library)
#ifdef SF_EMBREE4
#include <embree4/rtcore.h>
#else
#include <embree3/rtcore.h>
#endif

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <deque>
#include <limits>
#include <mutex>
#include <string>
#include <thread>
#include <tuple>
#include <vector>

#if RTC_VERSION_MAJOR >= 4
#define SF_FILTER_SCENE_FLAG RTC_SCENE_FLAG_FILTER_FUNCTION_IN_ARGUMENTS
typedef RTCRayQueryContext SFContextBase;
#else
#define SF_FILTER_SCENE_FLAG RTC_SCENE_FLAG_CONTEXT_FILTER_FUNCTION
typedef RTCIntersectContext SFContextBase;
#endif

namespace {

// rays per block: small enough to balance two threads on a 320x240 view, large enough
// that a block's bookkeeping is negligible
constexpr int64_t kBlock = 512;

struct HitRecord {
    double t;
    double cos;
    int64_t face;
};

// What the filter callback needs. The Embree context must come first: Embree hands the
// callback a pointer to it.
struct Collector {
    SFContextBase base;
    const int64_t* face_base;  // first face (house index) of each geometry of the scene
    const double* plane;      // (m, 4): each face's unit normal x, y, z and offset, together
    const double* o;         // the ray, float64, unshifted
    const double* d;
    double cutoff;           // hits farther than this are dropped (inf: none)
    double limit32;          // engine distances farther than this are not kept
    bool raw;                // keep every crossing (no plane-distance test)
    std::vector<HitRecord>* out;
};

// The distance along ray (o, d) to the plane q (unit normal x, y, z and offset) and the
// cosine n . d: `(offset - n.o) / (n.d)`, each dot product summed x, y, z, as
// sceneforge.raytrace._plane_distance computes it.
inline double plane_distance(const double* q, const double* o, const double* d, double& cos) {
    const double numerator = q[3] - (q[0] * o[0] + q[1] * o[1] + q[2] * o[2]);
    cos = q[0] * d[0] + q[1] * d[1] + q[2] * d[2];
    return numerator / cos;
}

void collect_filter(const RTCFilterFunctionNArguments* args) {
    Collector* c = reinterpret_cast<Collector*>(args->context);
    for (unsigned int i = 0; i < args->N; ++i) {
        if (args->valid[i] != -1) continue;
        args->valid[i] = 0;  // reject: the traversal goes on to the next hit
        const float t32 = RTCRayN_tfar(args->ray, args->N, i);
        const unsigned int geom = RTCHitN_geomID(args->hit, args->N, i);
        const unsigned int prim = RTCHitN_primID(args->hit, args->N, i);
        // every crossing is kept, even a triangle met twice (a BVH with spatial splits may
        // report it from two leaves): the per-ray pass merges it with itself, and the hits
        // do not depend on which of two tied triangles a traversal meets first
        if (static_cast<double>(t32) > c->limit32) continue;
        const int64_t face = c->face_base[geom] + prim;
        // the plane distance is computed once the ray's traversal is done (plane_distances):
        // a house's plane table is tens of MB, and reading a row here waited for memory
        // (three quarters of this callback's time on a 1 M-triangle room); fetched now, the
        // row has arrived by then
        if (!c->raw) __builtin_prefetch(c->plane + 4 * face);
        c->out->push_back({0.0, 0.0, face});
    }
}

// The float64 plane distance and cosine of hits[begin:] (one ray's, from collect_filter),
// dropping those not finite or beyond the cut-off; the kept hits keep their order.
void plane_distances(const Collector& c, std::vector<HitRecord>& hits, size_t begin) {
    size_t kept = begin;
    for (size_t k = begin; k < hits.size(); ++k) {
        const int64_t face = hits[k].face;
        double cos;
        const double t = plane_distance(c.plane + 4 * face, c.o, c.d, cos);
        if (!std::isfinite(t) || !(t <= c.cutoff)) continue;
        hits[kept++] = {t, cos, face};
    }
    hits.resize(kept);
}

struct BlockHits {
    std::vector<HitRecord> hits;  // grouped by ray, in ray order
    std::vector<int64_t> counts;  // per ray of the block
    double t_min = std::numeric_limits<double>::infinity();
    double t_max = -std::numeric_limits<double>::infinity();
};

struct Scene {
    RTCScene scene = nullptr;
    std::vector<int64_t> face_base;  // per geometry
};

struct EngineObject {
    PyObject_HEAD
    RTCDevice device;
    int threads;
    int packet;  // rays per first-hit packet: 16, 8 or 4 (rtcIntersectN), 1 (rtcIntersect1)
    std::deque<Scene>* scenes;  // a deque: adding a scene keeps the others in place (queries run without the GIL)
    // float64 copies of the house the callbacks read (plane terms, triangles)
    // (m, 4) each face's normal x, y, z and plane offset side by side (a hit reads one
    // cache line, not four)
    std::vector<double>* planes;
    std::vector<int32_t>* instance;   // (m,) owning instance of each face
    std::vector<int64_t>* first_face; // (n_instances + 1,)
    std::vector<double>* vertices;    // (v, 3) float64, unshifted
    std::vector<int64_t>* faces;      // (m, 3)
    // (m, 3) float32 each face's heights onto its edges (v1v2, v0v2, v0v1: the distance
    // from the edge a barycentric of 1 at the opposite corner means), for telling packet
    // hits next to an edge (nearest_faces_packed)
    std::vector<float>* heights;
    double shift[3];
    // collect's per-block hit lists, kept from call to call: fresh memory costs a page fault
    // per 4 KiB touched, which on a busy machine was a quarter of a query's time; a call
    // that finds them in use (another thread's query) makes its own
    std::vector<BlockHits>* scratch;
    std::mutex* scratch_lock;
};

// ------------------------------------------------------------------ buffers

struct Buffer {
    Py_buffer view{};
    bool held = false;
    ~Buffer() {
        if (held) PyBuffer_Release(&view);
    }
};

// A C-contiguous buffer of `count` items of `itemsize` bytes (count < 0: any).
bool get_buffer(PyObject* obj, Buffer& b, Py_ssize_t itemsize, Py_ssize_t count, const char* name) {
    if (PyObject_GetBuffer(obj, &b.view, PyBUF_C_CONTIGUOUS) != 0) return false;
    b.held = true;
    if (b.view.len % itemsize != 0 || (count >= 0 && b.view.len != count * itemsize)) {
        PyErr_Format(PyExc_ValueError, "%s: expected %zd items of %zd bytes, got %zd bytes", name, count, itemsize,
                     b.view.len);
        return false;
    }
    return true;
}

PyObject* new_bytearray(const void* data, size_t bytes) {
    PyObject* out = PyByteArray_FromStringAndSize(nullptr, static_cast<Py_ssize_t>(bytes));
    if (out && bytes) std::memcpy(PyByteArray_AS_STRING(out), data, bytes);
    return out;
}

// Rays as the queries read them: float64 rows, each of origins and directions either one
// row shared by every ray or one row per ray.
struct RayRows {
    const double* o;
    const double* d;
    bool o_shared, d_shared;
    int64_t n;
    const double* origin(int64_t r) const { return o + (o_shared ? 0 : 3 * r); }
    const double* direction(int64_t r) const { return d + (d_shared ? 0 : 3 * r); }
};

bool get_rays(PyObject* origins, PyObject* directions, Py_ssize_t n, Buffer& bo, Buffer& bd, RayRows& rays) {
    if (!get_buffer(origins, bo, 3 * sizeof(double), -1, "origins")) return false;
    if (!get_buffer(directions, bd, 3 * sizeof(double), -1, "directions")) return false;
    const Py_ssize_t no = bo.view.len / (3 * sizeof(double)), nd = bd.view.len / (3 * sizeof(double));
    if ((no != 1 && no != n) || (nd != 1 && nd != n) || (n > 0 && (no == 0 || nd == 0))) {
        PyErr_Format(PyExc_ValueError, "rays: %zd origin rows and %zd direction rows for %zd rays", no, nd, n);
        return false;
    }
    rays = {static_cast<const double*>(bo.view.buf), static_cast<const double*>(bd.view.buf), no == 1 && n != 1,
            nd == 1 && n != 1, n};
    return true;
}

bool get_scene_ids(EngineObject* self, PyObject* ids, std::vector<const Scene*>& out) {
    PyObject* seq = PySequence_Fast(ids, "scene ids must be a sequence");
    if (!seq) return false;
    const Py_ssize_t k = PySequence_Fast_GET_SIZE(seq);
    for (Py_ssize_t i = 0; i < k; ++i) {
        const long id = PyLong_AsLong(PySequence_Fast_GET_ITEM(seq, i));
        if (id < 0 || id >= static_cast<long>(self->scenes->size())) {
            Py_DECREF(seq);
            if (!PyErr_Occurred()) PyErr_SetString(PyExc_IndexError, "no such scene");
            return false;
        }
        out.push_back(&(*self->scenes)[id]);
    }
    Py_DECREF(seq);
    return true;
}

// Run `work(block)` for every block of rays on `threads` threads (blocks handed out in
// order; which thread runs a block does not matter to the result).
template <class F>
void parallel_blocks(int64_t n_blocks, int threads, F&& work) {
    const int t = static_cast<int>(std::max<int64_t>(1, std::min<int64_t>(threads, n_blocks)));
    if (t == 1) {
        for (int64_t b = 0; b < n_blocks; ++b) work(b);
        return;
    }
    std::atomic<int64_t> next{0};
    std::vector<std::thread> pool;
    pool.reserve(t);
    for (int i = 0; i < t; ++i)
        pool.emplace_back([&]() {
            for (int64_t b; (b = next.fetch_add(1)) < n_blocks;) work(b);
        });
    for (auto& th : pool) th.join();
}

void set_ray(RTCRayHit& rh, const EngineObject* e, const double* o, const double* d, float tfar) {
    // the same float64 -> float32 conversions as the Open3D engine's query tensor
    rh.ray.org_x = static_cast<float>(o[0] - e->shift[0]);
    rh.ray.org_y = static_cast<float>(o[1] - e->shift[1]);
    rh.ray.org_z = static_cast<float>(o[2] - e->shift[2]);
    rh.ray.dir_x = static_cast<float>(d[0]);
    rh.ray.dir_y = static_cast<float>(d[1]);
    rh.ray.dir_z = static_cast<float>(d[2]);
    rh.ray.tnear = 0.0f;
    rh.ray.tfar = tfar;
    rh.ray.mask = 0xFFFFFFFFu;
    rh.ray.flags = 0;
    rh.ray.time = 0.0f;
    rh.ray.id = 0;
    rh.hit.geomID = RTC_INVALID_GEOMETRY_ID;
    rh.hit.instID[0] = RTC_INVALID_GEOMETRY_ID;
}

// One rtcIntersect1 of `scene` through the collector's filter.
void intersect_collecting(const Scene* s, Collector& c, RTCRayHit& rh) {
    c.face_base = s->face_base.data();
#if RTC_VERSION_MAJOR >= 4
    RTCIntersectArguments args;
    rtcInitIntersectArguments(&args);
    args.context = &c.base;
    args.filter = collect_filter;
    args.flags = static_cast<RTCRayQueryFlags>(args.flags | RTC_RAY_QUERY_FLAG_INVOKE_ARGUMENT_FILTER);
    rtcIntersect1(s->scene, &rh, &args);
#else
    rtcIntersect1(s->scene, &c.base, &rh);
#endif
}

void intersect_nearest(const Scene* s, RTCRayHit& rh) {
#if RTC_VERSION_MAJOR >= 4
    rtcIntersect1(s->scene, &rh);
#else
    RTCIntersectContext context;
    rtcInitIntersectContext(&context);
    rtcIntersect1(s->scene, &context, &rh);
#endif
}

void init_collector(Collector& c, const EngineObject* e) {
#if RTC_VERSION_MAJOR >= 4
    rtcInitRayQueryContext(&c.base);
#else
    rtcInitIntersectContext(&c.base);
    c.base.filter = collect_filter;
#endif
    c.plane = e->planes->data();
}

// ------------------------------------------------------------------ the engine type

void engine_dealloc(EngineObject* self) {
    if (self->scenes) {
        for (auto& s : *self->scenes) rtcReleaseScene(s.scene);
        delete self->scenes;
    }
    delete self->heights;
    delete self->planes;
    delete self->instance;
    delete self->first_face;
    delete self->vertices;
    delete self->faces;
    delete self->scratch;
    delete self->scratch_lock;
    if (self->device) rtcReleaseDevice(self->device);
    Py_TYPE(self)->tp_free(reinterpret_cast<PyObject*>(self));
}

template <class T>
bool copy_buffer(PyObject* obj, std::vector<T>*& out, Py_ssize_t count, const char* name) {
    Buffer b;
    if (!get_buffer(obj, b, sizeof(T), count, name)) return false;
    const T* p = static_cast<const T*>(b.view.buf);
    out = new std::vector<T>(p, p + b.view.len / sizeof(T));
    return true;
}

// The (m, 4) plane table from normal_xyz (3, m) and offset (m,).
bool get_planes(PyObject* normal_xyz, PyObject* offset, Py_ssize_t m, std::vector<double>*& out) {
    Buffer bn, bo;
    if (!get_buffer(normal_xyz, bn, sizeof(double), 3 * m, "normal_xyz") ||
        !get_buffer(offset, bo, sizeof(double), m, "offset"))
        return false;
    const double* n = static_cast<const double*>(bn.view.buf);
    const double* off = static_cast<const double*>(bo.view.buf);
    out = new std::vector<double>(4 * m);
    for (Py_ssize_t f = 0; f < m; ++f) {
        double* q = out->data() + 4 * f;
        q[0] = n[f], q[1] = n[m + f], q[2] = n[2 * m + f], q[3] = off[f];
    }
    return true;
}

// Engine(threads, vertices (v,3) f8, faces (m,3) i8, instance (m,) i4, first_face (n+1,) i8,
//        normal_xyz (3,m) f8, offset (m,) f8, shift (3,) f8[, packet])
//   packet : rays per first-hit packet, 16, 8, 4 or 1 (ray by ray); 0 (default): the widest
//            the CPU runs natively. A width it does not run natively is refused.
int engine_init(EngineObject* self, PyObject* args, PyObject*) {
    int threads, packet = 0;
    PyObject *vertices, *faces, *instance, *first_face, *normal_xyz, *offset, *shift;
    if (!PyArg_ParseTuple(args, "iOOOOOOO|i", &threads, &vertices, &faces, &instance, &first_face, &normal_xyz,
                          &offset, &shift, &packet))
        return -1;
    if (threads < 1) {
        PyErr_SetString(PyExc_ValueError, "threads must be >= 1");
        return -1;
    }
    if (packet != 0 && packet != 1 && packet != 4 && packet != 8 && packet != 16) {
        PyErr_Format(PyExc_ValueError, "packet must be 0, 1, 4, 8 or 16, got %d", packet);
        return -1;
    }
    self->threads = threads;
    self->scenes = new std::deque<Scene>();
    self->scratch = new std::vector<BlockHits>();
    self->scratch_lock = new std::mutex();
    if (!copy_buffer(vertices, self->vertices, -1, "vertices") || !copy_buffer(faces, self->faces, -1, "faces"))
        return -1;
    const Py_ssize_t m = static_cast<Py_ssize_t>(self->faces->size() / 3);
    if (!copy_buffer(instance, self->instance, m, "instance") ||
        !copy_buffer(first_face, self->first_face, -1, "first_face") ||
        !get_planes(normal_xyz, offset, m, self->planes))
        return -1;
    self->heights = new std::vector<float>(3 * m);
    {
        const double* V = self->vertices->data();
        const int64_t* F = self->faces->data();
        const int64_t n_vertices = static_cast<int64_t>(self->vertices->size() / 3);
        for (Py_ssize_t f = 0; f < m; ++f) {
            float* h = self->heights->data() + 3 * f;
            h[0] = h[1] = h[2] = 0.0f;  // degenerate or out of range: every hit is next to an edge
            const int64_t* c = F + 3 * f;
            if (c[0] < 0 || c[1] < 0 || c[2] < 0 || c[0] >= n_vertices || c[1] >= n_vertices || c[2] >= n_vertices)
                continue;
            const double *a = V + 3 * c[0], *b = V + 3 * c[1], *d = V + 3 * c[2];
            const double ab[3] = {b[0] - a[0], b[1] - a[1], b[2] - a[2]};
            const double ad[3] = {d[0] - a[0], d[1] - a[1], d[2] - a[2]};
            const double bd[3] = {d[0] - b[0], d[1] - b[1], d[2] - b[2]};
            const double n[3] = {ab[1] * ad[2] - ab[2] * ad[1], ab[2] * ad[0] - ab[0] * ad[2], ab[0] * ad[1] - ab[1] * ad[0]};
            const double area2 = std::sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
            const double len[3] = {std::sqrt(bd[0] * bd[0] + bd[1] * bd[1] + bd[2] * bd[2]),
                                   std::sqrt(ad[0] * ad[0] + ad[1] * ad[1] + ad[2] * ad[2]),
                                   std::sqrt(ab[0] * ab[0] + ab[1] * ab[1] + ab[2] * ab[2])};
            for (int k = 0; k < 3; ++k)
                if (len[k] > 0 && std::isfinite(area2)) h[k] = static_cast<float>(area2 / len[k]);
        }
    }
    Buffer bs;
    if (!get_buffer(shift, bs, sizeof(double), 3, "shift")) return -1;
    std::memcpy(self->shift, bs.view.buf, sizeof(self->shift));
    const std::string config = "threads=" + std::to_string(threads);
    self->device = rtcNewDevice(config.c_str());
    if (!self->device) {
        PyErr_Format(PyExc_RuntimeError, "Embree: cannot create a device (error %d)", rtcGetDeviceError(nullptr));
        return -1;
    }
    // the packet widths this CPU and this Embree build run natively (none where Embree was
    // built without ray packets)
    auto native = [&](int k) {
        const RTCDeviceProperty property = k == 16  ? RTC_DEVICE_PROPERTY_NATIVE_RAY16_SUPPORTED
                                           : k == 8 ? RTC_DEVICE_PROPERTY_NATIVE_RAY8_SUPPORTED
                                                    : RTC_DEVICE_PROPERTY_NATIVE_RAY4_SUPPORTED;
        return k == 1 || rtcGetDeviceProperty(self->device, property) != 0;
    };
    if (packet == 0) {
        packet = native(16) ? 16 : native(8) ? 8 : native(4) ? 4 : 1;
    } else if (!native(packet)) {
        PyErr_Format(PyExc_ValueError, "this CPU or Embree build has no native %d-ray packets", packet);
        return -1;
    }
    self->packet = packet;
    return 0;
}

PyObject* engine_packet(EngineObject* self, void*) { return PyLong_FromLong(self->packet); }

// add_scene(members (g,) i8, first_vertex (n+1,) i8) -> scene id: one geometry per member
// instance, in the given order, robust (the Open3D engine's triangles, in fewer geometries).
PyObject* engine_add_scene(EngineObject* self, PyObject* args) {
    PyObject *members_obj, *first_vertex_obj;
    if (!PyArg_ParseTuple(args, "OO", &members_obj, &first_vertex_obj)) return nullptr;
    Buffer bm, bv;
    if (!get_buffer(members_obj, bm, sizeof(int64_t), -1, "members") ||
        !get_buffer(first_vertex_obj, bv, sizeof(int64_t), static_cast<Py_ssize_t>(self->first_face->size()),
                    "first_vertex"))
        return nullptr;
    const int64_t* members = static_cast<const int64_t*>(bm.view.buf);
    const int64_t* fv = static_cast<const int64_t*>(bv.view.buf);
    const int64_t* ff = self->first_face->data();
    const int64_t n_members = bm.view.len / sizeof(int64_t);
    const int64_t n_instances = static_cast<int64_t>(self->first_face->size()) - 1;
    Scene s;
    s.scene = rtcNewScene(self->device);
    rtcSetSceneFlags(s.scene, static_cast<RTCSceneFlags>(RTC_SCENE_FLAG_ROBUST | SF_FILTER_SCENE_FLAG));
    const double* V = self->vertices->data();
    const int64_t* F = self->faces->data();
    for (int64_t k = 0; k < n_members; ++k) {
        const int64_t i = members[k];
        if (i < 0 || i >= n_instances) {
            rtcReleaseScene(s.scene);
            PyErr_SetString(PyExc_IndexError, "member instance out of range");
            return nullptr;
        }
        RTCGeometry g = rtcNewGeometry(self->device, RTC_GEOMETRY_TYPE_TRIANGLE);
        const int64_t nv = fv[i + 1] - fv[i], nf = ff[i + 1] - ff[i];
        float* vb = static_cast<float*>(
            rtcSetNewGeometryBuffer(g, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3, 3 * sizeof(float), nv));
        unsigned* ib = static_cast<unsigned*>(
            rtcSetNewGeometryBuffer(g, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3, 3 * sizeof(unsigned), nf));
        for (int64_t v = 0; v < nv; ++v)
            for (int a = 0; a < 3; ++a) vb[3 * v + a] = static_cast<float>(V[3 * (fv[i] + v) + a] - self->shift[a]);
        for (int64_t f = 0; f < nf; ++f)
            for (int a = 0; a < 3; ++a) ib[3 * f + a] = static_cast<unsigned>(F[3 * (ff[i] + f) + a] - fv[i]);
        rtcCommitGeometry(g);
        rtcAttachGeometry(s.scene, g);  // ids 0, 1, ... in attach order
        rtcReleaseGeometry(g);
        s.face_base.push_back(ff[i]);
    }
    Py_BEGIN_ALLOW_THREADS
    rtcCommitScene(s.scene);
    Py_END_ALLOW_THREADS
    const RTCError err = rtcGetDeviceError(self->device);
    if (err != RTC_ERROR_NONE) {
        rtcReleaseScene(s.scene);
        PyErr_Format(PyExc_RuntimeError, "Embree: building the scene failed (error %d)", static_cast<int>(err));
        return nullptr;
    }
    self->scenes->push_back(std::move(s));
    return PyLong_FromSsize_t(static_cast<Py_ssize_t>(self->scenes->size()) - 1);
}

// The nearest hit of one ray in one scene (rtcIntersect1): its float32 distance and face.
void nearest_in_scene(const EngineObject* e, const Scene* s, const double* o, const double* d, float& t,
                      int64_t& face) {
    RTCRayHit rh;
    set_ray(rh, e, o, d, std::numeric_limits<float>::infinity());
    intersect_nearest(s, rh);
    const bool hit = rh.hit.geomID != RTC_INVALID_GEOMETRY_ID;
    t = hit ? rh.ray.tfar : std::numeric_limits<float>::infinity();
    face = hit ? s->face_base[rh.hit.geomID] + rh.hit.primID : -1;
}

// The candidates for a ray's nearest hit: every triangle it crosses at a float32 distance
// at most kCandidateWindow (relative) beyond the nearest one, t_nearest * (1 + window)
// rounded to float32 (sceneforge.raytrace.CANDIDATE_WINDOW, the same float32 product).
// Two triangles tie there when they meet at an edge the ray passes through, or overlap;
// which of them a traversal names first depends on the Embree build and the CPU.
constexpr float kCandidateWindow = 5e-7f;  // about 4 float32 steps

struct CandidateFinder {
    SFContextBase base;  // first: Embree hands the callback a pointer to it
    const int64_t* face_base;
    float limit;  // candidates lie at or before this float32 distance
    const double* plane;
    const double *o, *d;
    double best_key;  // the best candidate so far: plane distance (inf where not finite), face
    int64_t best_face;
};

// Keeps the candidate of smallest float64 plane distance, exact ties (and non-finite
// distances: a ray in the triangle's plane) by lower face index, and rejects every hit.
void candidate_filter(const RTCFilterFunctionNArguments* args) {
    CandidateFinder* c = reinterpret_cast<CandidateFinder*>(args->context);
    for (unsigned int i = 0; i < args->N; ++i) {
        if (args->valid[i] != -1) continue;
        args->valid[i] = 0;
        if (!(RTCRayN_tfar(args->ray, args->N, i) <= c->limit)) continue;
        const int64_t face = c->face_base[RTCHitN_geomID(args->hit, args->N, i)] + RTCHitN_primID(args->hit, args->N, i);
        double cos;
        double key = plane_distance(c->plane + 4 * face, c->o, c->d, cos);
        if (!std::isfinite(key)) key = std::numeric_limits<double>::infinity();
        if (c->best_face < 0 || key < c->best_key || (key == c->best_key && face < c->best_face))
            c->best_key = key, c->best_face = face;
    }
}

// The nearest face (house index) of one ray over the scenes, -1 where none: of the
// triangles crossed within kCandidateWindow of the nearest float32 distance over all the
// scenes, the one of smallest float64 plane distance, exact ties by the lower face index
// (the lower instance, then the lower triangle of it). The choice depends only on the
// set of triangles the ray crosses, not on the order a traversal meets them in: the same
// face from every Embree build and CPU and from the Open3D engine (its intersect_first).
int64_t nearest_face(const EngineObject* e, const std::vector<const Scene*>& scenes, const double* o, const double* d) {
    constexpr float inf = std::numeric_limits<float>::infinity();
    float own[16];
    std::vector<float> many;
    float* t = own;
    if (scenes.size() > 16) many.resize(scenes.size()), t = many.data();
    float nearest = inf;
    int64_t nearest_face = -1;
    for (size_t k = 0; k < scenes.size(); ++k) {
        int64_t f;
        nearest_in_scene(e, scenes[k], o, d, t[k], f);
        if (f >= 0 && t[k] < nearest) nearest = t[k], nearest_face = f;
    }
    if (nearest_face < 0) return -1;
    CandidateFinder c;
    c.limit = nearest * (1.0f + kCandidateWindow);
    c.plane = e->planes->data();
    c.o = o, c.d = d;
    c.best_key = std::numeric_limits<double>::infinity(), c.best_face = -1;
    for (size_t k = 0; k < scenes.size(); ++k) {
        if (!(t[k] <= c.limit)) continue;  // nothing of this scene in the window
        c.face_base = scenes[k]->face_base.data();
        RTCRayHit rh;
        set_ray(rh, e, o, d, std::nextafter(c.limit, inf));
#if RTC_VERSION_MAJOR >= 4
        rtcInitRayQueryContext(&c.base);
        RTCIntersectArguments args;
        rtcInitIntersectArguments(&args);
        args.context = &c.base;
        args.filter = candidate_filter;
        args.flags = static_cast<RTCRayQueryFlags>(args.flags | RTC_RAY_QUERY_FLAG_INVOKE_ARGUMENT_FILTER);
        rtcIntersect1(scenes[k]->scene, &rh, &args);
#else
        rtcInitIntersectContext(&c.base);
        c.base.filter = candidate_filter;
        rtcIntersect1(scenes[k]->scene, &c.base, &rh);
#endif
    }
    // the window query meets the nearest triangle again (the same ray, the same
    // arithmetic); should it not, that triangle stays
    return c.best_face >= 0 ? c.best_face : nearest_face;
}

// Packets of K rays (rtcIntersectK) for the first-hit passes: a view's rays are coherent
// (one origin, neighbouring directions), so a packet walks the BVH once for K rays; on
// the toy house's 480x360 envelope rays, checks below included, that is 1.6x less CPU
// than ray by ray. Each lane is set_ray's float32 ray, so where a ray's nearest hit is
// clear-cut a packet names the face rtcIntersect1 names. It may not where it is not: two
// or more triangles within float32 rounding of the nearest distance (coincident faces,
// faces meeting at an edge; which one is named depends on the traversal order, and the
// two modes' distances of one triangle can differ in the last bits), a hit on or next to
// a triangle's edge, or no hit (an edge-on ray can hit in one mode and miss in the other). Those rays -- found by the hit's distance to its triangle's edges
// (near_edge) and a second packet query over a window around the nearest distance
// (tie_filter, a window twice kCandidateWindow) -- and the rays whose nearest hits in two
// scenes lie that close are decided again ray by ray (nearest_face), so every ray names
// the face ray-by-ray tracing names; the tests hold every width equal to it.
template <int K>
struct Packet;
#if RTC_VERSION_MAJOR >= 4
#define SF_PACKET(K)                                                                            \
    template <>                                                                                 \
    struct Packet<K> {                                                                          \
        typedef RTCRayHit##K RayHit;                                                            \
        static void intersect(const int* valid, RTCScene scene, RayHit* rh, SFContextBase* c,   \
                              RTCFilterFunctionN filter) {                                      \
            RTCIntersectArguments args;                                                         \
            rtcInitIntersectArguments(&args);                                                   \
            args.flags = RTC_RAY_QUERY_FLAG_COHERENT;                                           \
            if (filter) {                                                                       \
                rtcInitRayQueryContext(c);                                                      \
                args.context = c;                                                               \
                args.filter = filter;                                                           \
                args.flags = static_cast<RTCRayQueryFlags>(args.flags |                         \
                                                           RTC_RAY_QUERY_FLAG_INVOKE_ARGUMENT_FILTER); \
            }                                                                                   \
            rtcIntersect##K(valid, scene, rh, &args);                                           \
        }                                                                                       \
    };
#else
#define SF_PACKET(K)                                                                            \
    template <>                                                                                 \
    struct Packet<K> {                                                                          \
        typedef RTCRayHit##K RayHit;                                                            \
        static void intersect(const int* valid, RTCScene scene, RayHit* rh, SFContextBase* c,   \
                              RTCFilterFunctionN filter) {                                      \
            RTCIntersectContext plain;                                                          \
            if (!filter) c = &plain;                                                            \
            rtcInitIntersectContext(c);                                                         \
            c->flags = RTC_INTERSECT_CONTEXT_FLAG_COHERENT;                                     \
            c->filter = filter;                                                                 \
            rtcIntersect##K(valid, scene, c, rh);                                               \
        }                                                                                       \
    };
#endif
SF_PACKET(4)
SF_PACKET(8)
SF_PACKET(16)
#undef SF_PACKET

// Lane j of a packet: set_ray's ray over [tnear, tfar], its id the lane.
template <class RayHit>
void set_lane(RayHit& rh, int j, const EngineObject* e, const double* o, const double* d, float tnear, float tfar) {
    rh.ray.org_x[j] = static_cast<float>(o[0] - e->shift[0]);
    rh.ray.org_y[j] = static_cast<float>(o[1] - e->shift[1]);
    rh.ray.org_z[j] = static_cast<float>(o[2] - e->shift[2]);
    rh.ray.dir_x[j] = static_cast<float>(d[0]);
    rh.ray.dir_y[j] = static_cast<float>(d[1]);
    rh.ray.dir_z[j] = static_cast<float>(d[2]);
    rh.ray.tnear[j] = tnear;
    rh.ray.tfar[j] = tfar;
    rh.ray.mask[j] = 0xFFFFFFFFu;
    rh.ray.flags[j] = 0;
    rh.ray.time[j] = 0.0f;
    rh.ray.id[j] = static_cast<unsigned int>(j);
    rh.hit.geomID[j] = RTC_INVALID_GEOMETRY_ID;
    rh.hit.instID[0][j] = RTC_INVALID_GEOMETRY_ID;
}

// The second query's filter: notes a lane whose ray crosses a triangle other than the one
// the packet named within kTieWindow of the nearest distance (a tie, or as good as one: the
// two modes' float32 distances of one triangle can differ in the last bits), and rejects
// every hit (the query covers only that window, so it visits few nodes).
constexpr float kTieWindow = 2 * kCandidateWindow;  // relative; about 8 float32 steps
struct TieFinder {
    SFContextBase base;  // first: Embree hands the callback a pointer to it
    unsigned int geom[16], prim[16];  // the face each lane's packet named
    bool tie[16];
};

void tie_filter(const RTCFilterFunctionNArguments* args) {
    TieFinder* c = reinterpret_cast<TieFinder*>(args->context);
    for (unsigned int i = 0; i < args->N; ++i) {
        if (args->valid[i] != -1) continue;
        args->valid[i] = 0;
        const unsigned int j = RTCRayN_id(args->ray, args->N, i);
        const unsigned int geom = RTCHitN_geomID(args->hit, args->N, i);
        const unsigned int prim = RTCHitN_primID(args->hit, args->N, i);
        if (geom != c->geom[j] || prim != c->prim[j]) c->tie[j] = true;
    }
}

// Whether a hit at distance t with barycentrics (u, v) on `face` lies within kEdgeWindow * t
// of one of the face's edges (or the face is degenerate): where float32 rounding may let one
// traversal mode hit the face and the other miss it.
constexpr float kEdgeWindow = 1e-5f;  // relative to the distance: 10 um at 1 m
inline bool near_edge(const EngineObject* e, int64_t face, float t, float u, float v) {
    const float* h = e->heights->data() + 3 * face;
    const float margin = kEdgeWindow * t;
    return !((1.0f - u - v) * h[0] > margin && u * h[1] > margin && v * h[2] > margin);
}


// nearest_face of rays lo..hi-1 (their own origins), K at a time.
template <int K>
void nearest_faces_packed(const EngineObject* e, const std::vector<const Scene*>& scenes, const RayRows& rays,
                          int64_t lo, int64_t hi, int64_t* face) {
    constexpr float inf = std::numeric_limits<float>::infinity();
    for (int64_t r0 = lo; r0 < hi; r0 += K) {
        const int lanes = static_cast<int>(std::min<int64_t>(K, hi - r0));
        alignas(64) int valid[K];
        float nearest[K];
        bool redo[K];  // decided ray by ray (nearest_face)
        for (int j = 0; j < K; ++j) valid[j] = j < lanes ? -1 : 0, nearest[j] = inf, redo[j] = false;
        for (int j = 0; j < lanes; ++j) face[r0 + j] = -1;
        auto ray = [&](int j) { return r0 + (j < lanes ? j : 0); };  // idle lanes repeat the first (not traced)
        for (const Scene* s : scenes) {
            typename Packet<K>::RayHit rh;
            for (int j = 0; j < K; ++j) set_lane(rh, j, e, rays.origin(ray(j)), rays.direction(ray(j)), 0.0f, inf);
            Packet<K>::intersect(valid, s->scene, &rh, nullptr, nullptr);
            // the lanes whose distance another triangle of the scene shares
            TieFinder ties;
            alignas(64) int again[K];
            bool any = false;
            typename Packet<K>::RayHit probe;
            for (int j = 0; j < K; ++j) {
                const bool hit = valid[j] == -1 && !redo[j] && rh.hit.geomID[j] != RTC_INVALID_GEOMETRY_ID;
                again[j] = hit ? -1 : 0;
                any |= hit;
                ties.tie[j] = false;
                ties.geom[j] = rh.hit.geomID[j], ties.prim[j] = rh.hit.primID[j];
                const float t = hit ? rh.ray.tfar[j] : 0.0f;
                probe.ray.org_x[j] = rh.ray.org_x[j], probe.ray.org_y[j] = rh.ray.org_y[j];
                probe.ray.org_z[j] = rh.ray.org_z[j], probe.ray.dir_x[j] = rh.ray.dir_x[j];
                probe.ray.dir_y[j] = rh.ray.dir_y[j], probe.ray.dir_z[j] = rh.ray.dir_z[j];
                probe.ray.tnear[j] = t * (1.0f - kTieWindow), probe.ray.tfar[j] = t * (1.0f + kTieWindow);
                probe.ray.mask[j] = 0xFFFFFFFFu, probe.ray.flags[j] = 0, probe.ray.time[j] = 0.0f;
                probe.ray.id[j] = static_cast<unsigned int>(j);
                probe.hit.geomID[j] = RTC_INVALID_GEOMETRY_ID, probe.hit.instID[0][j] = RTC_INVALID_GEOMETRY_ID;
            }
            if (any) Packet<K>::intersect(again, s->scene, &probe, &ties.base, tie_filter);
            for (int j = 0; j < lanes; ++j) {
                if (redo[j]) continue;
                if (rh.hit.geomID[j] == RTC_INVALID_GEOMETRY_ID) {
                    // an edge-on ray can hit ray by ray where the packet missed
                    float t;
                    int64_t f;
                    nearest_in_scene(e, s, rays.origin(r0 + j), rays.direction(r0 + j), t, f);
                    redo[j] = f >= 0;
                    continue;
                }
                const float t = rh.ray.tfar[j];
                const int64_t f = s->face_base[rh.hit.geomID[j]] + rh.hit.primID[j];
                // a tie within the scene, a hit next to an edge, or within the window of
                // another scene's nearest hit: the candidates are found ray by ray
                redo[j] = ties.tie[j] || near_edge(e, f, t, rh.hit.u[j], rh.hit.v[j]) ||
                          (nearest[j] < inf && std::min(t, nearest[j]) * (1.0f + kTieWindow) >= std::max(t, nearest[j]));
                if (!redo[j] && t < nearest[j]) nearest[j] = t, face[r0 + j] = f;
            }
        }
        for (int j = 0; j < lanes; ++j)
            if (redo[j]) face[r0 + j] = nearest_face(e, scenes, rays.origin(r0 + j), rays.direction(r0 + j));
    }
}

// nearest_face of rays lo..hi-1, in packets of the engine's width.
void nearest_faces(const EngineObject* e, const std::vector<const Scene*>& scenes, const RayRows& rays, int64_t lo,
                   int64_t hi, int64_t* face) {
    switch (e->packet) {
        case 16: return nearest_faces_packed<16>(e, scenes, rays, lo, hi, face);
        case 8: return nearest_faces_packed<8>(e, scenes, rays, lo, hi, face);
        case 4: return nearest_faces_packed<4>(e, scenes, rays, lo, hi, face);
        default:
            for (int64_t r = lo; r < hi; ++r) face[r] = nearest_face(e, scenes, rays.origin(r), rays.direction(r));
    }
}

// first(scene_ids, n, origins, directions) -> bytearray (n,) i8: the nearest face of each
// ray over the scenes (-1: none) (nearest_face: ties canonical).
PyObject* engine_first(EngineObject* self, PyObject* args) {
    PyObject *ids, *origins, *directions;
    Py_ssize_t n;
    if (!PyArg_ParseTuple(args, "OnOO", &ids, &n, &origins, &directions)) return nullptr;
    std::vector<const Scene*> scenes;
    Buffer bo, bd;
    RayRows rays;
    if (!get_scene_ids(self, ids, scenes) || !get_rays(origins, directions, n, bo, bd, rays)) return nullptr;
    PyObject* out = PyByteArray_FromStringAndSize(nullptr, n * static_cast<Py_ssize_t>(sizeof(int64_t)));
    if (!out) return nullptr;
    int64_t* face = reinterpret_cast<int64_t*>(PyByteArray_AS_STRING(out));
    Py_BEGIN_ALLOW_THREADS
    parallel_blocks((n + kBlock - 1) / kBlock, self->threads, [&](int64_t b) {
        nearest_faces(self, scenes, rays, b * kBlock, std::min<int64_t>(n, (b + 1) * kBlock), face);
    });
    Py_END_ALLOW_THREADS
    return out;
}

// The closing hits of rays lo..hi-1, as HouseTracer._closing and _first_hit make them
// from an engine's nearest faces: each ray's nearest face among the closing scenes; where
// its plane distance is below `near`, the nearest face seen again from `near` along the
// ray (origin + near * d, as numpy computes it); then the plane distance t and cosine of
// that face from the ray's own origin. t is NaN and cos 0 where nothing closes the ray.
// face, t and cos are indexed by ray (cos from lo: cos[r - lo]).
void closing_hits(const EngineObject* e, const std::vector<const Scene*>& scenes, const RayRows& rays, int64_t lo,
                  int64_t hi, double near, int64_t* face, double* t, double* cos) {
    nearest_faces(e, scenes, rays, lo, hi, face);
    const double* planes = e->planes->data();
    for (int64_t r = lo; r < hi; ++r) {
        const double* o = rays.origin(r);
        const double* d = rays.direction(r);
        double& c = cos[r - lo];
        auto plane = [&](int64_t f) { t[r] = plane_distance(planes + 4 * f, o, d, c); };
        if (face[r] >= 0) plane(face[r]);
        if (near > 0 && face[r] >= 0 && t[r] < near) {
            const double moved[3] = {o[0] + near * d[0], o[1] + near * d[1], o[2] + near * d[2]};
            face[r] = nearest_face(e, scenes, moved, d);
            if (face[r] >= 0) plane(face[r]);
        }
        if (face[r] < 0) t[r] = std::numeric_limits<double>::quiet_NaN(), c = 0.0;
    }
}

// closing(scene_ids, n, origins, directions, near) -> (face i8, t f8, instance i4,
// triangle i8, front_facing bool) bytearrays: each ray's closing hit (closing_hits) over the scenes, what
// HouseTracer._first_hit (near 0) and _closing make of the engine's nearest faces.
PyObject* engine_closing(EngineObject* self, PyObject* args) {
    PyObject *ids, *origins, *directions;
    Py_ssize_t n;
    double near;
    if (!PyArg_ParseTuple(args, "OnOOd", &ids, &n, &origins, &directions, &near)) return nullptr;
    std::vector<const Scene*> scenes;
    Buffer bo, bd;
    RayRows rays;
    if (!get_scene_ids(self, ids, scenes) || !get_rays(origins, directions, n, bo, bd, rays)) return nullptr;
    // the results, written in place (no copies: fresh memory is costly, see scratch)
    PyObject* out[5] = {PyByteArray_FromStringAndSize(nullptr, n * sizeof(int64_t)),
                        PyByteArray_FromStringAndSize(nullptr, n * sizeof(double)),
                        PyByteArray_FromStringAndSize(nullptr, n * sizeof(int32_t)),
                        PyByteArray_FromStringAndSize(nullptr, n * sizeof(int64_t)),
                        PyByteArray_FromStringAndSize(nullptr, n)};
    if (!out[0] || !out[1] || !out[2] || !out[3] || !out[4]) {
        for (PyObject* o : out) Py_XDECREF(o);
        return nullptr;
    }
    int64_t* face = reinterpret_cast<int64_t*>(PyByteArray_AS_STRING(out[0]));
    double* t = reinterpret_cast<double*>(PyByteArray_AS_STRING(out[1]));
    int32_t* instance = reinterpret_cast<int32_t*>(PyByteArray_AS_STRING(out[2]));
    int64_t* triangle = reinterpret_cast<int64_t*>(PyByteArray_AS_STRING(out[3]));
    bool* front = reinterpret_cast<bool*>(PyByteArray_AS_STRING(out[4]));
    const int32_t* face_instance = self->instance->data();
    const int64_t* first_face = self->first_face->data();
    Py_BEGIN_ALLOW_THREADS
    parallel_blocks((n + kBlock - 1) / kBlock, self->threads, [&](int64_t b) {
        const int64_t lo = b * kBlock, hi = std::min<int64_t>(n, lo + kBlock);
        double cos[kBlock];
        closing_hits(self, scenes, rays, lo, hi, near, face, t, cos);
        for (int64_t r = lo; r < hi; ++r) {
            const int64_t f = face[r];
            instance[r] = f >= 0 ? face_instance[f] : -1;
            triangle[r] = f >= 0 ? f - first_face[instance[r]] : -1;
            front[r] = cos[r - lo] < 0;
        }
    });
    Py_END_ALLOW_THREADS
    return Py_BuildValue("(NNNNN)", out[0], out[1], out[2], out[3], out[4]);
}

// collect(scene_ids, n, origins, directions, cutoff, margin, same_instance, raw
//         [, closing_ids, near, slack])
//   cutoff : None or (n,) f8; hits farther along ray r than cutoff[r] are dropped, and the
//            traversal stops at cutoff[r] + margin (engine distance)
//   raw    : True: every crossing, unordered -> (ray i8, face i8) bytearrays
//            False: the CSR arrays of Hits -> (offsets i8, t f8, instance i4, triangle i8,
//            front_facing bool) bytearrays
//   closing_ids : with cutoff None, the scenes that close a ray: each ray's closing hit is
//            found first (closing_hits, from `near` on) and its cutoff is the closing
//            distance + slack (inf where none); five more bytearrays follow the Hits ones,
//            the closing hits: face i8, t f8, instance i4, triangle i8, front_facing bool
PyObject* hits_result(const EngineObject* self, std::vector<BlockHits>& blocks, int64_t n_blocks, int64_t n,
                      double tol);

PyObject* engine_collect(EngineObject* self, PyObject* args) {
    PyObject *ids, *origins, *directions, *cutoff_obj, *closing_obj = Py_None;
    Py_ssize_t n;
    double margin, tol, near = 0.0, slack = 0.0;
    int raw;
    if (!PyArg_ParseTuple(args, "OnOOOddp|Odd", &ids, &n, &origins, &directions, &cutoff_obj, &margin, &tol, &raw,
                          &closing_obj, &near, &slack))
        return nullptr;
    std::vector<const Scene*> scenes, closing_scenes;
    Buffer bo, bd, bc;
    RayRows rays;
    if (!get_scene_ids(self, ids, scenes) || !get_rays(origins, directions, n, bo, bd, rays)) return nullptr;
    const double* cutoff = nullptr;
    if (cutoff_obj != Py_None) {
        if (!get_buffer(cutoff_obj, bc, sizeof(double), n, "cutoff")) return nullptr;
        cutoff = static_cast<const double*>(bc.view.buf);
    }
    const bool closing = closing_obj != Py_None;
    if (closing && (cutoff || raw)) {
        PyErr_SetString(PyExc_ValueError, "closing scenes need cutoff None and raw False");
        return nullptr;
    }
    if (closing && !get_scene_ids(self, closing_obj, closing_scenes)) return nullptr;
    const double inf = std::numeric_limits<double>::infinity();
    // the closing hits go straight into their results: face i8, t f8, instance i4, triangle
    // i8, front_facing bool
    PyObject* closing_out[5] = {nullptr, nullptr, nullptr, nullptr, nullptr};
    if (closing) {
        const size_t sizes[5] = {sizeof(int64_t), sizeof(double), sizeof(int32_t), sizeof(int64_t), 1};
        for (int k = 0; k < 5; ++k)
            if (!(closing_out[k] = PyByteArray_FromStringAndSize(nullptr, n * sizes[k]))) {
                for (PyObject* o : closing_out) Py_XDECREF(o);
                return nullptr;
            }
    }
    auto closing_array = [&](int k) { return closing ? PyByteArray_AS_STRING(closing_out[k]) : nullptr; };
    int64_t* closing_face = reinterpret_cast<int64_t*>(closing_array(0));
    double* closing_t = reinterpret_cast<double*>(closing_array(1));
    int32_t* closing_inst = reinterpret_cast<int32_t*>(closing_array(2));
    int64_t* closing_tri = reinterpret_cast<int64_t*>(closing_array(3));
    bool* closing_front = reinterpret_cast<bool*>(closing_array(4));
    const int32_t* face_instance = self->instance->data();
    const int64_t* first_face = self->first_face->data();
    const int64_t n_blocks = (n + kBlock - 1) / kBlock;
    std::unique_lock<std::mutex> held(*self->scratch_lock, std::try_to_lock);
    std::vector<BlockHits> own;
    std::vector<BlockHits>& blocks = held.owns_lock() ? *self->scratch : own;
    if (static_cast<int64_t>(blocks.size()) < n_blocks) blocks.resize(n_blocks);
    for (int64_t b = 0; b < n_blocks; ++b) {
        blocks[b].hits.clear();
        blocks[b].t_min = inf, blocks[b].t_max = -inf;
    }

    Py_BEGIN_ALLOW_THREADS
    // pass 1: trace, keeping each ray's hits (within the cut-off) with their distances
    parallel_blocks(n_blocks, self->threads, [&](int64_t b) {
        BlockHits& out = blocks[b];
        const int64_t lo = b * kBlock, hi = std::min<int64_t>(n, lo + kBlock);
        out.counts.assign(hi - lo, 0);
        Collector c;
        init_collector(c, self);
        c.raw = raw != 0;
        c.out = &out.hits;
        if (closing) {  // the block's closing hits first, in packets
            double cos[kBlock];
            closing_hits(self, closing_scenes, rays, lo, hi, near, closing_face, closing_t, cos);
            for (int64_t r = lo; r < hi; ++r) {
                const int64_t f = closing_face[r];
                closing_inst[r] = f >= 0 ? face_instance[f] : -1;
                closing_tri[r] = f >= 0 ? f - first_face[closing_inst[r]] : -1;
                closing_front[r] = cos[r - lo] < 0;
            }
        }
        for (int64_t r = lo; r < hi; ++r) {
            const double* o = rays.origin(r);
            const double* d = rays.direction(r);
            c.o = o, c.d = d;
            if (closing) {
                c.cutoff = std::isnan(closing_t[r]) ? inf : closing_t[r] + slack;
            } else {
                c.cutoff = cutoff ? cutoff[r] : inf;
            }
            // what the Open3D engine keeps of its float32 distances: t <= cutoff + margin
            c.limit32 = c.cutoff + margin;
            float tfar = static_cast<float>(c.limit32);
            if (static_cast<double>(tfar) < c.limit32) tfar = std::nextafter(tfar, std::numeric_limits<float>::infinity());
            const size_t before = out.hits.size();
            for (const Scene* s : scenes) {
                RTCRayHit rh;
                set_ray(rh, self, o, d, tfar);
                intersect_collecting(s, c, rh);
            }
            if (!raw) plane_distances(c, out.hits, before);
            out.counts[r - lo] = static_cast<int64_t>(out.hits.size() - before);
            if (!raw)
                for (size_t k = before; k < out.hits.size(); ++k) {
                    out.t_min = std::min(out.t_min, out.hits[k].t);
                    out.t_max = std::max(out.t_max, out.hits[k].t);
                }
        }
    });
    Py_END_ALLOW_THREADS

    int64_t total = 0;
    for (int64_t b = 0; b < n_blocks; ++b) total += static_cast<int64_t>(blocks[b].hits.size());

    if (raw) {
        std::vector<int64_t> ray(total), face(total);
        int64_t k = 0;
        for (int64_t b = 0; b < n_blocks; ++b) {
            const auto& blk = blocks[b];
            size_t h = 0;
            for (size_t j = 0; j < blk.counts.size(); ++j)
                for (int64_t c = 0; c < blk.counts[j]; ++c, ++h, ++k) {
                    ray[k] = b * kBlock + static_cast<int64_t>(j);
                    face[k] = blk.hits[h].face;
                }
        }
        PyObject* a = new_bytearray(ray.data(), total * sizeof(int64_t));
        PyObject* f = new_bytearray(face.data(), total * sizeof(int64_t));
        if (!a || !f) {
            Py_XDECREF(a);
            Py_XDECREF(f);
            return nullptr;
        }
        return Py_BuildValue("(NN)", a, f);
    }

    // pass 2 and the output: each ray's hits ordered as `_order_by_ray_and_distance` does and
    // same-instance repeats dropped as `_same_instance_repeats` does (hits_result, shared with
    // the nearest-hits queries)
    PyObject* hits = hits_result(self, blocks, n_blocks, n, tol);
    if (!hits || !closing) {
        if (!hits)
            for (PyObject* o : closing_out) Py_XDECREF(o);
        return hits;
    }
    PyObject* both = Py_BuildValue("(OOOOONNNNN)", PyTuple_GET_ITEM(hits, 0), PyTuple_GET_ITEM(hits, 1),
                                   PyTuple_GET_ITEM(hits, 2), PyTuple_GET_ITEM(hits, 3), PyTuple_GET_ITEM(hits, 4),
                                   closing_out[0], closing_out[1], closing_out[2], closing_out[3], closing_out[4]);
    Py_DECREF(hits);
    return both;
}

// ------------------------------------------------------------------ the K nearest hits

// The first K hits of each ray over the whole house, as the merged, sorted hits of the ray
// have them (docs/spec.md §4.7: the ray-intersection layers), in one traversal per ray
// and scene that stops once no farther hit can be among them:
//
//   * the filter keeps the ray's `capacity` nearest hits so far in a list sorted by
//     (float64 plane distance, face) -- a ray's hit order, exact ties by the lower
//     instance, then triangle -- and rejects every hit it keeps, so that the traversal
//     goes on; hits without a finite plane distance are dropped, as collect drops them;
//   * once the list is full, a hit whose engine (float32) distance lies beyond the last
//     kept hit's plane distance + margin cannot be among the nearest (the margin of
//     collect's cut-off: engine and plane distances of one hit differ by far less), and
//     neither can anything farther: the filter accepts it, so Embree's tfar shrinks to it
//     and the traversal skips what lies beyond. A hit that can still be among them is
//     never accepted, and tfar never drops below a distance one could have;
//   * the same-instance merge then runs over the list, in order, as _same_instance_repeats
//     does: a hit is dropped when an earlier hit of the list of its instance lies within
//     `same_instance` before it. Whether a hit is dropped depends only on the hits before
//     it, so the list's kept hits are the first kept hits of all the ray's hits. Where
//     merged hits leave fewer than K of a full list, the ray is traced again with a list
//     twice as long, until K are kept or the list holds every hit of the ray.
//
// The capacity starts at K + spare: a few same-instance repeats (a ray through an edge
// two triangles share, coincident faces) fit without tracing the ray again.
//
// Rays are traced in packets of the engine's width (a view's rays are coherent: a packet
// walks the BVH once for all its rays), each lane a ray with its own list. A packet's
// float32 arithmetic may differ from ray-by-ray tracing's in the last bits, which matters
// only next to a triangle's edge (where one mode may hit and the other miss, see
// nearest_faces_packed): a lane that kept a hit next to an edge (near_edge), or kept none,
// is traced again ray by ray, so every ray gets the hits ray-by-ray tracing (collect) gets.
struct NearestLane {
    const double *o, *d;
    HitRecord* list;  // sorted by (t, face)
    int count;
    float beyond;  // with the list full: hits at an engine distance above this cannot enter it (inf before)
    bool edge;     // packets: a hit next to its triangle's edge entered the list
};

struct NearestCollector {
    SFContextBase base;  // first: Embree hands the callback a pointer to it
    const EngineObject* engine;
    const int64_t* face_base;
    const double* plane;
    double margin;
    int capacity;
    bool packet;  // watch for hits next to an edge
    NearestLane lane[16];  // by ray id
};

inline bool hit_before(const HitRecord& a, const HitRecord& b) {
    return a.t < b.t || (a.t == b.t && a.face < b.face);
}

// x rounded up to float32.
inline float float_at_or_above(double x) {
    float f = static_cast<float>(x);
    if (static_cast<double>(f) < x) f = std::nextafter(f, std::numeric_limits<float>::infinity());
    return f;
}

void nearest_filter(const RTCFilterFunctionNArguments* args) {
    NearestCollector* c = reinterpret_cast<NearestCollector*>(args->context);
    for (unsigned int i = 0; i < args->N; ++i) {
        if (args->valid[i] != -1) continue;
        NearestLane& lane = c->lane[RTCRayN_id(args->ray, args->N, i)];
        const float t32 = RTCRayN_tfar(args->ray, args->N, i);
        const int64_t face = c->face_base[RTCHitN_geomID(args->hit, args->N, i)] + RTCHitN_primID(args->hit, args->N, i);
        double cos;
        const double t = plane_distance(c->plane + 4 * face, lane.o, lane.d, cos);
        const HitRecord hit{t, cos, face};
        if (std::isfinite(t) && (lane.count < c->capacity || hit_before(hit, lane.list[c->capacity - 1]))) {
            int j = lane.count < c->capacity ? lane.count++ : c->capacity - 1;
            for (; j > 0 && hit_before(hit, lane.list[j - 1]); --j) lane.list[j] = lane.list[j - 1];
            lane.list[j] = hit;
            if (lane.count == c->capacity) lane.beyond = float_at_or_above(lane.list[c->capacity - 1].t + c->margin);
            if (c->packet && near_edge(c->engine, face, t32, RTCHitN_u(args->hit, args->N, i),
                                       RTCHitN_v(args->hit, args->N, i)))
                lane.edge = true;
        } else if (t32 > lane.beyond) {
            continue;  // accepted: nothing at or beyond it is needed
        }
        args->valid[i] = 0;
    }
}

void init_nearest(NearestCollector& c, const EngineObject* e, int capacity, double margin, bool packet) {
    c.engine = e;
    c.plane = e->planes->data();
    c.margin = margin;
    c.capacity = capacity;
    c.packet = packet;
}

void start_lane(NearestLane& lane, const double* o, const double* d, HitRecord* list) {
    lane.o = o, lane.d = d, lane.list = list;
    lane.count = 0;
    lane.beyond = std::numeric_limits<float>::infinity();
    lane.edge = false;
}

// The tfar a lane's ray starts a scene with: past where its list cuts off.
inline float lane_tfar(const NearestLane& lane) {
    constexpr float inf = std::numeric_limits<float>::infinity();
    return lane.beyond < inf ? std::nextafter(lane.beyond, inf) : inf;
}

// The first k kept hits of a lane's list (same-instance repeats dropped) into out; their count.
int merged_hits(const EngineObject* e, const NearestLane& lane, int k, double same_instance, HitRecord* out) {
    const int32_t* face_instance = e->instance->data();
    int kept = 0;
    for (int j = 0; j < lane.count && kept < k; ++j) {
        bool repeat = false;
        const int32_t inst = face_instance[lane.list[j].face];
        for (int s = j - 1; s >= 0 && lane.list[j].t - lane.list[s].t <= same_instance; --s)
            if (face_instance[lane.list[s].face] == inst) {
                repeat = true;
                break;
            }
        if (!repeat) out[kept++] = lane.list[j];
    }
    return kept;
}

// The raw hits a ray's first k merged hits were taken from: the `count` nearest of its hits
// (unmerged, sorted), every hit of the ray where `full` is false.
struct RawHits {
    const HitRecord* list;
    int count;
    bool full;
};

// One ray's first k hits (merged, sorted) into out[0..kept), traced ray by ray over the
// scenes; returns kept (fewer than k only where the ray has fewer hits). `list` is the
// caller's scratch, which holds the raw hits after (`raw`); `retraced` counts the times the
// ray was traced again with a longer list.
int nearest_of_ray(const EngineObject* e, const std::vector<const Scene*>& scenes, const double* o, const double* d,
                   int k, int spare, double margin, double same_instance, std::vector<HitRecord>& list,
                   HitRecord* out, int64_t& retraced, RawHits& raw) {
    for (int capacity = k + spare;; capacity *= 2, ++retraced) {
        if (static_cast<int>(list.size()) < capacity) list.resize(capacity);
        NearestCollector c;
        init_nearest(c, e, capacity, margin, false);
        NearestLane& lane = c.lane[0];
        start_lane(lane, o, d, list.data());
        for (const Scene* s : scenes) {
            c.face_base = s->face_base.data();
            RTCRayHit rh;
            set_ray(rh, e, o, d, lane_tfar(lane));  // ray id 0: lane 0
#if RTC_VERSION_MAJOR >= 4
            rtcInitRayQueryContext(&c.base);
            RTCIntersectArguments args;
            rtcInitIntersectArguments(&args);
            args.context = &c.base;
            args.filter = nearest_filter;
            args.flags = static_cast<RTCRayQueryFlags>(args.flags | RTC_RAY_QUERY_FLAG_INVOKE_ARGUMENT_FILTER);
            rtcIntersect1(s->scene, &rh, &args);
#else
            rtcInitIntersectContext(&c.base);
            c.base.filter = nearest_filter;
            rtcIntersect1(s->scene, &c.base, &rh);
#endif
        }
        const int kept = merged_hits(e, lane, k, same_instance, out);
        raw = {list.data(), lane.count, lane.count == capacity};
        if (kept == k || !raw.full) return kept;
    }
}

// Where the nearest-hit queries write ray r's hits: layer j at j * n + r (normals: component
// a at (3 * j + a) * n + r). Either the hits themselves (t, face) or, for engine_nearest_surfaces,
// what a view stores of them: depth t * depth_scale, the face's winding normal rotated by R
// (row a of R times it, summed x, y, z in float64), the face's instance and its label, each
// rounded as sceneforge.raytrace._nearest_surfaces computes it; front_facing either way.
struct NearestOut {
    int64_t n;
    int k;
    bool* front;
    // the hits: t f8 and face i8 (null for surfaces)
    double* t = nullptr;
    int64_t* face = nullptr;
    // the surfaces: inputs, then outputs
    const EngineObject* engine = nullptr;
    const double* scale = nullptr;
    bool scale_shared = false;
    const double* R = nullptr;
    const uint8_t* labels = nullptr;
    float* depth = nullptr;
    float* normal = nullptr;
    int32_t* instance = nullptr;
    uint8_t* label = nullptr;

    // Rays lo..hi-1 past their last hit, every layer (their hits are written over it).
    void blank(int64_t lo, int64_t hi) const {
        const float nan = std::numeric_limits<float>::quiet_NaN();
        for (int j = 0; j < k; ++j) {
            const int64_t a = j * n + lo, b = j * n + hi;
            std::fill(front + a, front + b, false);
            if (t) {
                std::fill(t + a, t + b, std::numeric_limits<double>::quiet_NaN());
                std::fill(face + a, face + b, int64_t{-1});
                continue;
            }
            std::fill(depth + a, depth + b, nan);
            std::fill(instance + a, instance + b, int32_t{-1});
            std::fill(label + a, label + b, uint8_t{0});
            for (int c = 0; c < 3; ++c) std::fill(normal + (3 * j + c) * n + lo, normal + (3 * j + c) * n + hi, nan);
        }
    }

    // Ray r's hits (after blank: the layers past them are written already).
    void write(int64_t r, const HitRecord* hits, int kept) const {
        for (int j = 0; j < kept; ++j) {
            const int64_t i = j * n + r;
            front[i] = hits[j].cos < 0;
            if (t) {
                t[i] = hits[j].t, face[i] = hits[j].face;
                continue;
            }
            float* normal_i = normal + 3 * j * n + r;  // x, y, z n apart
            const int64_t f = hits[j].face;
            depth[i] = static_cast<float>(hits[j].t * scale[scale_shared ? 0 : r]);
            const int32_t inst = (*engine->instance)[f];
            instance[i] = inst, label[i] = labels[inst];
            const double* q = engine->planes->data() + 4 * f;  // the unit normal x, y, z, then the offset
            for (int a = 0; a < 3; ++a)
                normal_i[a * n] = static_cast<float>(R[3 * a] * q[0] + R[3 * a + 1] * q[1] + R[3 * a + 2] * q[2]);
        }
    }
};

// The nearest hits of rays lo..hi-1, P at a time (see above), written to `out`; each ray's
// raw hits also handed to on_ray(r, RawHits).
template <int P, class F>
void nearest_packed(const EngineObject* e, const std::vector<const Scene*>& scenes, const RayRows& rays, int64_t lo,
                    int64_t hi, int spare, double margin, double same_instance, const NearestOut& out,
                    int64_t& retraced, int64_t& single_rays, F&& on_ray) {
    const int k = out.k, capacity = k + spare;
    std::vector<HitRecord> lists(static_cast<size_t>(P) * capacity), single, hits(k);
    for (int64_t r0 = lo; r0 < hi; r0 += P) {
        const int lanes = static_cast<int>(std::min<int64_t>(P, hi - r0));
        auto ray = [&](int j) { return r0 + (j < lanes ? j : 0); };  // idle lanes repeat the first (not traced)
        NearestCollector c;
        init_nearest(c, e, capacity, margin, true);
        alignas(64) int valid[P];
        for (int j = 0; j < P; ++j) {
            valid[j] = j < lanes ? -1 : 0;
            start_lane(c.lane[j], rays.origin(ray(j)), rays.direction(ray(j)), lists.data() + j * capacity);
        }
        for (const Scene* s : scenes) {
            c.face_base = s->face_base.data();
            typename Packet<P>::RayHit rh;
            for (int j = 0; j < P; ++j) set_lane(rh, j, e, c.lane[j].o, c.lane[j].d, 0.0f, lane_tfar(c.lane[j]));
            Packet<P>::intersect(valid, s->scene, &rh, &c.base, nearest_filter);
        }
        for (int j = 0; j < lanes; ++j) {
            const NearestLane& lane = c.lane[j];
            int kept = -1;
            RawHits raw{lane.list, lane.count, lane.count == capacity};
            if (!lane.edge && lane.count > 0) {
                kept = merged_hits(e, lane, k, same_instance, hits.data());
                if (kept < k && raw.full) kept = -1, ++retraced;
            }
            if (kept < 0) {  // next to an edge, no hit (an edge-on ray may hit ray by ray), or repeats
                kept = nearest_of_ray(e, scenes, lane.o, lane.d, k, spare, margin, same_instance, single,
                                      hits.data(), retraced, raw);
                ++single_rays;
            }
            out.write(r0 + j, hits.data(), kept);
            on_ray(r0 + j, raw);
        }
    }
}

// The nearest hits of rays lo..hi-1 into `out` (blank first), in packets of the engine's
// width; on_ray(r, RawHits) as for nearest_packed. Adds to `retraced` and `single_rays`.
template <class F>
void nearest_block(const EngineObject* e, const std::vector<const Scene*>& scenes, const RayRows& rays, int64_t lo,
                   int64_t hi, int spare, double margin, double same_instance, const NearestOut& out,
                   int64_t& retraced, int64_t& single_rays, F&& on_ray) {
    out.blank(lo, hi);
    switch (e->packet) {
        case 16:
            return nearest_packed<16>(e, scenes, rays, lo, hi, spare, margin, same_instance, out, retraced,
                                      single_rays, on_ray);
        case 8:
            return nearest_packed<8>(e, scenes, rays, lo, hi, spare, margin, same_instance, out, retraced,
                                     single_rays, on_ray);
        case 4:
            return nearest_packed<4>(e, scenes, rays, lo, hi, spare, margin, same_instance, out, retraced,
                                     single_rays, on_ray);
        default: {
            std::vector<HitRecord> list, hits(out.k);
            for (int64_t r = lo; r < hi; ++r) {
                RawHits raw;
                out.write(r, hits.data(),
                          nearest_of_ray(e, scenes, rays.origin(r), rays.direction(r), out.k, spare, margin,
                                         same_instance, list, hits.data(), retraced, raw));
                on_ray(r, raw);
            }
        }
    }
}

// Every ray's nearest hits into `out`, in blocks on the engine's threads; returns (longer,
// single): the traversals again with a longer list (same-instance repeats that used up the
// spare) and the rays of packets traced again ray by ray.
PyObject* run_nearest(EngineObject* self, const std::vector<const Scene*>& scenes, const RayRows& rays, int spare,
                      double margin, double same_instance, const NearestOut& out) {
    std::atomic<int64_t> again{0}, singles{0};
    const int64_t n = rays.n;
    Py_BEGIN_ALLOW_THREADS
    parallel_blocks((n + kBlock - 1) / kBlock, self->threads, [&](int64_t b) {
        int64_t retraced = 0, single_rays = 0;
        nearest_block(self, scenes, rays, b * kBlock, std::min<int64_t>(n, (b + 1) * kBlock), spare, margin,
                      same_instance, out, retraced, single_rays, [](int64_t, const RawHits&) {});
        again += retraced, singles += single_rays;
    });
    Py_END_ALLOW_THREADS
    return Py_BuildValue("(LL)", static_cast<long long>(again.load()), static_cast<long long>(singles.load()));
}

// A writable C-contiguous buffer of exactly `bytes` bytes.
bool get_out_buffer(PyObject* obj, Buffer& b, Py_ssize_t bytes, const char* name) {
    if (PyObject_GetBuffer(obj, &b.view, PyBUF_C_CONTIGUOUS | PyBUF_WRITABLE) != 0) return false;
    b.held = true;
    if (b.view.len != bytes) {
        PyErr_Format(PyExc_ValueError, "%s: expected %zd bytes, got %zd", name, bytes, b.view.len);
        return false;
    }
    return true;
}

// The arguments both nearest-hit queries start with: scene_ids, n, origins, directions, k,
// spare, margin, same_instance.
struct NearestArgs {
    PyObject *ids, *origins, *directions;
    Py_ssize_t n;
    int k, spare;
    double margin, same_instance;
};

bool check_nearest(EngineObject* self, const NearestArgs& a, std::vector<const Scene*>& scenes, Buffer& bo,
                   Buffer& bd, RayRows& rays) {
    if (a.k < 1 || a.spare < 0) {
        PyErr_Format(PyExc_ValueError, "nearest: k must be >= 1 and spare >= 0, got %d and %d", a.k, a.spare);
        return false;
    }
    return get_scene_ids(self, a.ids, scenes) && get_rays(a.origins, a.directions, a.n, bo, bd, rays);
}

// nearest(scene_ids, n, origins, directions, k, spare, margin, same_instance, t (k,n) f8 out,
//         face (k,n) i8 out, front_facing (k,n) bool out) -> (longer, single)
//   Layer j of ray r (index j * n + r): its j-th hit of the merged, sorted hits over the
//   scenes (as collect's), t NaN, face -1 and front_facing false past its last hit (see
//   run_nearest for the counts returned).
PyObject* engine_nearest(EngineObject* self, PyObject* args) {
    NearestArgs a;
    PyObject *t_o, *face_o, *front_o;
    if (!PyArg_ParseTuple(args, "OnOOiiddOOO", &a.ids, &a.n, &a.origins, &a.directions, &a.k, &a.spare, &a.margin,
                          &a.same_instance, &t_o, &face_o, &front_o))
        return nullptr;
    std::vector<const Scene*> scenes;
    Buffer bo, bd, bt, bf, bfr;
    RayRows rays;
    const Py_ssize_t items = static_cast<Py_ssize_t>(a.k) * a.n;
    if (!check_nearest(self, a, scenes, bo, bd, rays) || !get_out_buffer(t_o, bt, 8 * items, "t out") ||
        !get_out_buffer(face_o, bf, 8 * items, "face out") || !get_out_buffer(front_o, bfr, items, "front_facing out"))
        return nullptr;
    NearestOut out{a.n, a.k, static_cast<bool*>(bfr.view.buf)};
    out.t = static_cast<double*>(bt.view.buf);
    out.face = static_cast<int64_t*>(bf.view.buf);
    return run_nearest(self, scenes, rays, a.spare, a.margin, a.same_instance, out);
}

// nearest_surfaces(scene_ids, n, origins, directions, k, spare, margin, same_instance,
//                  depth_scale (n,) or (1,) f8, rotation (3,3) f8, labels (n_instances,) u1,
//                  depth (k,n) f4 out, normal (k,3,n) f4 out, instance (k,n) i4 out,
//                  label (k,n) u1 out, front_facing (k,n) bool out) -> (longer, single)
//   engine_nearest's hits written as sceneforge.raytrace._nearest_surfaces writes them
//   (NearestOut): NaN, NaN, -1, 0 and false past a ray's last hit.
PyObject* engine_nearest_surfaces(EngineObject* self, PyObject* args) {
    NearestArgs a;
    PyObject *scale_o, *rot_o, *labels_o, *depth_o, *normal_o, *inst_o, *label_o, *front_o;
    if (!PyArg_ParseTuple(args, "OnOOiiddOOOOOOOO", &a.ids, &a.n, &a.origins, &a.directions, &a.k, &a.spare,
                          &a.margin, &a.same_instance, &scale_o, &rot_o, &labels_o, &depth_o, &normal_o, &inst_o,
                          &label_o, &front_o))
        return nullptr;
    std::vector<const Scene*> scenes;
    Buffer bo, bd, bs, br, bl, bdp, bn, bi, blb, bfr;
    RayRows rays;
    const Py_ssize_t items = static_cast<Py_ssize_t>(a.k) * a.n;
    const Py_ssize_t n_instances = static_cast<Py_ssize_t>(self->first_face->size()) - 1;
    if (!check_nearest(self, a, scenes, bo, bd, rays) || !get_buffer(scale_o, bs, sizeof(double), -1, "depth_scale") ||
        !get_buffer(rot_o, br, sizeof(double), 9, "rotation") ||
        !get_buffer(labels_o, bl, 1, n_instances, "labels") || !get_out_buffer(depth_o, bdp, 4 * items, "depth out") ||
        !get_out_buffer(normal_o, bn, 12 * items, "normal out") ||
        !get_out_buffer(inst_o, bi, 4 * items, "instance out") || !get_out_buffer(label_o, blb, items, "label out") ||
        !get_out_buffer(front_o, bfr, items, "front_facing out"))
        return nullptr;
    const Py_ssize_t n_scale = bs.view.len / static_cast<Py_ssize_t>(sizeof(double));
    if (n_scale != 1 && n_scale != a.n) {
        PyErr_Format(PyExc_ValueError, "depth_scale: %zd values for %zd rays", n_scale, a.n);
        return nullptr;
    }
    NearestOut out{a.n, a.k, static_cast<bool*>(bfr.view.buf)};
    out.engine = self;
    out.scale = static_cast<const double*>(bs.view.buf);
    out.scale_shared = n_scale == 1;
    out.R = static_cast<const double*>(br.view.buf);
    out.labels = static_cast<const uint8_t*>(bl.view.buf);
    out.depth = static_cast<float*>(bdp.view.buf);
    out.normal = static_cast<float*>(bn.view.buf);
    out.instance = static_cast<int32_t*>(bi.view.buf);
    out.label = static_cast<uint8_t*>(blb.view.buf);
    return run_nearest(self, scenes, rays, a.spare, a.margin, a.same_instance, out);
}

// The CSR arrays of Hits from per-block raw hits (every block's hits grouped by ray, in ray
// order, with their plane distances; t_min and t_max over them): engine_collect's pass 2 and
// output, operation for operation -- each ray's hits ordered by the batch's float key, exact
// key ties by face, same-instance repeats dropped -- so that the same raw hits give the same
// bytes. Returns (offsets, t, instance, triangle, front_facing) bytearrays, or null (error set).
PyObject* hits_result(const EngineObject* self, std::vector<BlockHits>& blocks, int64_t n_blocks, int64_t n,
                      double tol) {
    const double inf = std::numeric_limits<double>::infinity();
    const int32_t* face_instance = self->instance->data();
    const int64_t* first_face = self->first_face->data();
    double t0 = inf, t1 = -inf;
    for (int64_t b = 0; b < n_blocks; ++b) t0 = std::min(t0, blocks[b].t_min), t1 = std::max(t1, blocks[b].t_max);
    const double span = (t1 - t0) + 1.0;
    Py_BEGIN_ALLOW_THREADS
    parallel_blocks(n_blocks, self->threads, [&](int64_t b) {
        BlockHits& blk = blocks[b];
        std::vector<std::pair<double, int64_t>> keyed;  // (key, position in the ray's hits)
        std::vector<HitRecord> sorted;
        size_t h = 0, written = 0;  // kept hits go back into blk.hits, never past the ray being read
        for (size_t j = 0; j < blk.counts.size(); ++j) {
            const int64_t count = blk.counts[j];
            const double r = static_cast<double>(b * kBlock + static_cast<int64_t>(j));
            HitRecord* hits = blk.hits.data() + h;
            h += count;
            if (count == 0) continue;
            if (count == 1) {
                blk.hits[written++] = hits[0];
                continue;
            }
            keyed.resize(count);
            for (int64_t k = 0; k < count; ++k) keyed[k] = {r * span + (hits[k].t - t0), k};
            auto before = [&](const std::pair<double, int64_t>& x, const std::pair<double, int64_t>& y) {
                if (x.first != y.first) return x.first < y.first;
                return hits[x.second].face < hits[y.second].face;
            };
            if (count <= 24) {
                for (int64_t k = 1; k < count; ++k) {
                    const auto item = keyed[k];
                    int64_t i = k;
                    for (; i > 0 && before(item, keyed[i - 1]); --i) keyed[i] = keyed[i - 1];
                    keyed[i] = item;
                }
            } else {
                std::sort(keyed.begin(), keyed.end(), before);
            }
            sorted.resize(count);
            for (int64_t k = 0; k < count; ++k) sorted[k] = hits[keyed[k].second];
            int64_t n_kept = 0;
            for (int64_t k = 0; k < count; ++k) {
                bool repeat = false;
                const int32_t inst = face_instance[sorted[k].face];
                for (int64_t s = k - 1; s >= 0 && sorted[k].t - sorted[s].t <= tol; --s)
                    if (face_instance[sorted[s].face] == inst) {
                        repeat = true;
                        break;
                    }
                if (!repeat) blk.hits[written++] = sorted[k], ++n_kept;
            }
            blk.counts[j] = n_kept;
        }
        blk.hits.resize(written);
    });
    Py_END_ALLOW_THREADS

    int64_t total = 0;
    for (int64_t b = 0; b < n_blocks; ++b) total += static_cast<int64_t>(blocks[b].hits.size());
    PyObject* out[5] = {PyByteArray_FromStringAndSize(nullptr, (n + 1) * sizeof(int64_t)),
                        PyByteArray_FromStringAndSize(nullptr, total * sizeof(double)),
                        PyByteArray_FromStringAndSize(nullptr, total * sizeof(int32_t)),
                        PyByteArray_FromStringAndSize(nullptr, total * sizeof(int64_t)),
                        PyByteArray_FromStringAndSize(nullptr, total)};
    if (!out[0] || !out[1] || !out[2] || !out[3] || !out[4]) {
        for (PyObject* o : out) Py_XDECREF(o);
        return nullptr;
    }
    int64_t* offsets = reinterpret_cast<int64_t*>(PyByteArray_AS_STRING(out[0]));
    double* t = reinterpret_cast<double*>(PyByteArray_AS_STRING(out[1]));
    int32_t* instance = reinterpret_cast<int32_t*>(PyByteArray_AS_STRING(out[2]));
    int64_t* triangle = reinterpret_cast<int64_t*>(PyByteArray_AS_STRING(out[3]));
    bool* front = reinterpret_cast<bool*>(PyByteArray_AS_STRING(out[4]));
    int64_t k = 0;
    offsets[0] = 0;
    for (int64_t b = 0; b < n_blocks; ++b) {
        const auto& blk = blocks[b];
        for (size_t j = 0; j < blk.counts.size(); ++j) {
            const int64_t r = b * kBlock + static_cast<int64_t>(j);
            offsets[r + 1] = offsets[r] + blk.counts[j];
        }
        for (const auto& hit : blk.hits) {
            const int32_t inst = face_instance[hit.face];
            t[k] = hit.t;
            instance[k] = inst;
            triangle[k] = hit.face - first_face[inst];
            front[k] = hit.cos < 0;
            ++k;
        }
    }
    return Py_BuildValue("(NNNNN)", out[0], out[1], out[2], out[3], out[4]);
}

// frontal_nearest(object_ids, closing_ids, objects (n_instances,) bool, n, origins, directions,
//                 margin, same_instance, slack, k, spare, depth_scale, rotation, labels,
//                 depth out, normal out, instance out, label out, front_facing out)
//   -> (offsets, t, instance, triangle, front_facing, closing face, t, instance, triangle,
//       front_facing, (longer, single))
//
// The frontal query and the ray-intersection layers of a view from one traversal per ray:
// the first ten results are what collect(object_ids, ..., closing_ids, 0, slack) returns,
// bit for bit (each ray's closing hit, found first in packets by closing_hits, and its object
// hits up to it + slack as Hits), and the depth ... front_facing outputs are what
// nearest_surfaces writes over the object and closing scenes together. A ray's object hits
// up to its cut-off are among the nearest hits the traversal keeps whenever the list is not
// full or ends beyond the cut-off: they are taken from there (the hits of the members of
// `objects`, plane distance at most the cut-off: the hits collect keeps); for the other rays
// (more surfaces before the closing hit than the list holds) the objects are traced again as
// collect traces them. Both go through collect's pass 2 (hits_result).
PyObject* engine_frontal_nearest(EngineObject* self, PyObject* args) {
    NearestArgs a;
    PyObject *closing_obj, *objects_obj, *scale_o, *rot_o, *labels_o, *depth_o, *normal_o, *inst_o, *label_o, *front_o;
    double slack;
    if (!PyArg_ParseTuple(args, "OOOnOOdddiiOOOOOOOO", &a.ids, &closing_obj, &objects_obj, &a.n, &a.origins,
                          &a.directions, &a.margin, &a.same_instance, &slack, &a.k, &a.spare, &scale_o, &rot_o,
                          &labels_o, &depth_o, &normal_o, &inst_o, &label_o, &front_o))
        return nullptr;
    std::vector<const Scene*> object_scenes, closing_scenes;
    Buffer bo, bd, bm, bs, br, bl, bdp, bn, bi, blb, bfr;
    RayRows rays;
    const Py_ssize_t items = static_cast<Py_ssize_t>(a.k) * a.n;
    const Py_ssize_t n_instances = static_cast<Py_ssize_t>(self->first_face->size()) - 1;
    if (!check_nearest(self, a, object_scenes, bo, bd, rays) || !get_scene_ids(self, closing_obj, closing_scenes) ||
        !get_buffer(objects_obj, bm, 1, n_instances, "objects") ||
        !get_buffer(scale_o, bs, sizeof(double), -1, "depth_scale") ||
        !get_buffer(rot_o, br, sizeof(double), 9, "rotation") ||
        !get_buffer(labels_o, bl, 1, n_instances, "labels") || !get_out_buffer(depth_o, bdp, 4 * items, "depth out") ||
        !get_out_buffer(normal_o, bn, 12 * items, "normal out") ||
        !get_out_buffer(inst_o, bi, 4 * items, "instance out") || !get_out_buffer(label_o, blb, items, "label out") ||
        !get_out_buffer(front_o, bfr, items, "front_facing out"))
        return nullptr;
    const Py_ssize_t n_scale = bs.view.len / static_cast<Py_ssize_t>(sizeof(double));
    if (n_scale != 1 && n_scale != a.n) {
        PyErr_Format(PyExc_ValueError, "depth_scale: %zd values for %zd rays", n_scale, a.n);
        return nullptr;
    }
    const int64_t n = a.n;
    NearestOut out{n, a.k, static_cast<bool*>(bfr.view.buf)};
    out.engine = self;
    out.scale = static_cast<const double*>(bs.view.buf);
    out.scale_shared = n_scale == 1;
    out.R = static_cast<const double*>(br.view.buf);
    out.labels = static_cast<const uint8_t*>(bl.view.buf);
    out.depth = static_cast<float*>(bdp.view.buf);
    out.normal = static_cast<float*>(bn.view.buf);
    out.instance = static_cast<int32_t*>(bi.view.buf);
    out.label = static_cast<uint8_t*>(blb.view.buf);
    std::vector<const Scene*> scenes(object_scenes);
    scenes.insert(scenes.end(), closing_scenes.begin(), closing_scenes.end());
    const bool* is_object = static_cast<const bool*>(bm.view.buf);

    PyObject* closing_out[5];
    const size_t sizes[5] = {sizeof(int64_t), sizeof(double), sizeof(int32_t), sizeof(int64_t), 1};
    for (int c = 0; c < 5; ++c) closing_out[c] = PyByteArray_FromStringAndSize(nullptr, n * sizes[c]);
    if (!closing_out[0] || !closing_out[1] || !closing_out[2] || !closing_out[3] || !closing_out[4]) {
        for (PyObject* o : closing_out) Py_XDECREF(o);
        return nullptr;
    }
    int64_t* closing_face = reinterpret_cast<int64_t*>(PyByteArray_AS_STRING(closing_out[0]));
    double* closing_t = reinterpret_cast<double*>(PyByteArray_AS_STRING(closing_out[1]));
    int32_t* closing_inst = reinterpret_cast<int32_t*>(PyByteArray_AS_STRING(closing_out[2]));
    int64_t* closing_tri = reinterpret_cast<int64_t*>(PyByteArray_AS_STRING(closing_out[3]));
    bool* closing_front = reinterpret_cast<bool*>(PyByteArray_AS_STRING(closing_out[4]));
    const int32_t* face_instance = self->instance->data();
    const int64_t* first_face = self->first_face->data();
    const double inf = std::numeric_limits<double>::infinity();
    const int64_t n_blocks = (n + kBlock - 1) / kBlock;
    std::vector<BlockHits> blocks(n_blocks);
    std::atomic<int64_t> again{0}, singles{0};

    Py_BEGIN_ALLOW_THREADS
    parallel_blocks(n_blocks, self->threads, [&](int64_t b) {
        const int64_t lo = b * kBlock, hi = std::min<int64_t>(n, lo + kBlock);
        BlockHits& blk = blocks[b];
        blk.counts.assign(hi - lo, 0);
        double cos[kBlock];
        closing_hits(self, closing_scenes, rays, lo, hi, 0.0, closing_face, closing_t, cos);
        for (int64_t r = lo; r < hi; ++r) {
            const int64_t f = closing_face[r];
            closing_inst[r] = f >= 0 ? face_instance[f] : -1;
            closing_tri[r] = f >= 0 ? f - first_face[closing_inst[r]] : -1;
            closing_front[r] = cos[r - lo] < 0;
        }
        Collector c;  // for rays whose object hits the nearest hits do not hold
        init_collector(c, self);
        c.raw = false;
        c.out = &blk.hits;
        int64_t retraced = 0, single_rays = 0;
        nearest_block(self, scenes, rays, lo, hi, a.spare, a.margin, a.same_instance, out, retraced, single_rays,
                      [&](int64_t r, const RawHits& raw) {
            const double cutoff = std::isnan(closing_t[r]) ? inf : closing_t[r] + slack;
            const size_t before = blk.hits.size();
            if (!raw.full || raw.list[raw.count - 1].t > cutoff) {
                for (int j = 0; j < raw.count && raw.list[j].t <= cutoff; ++j)
                    if (is_object[face_instance[raw.list[j].face]]) blk.hits.push_back(raw.list[j]);
            } else {  // as engine_collect traces a ray's objects
                c.o = rays.origin(r), c.d = rays.direction(r);
                c.cutoff = cutoff;
                c.limit32 = c.cutoff + a.margin;
                float tfar = static_cast<float>(c.limit32);
                if (static_cast<double>(tfar) < c.limit32)
                    tfar = std::nextafter(tfar, std::numeric_limits<float>::infinity());
                for (const Scene* s : object_scenes) {
                    RTCRayHit rh;
                    set_ray(rh, self, c.o, c.d, tfar);
                    intersect_collecting(s, c, rh);
                }
                plane_distances(c, blk.hits, before);
            }
            blk.counts[r - lo] = static_cast<int64_t>(blk.hits.size() - before);
            for (size_t h = before; h < blk.hits.size(); ++h) {
                blk.t_min = std::min(blk.t_min, blk.hits[h].t);
                blk.t_max = std::max(blk.t_max, blk.hits[h].t);
            }
        });
        again += retraced, singles += single_rays;
    });
    Py_END_ALLOW_THREADS

    PyObject* hits = hits_result(self, blocks, n_blocks, n, a.same_instance);
    if (!hits) {
        for (PyObject* o : closing_out) Py_XDECREF(o);
        return nullptr;
    }
    PyObject* counts = Py_BuildValue("(LL)", static_cast<long long>(again.load()), static_cast<long long>(singles.load()));
    return Py_BuildValue("(NNNNNNN)", hits, closing_out[0], closing_out[1], closing_out[2], closing_out[3],
                         closing_out[4], counts);
}

// ------------------------------------------------------------------ closest distance

struct ClosestQuery {
    const EngineObject* engine;
    const Scene* scene;
    double p[3];  // the query point, float64, unshifted
    double best;
};

inline double dot3(const double* a, const double* b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }

// Distance from p to triangle (a, b, c), float64 (Ericson, Real-Time Collision Detection 5.1.5).
double point_triangle_distance(const double* p, const double* a, const double* b, const double* c) {
    double ab[3], ac[3], ap[3], q[3];
    for (int i = 0; i < 3; ++i) ab[i] = b[i] - a[i], ac[i] = c[i] - a[i], ap[i] = p[i] - a[i];
    auto dist = [&](const double* x) {
        const double u = p[0] - x[0], v = p[1] - x[1], w = p[2] - x[2];
        return std::sqrt(u * u + v * v + w * w);
    };
    const double d1 = dot3(ab, ap), d2 = dot3(ac, ap);
    if (d1 <= 0 && d2 <= 0) return dist(a);
    double bp[3], cp[3];
    for (int i = 0; i < 3; ++i) bp[i] = p[i] - b[i], cp[i] = p[i] - c[i];
    const double d3 = dot3(ab, bp), d4 = dot3(ac, bp);
    if (d3 >= 0 && d4 <= d3) return dist(b);
    const double d5 = dot3(ab, cp), d6 = dot3(ac, cp);
    if (d6 >= 0 && d5 <= d6) return dist(c);
    const double vc = d1 * d4 - d3 * d2;
    if (vc <= 0 && d1 >= 0 && d3 <= 0) {
        const double v = d1 / (d1 - d3);
        for (int i = 0; i < 3; ++i) q[i] = a[i] + v * ab[i];
        return dist(q);
    }
    const double vb = d5 * d2 - d1 * d6;
    if (vb <= 0 && d2 >= 0 && d6 <= 0) {
        const double w = d2 / (d2 - d6);
        for (int i = 0; i < 3; ++i) q[i] = a[i] + w * ac[i];
        return dist(q);
    }
    const double va = d3 * d6 - d5 * d4;
    if (va <= 0 && (d4 - d3) >= 0 && (d5 - d6) >= 0) {
        const double w = (d4 - d3) / ((d4 - d3) + (d5 - d6));
        for (int i = 0; i < 3; ++i) q[i] = b[i] + w * (c[i] - b[i]);
        return dist(q);
    }
    const double denom = 1.0 / (va + vb + vc);
    const double v = vb * denom, w = vc * denom;
    for (int i = 0; i < 3; ++i) q[i] = a[i] + ab[i] * v + ac[i] * w;
    return dist(q);
}

// float32 radius that still contains every point within float64 distance d, allowing for
// the float32 rounding of the shifted vertices and query point
inline float search_radius(double d) { return static_cast<float>(d * (1.0 + 1e-5) + 1e-5); }

bool closest_callback(RTCPointQueryFunctionArguments* args) {
    ClosestQuery* q = static_cast<ClosestQuery*>(args->userPtr);
    const int64_t face = q->scene->face_base[args->geomID] + args->primID;
    const int64_t* F = q->engine->faces->data() + 3 * face;
    const double* V = q->engine->vertices->data();
    const double d = point_triangle_distance(q->p, V + 3 * F[0], V + 3 * F[1], V + 3 * F[2]);
    if (d < q->best) {
        q->best = d;
        const float radius = search_radius(d);
        if (radius < args->query->radius) {
            args->query->radius = radius;
            return true;
        }
    }
    return false;
}

// closest(scene_ids, points (k,3) f8) -> bytearray (k,) f8: distance to the nearest triangle
PyObject* engine_closest(EngineObject* self, PyObject* args) {
    PyObject *ids, *points;
    if (!PyArg_ParseTuple(args, "OO", &ids, &points)) return nullptr;
    std::vector<const Scene*> scenes;
    Buffer bp;
    if (!get_scene_ids(self, ids, scenes) || !get_buffer(points, bp, 3 * sizeof(double), -1, "points"))
        return nullptr;
    const int64_t k = bp.view.len / (3 * sizeof(double));
    const double* P = static_cast<const double*>(bp.view.buf);
    std::vector<double> out(k);
    Py_BEGIN_ALLOW_THREADS
    parallel_blocks((k + 63) / 64, self->threads, [&](int64_t b) {
        for (int64_t i = b * 64; i < std::min<int64_t>(k, (b + 1) * 64); ++i) {
            double best = std::numeric_limits<double>::infinity();
            for (const Scene* s : scenes) {
                ClosestQuery q{self, s, {P[3 * i], P[3 * i + 1], P[3 * i + 2]}, best};
                RTCPointQuery query;
                query.x = static_cast<float>(P[3 * i] - self->shift[0]);
                query.y = static_cast<float>(P[3 * i + 1] - self->shift[1]);
                query.z = static_cast<float>(P[3 * i + 2] - self->shift[2]);
                query.time = 0.0f;
                query.radius = std::isfinite(best) ? search_radius(best) : std::numeric_limits<float>::infinity();
                RTCPointQueryContext context;
                rtcInitPointQueryContext(&context);
                rtcPointQuery(s->scene, &query, &context, closest_callback, &q);
                best = q.best;
            }
            out[i] = best;
        }
    });
    Py_END_ALLOW_THREADS
    return new_bytearray(out.data(), k * sizeof(double));
}

// ------------------------------------------------------------------ layer rules

// layer_rules(offsets (n+1,) i8, t (k,) f8, instance (k,) i4, closing_t (n,) f8,
//             closing_instance (n,) i4, depth_scale (n,) or (1,) f8, category (c,) u1,
//             same_instance f8, depth (5,n) f4 out, category (3,n) u1 out, instance (2,n) i4 out
//             [, hit (4,n) i8 out])
//
// The layer rules of docs/spec.md §4.2-§4.3 on each ray's object hits (sorted, none beyond the closing hit + slack),
// what sceneforge.layers._apply_rules does with whole-array operations, here in one pass
// over the hits to find the visible instances (each ray's first object hit) and one more
// for the layers. Every value is computed as there: depths are the float64 product
// t * depth_scale rounded to float32, D3's test is t >= d2 - same_instance in float64. The
// output arrays come filled with their "none" values (NaN, 0, -1). With ``hit``, also the
// index into the object hits of the hit that fills each of D1..D4 (the labels of every layer).
PyObject* layer_rules(PyObject*, PyObject* args) {
    PyObject *offsets_o, *t_o, *inst_o, *ct_o, *ci_o, *scale_o, *cat_o, *depth_o, *ocat_o, *oinst_o;
    PyObject* ohit_o = Py_None;
    double same_instance;
    if (!PyArg_ParseTuple(args, "OOOOOOOdOOO|O", &offsets_o, &t_o, &inst_o, &ct_o, &ci_o, &scale_o, &cat_o,
                          &same_instance, &depth_o, &ocat_o, &oinst_o, &ohit_o))
        return nullptr;
    Buffer bo, bt, bi, bct, bci, bs, bc, bd, bocat, boinst, bohit;
    if (!get_buffer(offsets_o, bo, sizeof(int64_t), -1, "offsets")) return nullptr;
    const Py_ssize_t n = bo.view.len / static_cast<Py_ssize_t>(sizeof(int64_t)) - 1;
    if (n < 0) {
        PyErr_SetString(PyExc_ValueError, "offsets must have n_rays + 1 items");
        return nullptr;
    }
    const int64_t* offsets = static_cast<const int64_t*>(bo.view.buf);
    const Py_ssize_t k = offsets[n];
    if (!get_buffer(t_o, bt, sizeof(double), k, "t") || !get_buffer(inst_o, bi, sizeof(int32_t), k, "instance") ||
        !get_buffer(ct_o, bct, sizeof(double), n, "closing_t") ||
        !get_buffer(ci_o, bci, sizeof(int32_t), n, "closing_instance") ||
        !get_buffer(scale_o, bs, sizeof(double), -1, "depth_scale") ||
        !get_buffer(cat_o, bc, 1, -1, "category"))
        return nullptr;
    const Py_ssize_t n_scale = bs.view.len / static_cast<Py_ssize_t>(sizeof(double));
    if (n_scale != 1 && n_scale != n) {
        PyErr_Format(PyExc_ValueError, "depth_scale: %zd values for %zd rays", n_scale, n);
        return nullptr;
    }
    for (auto [obj, b, items, name] : {std::tuple{depth_o, &bd, 5 * n * 4, "depth"},
                                       std::tuple{ocat_o, &bocat, 3 * n, "category out"},
                                       std::tuple{oinst_o, &boinst, 2 * n * 4, "instance out"}}) {
        if (PyObject_GetBuffer(obj, &b->view, PyBUF_C_CONTIGUOUS | PyBUF_WRITABLE) != 0) return nullptr;
        b->held = true;
        if (b->view.len != items) {
            PyErr_Format(PyExc_ValueError, "%s: expected %zd bytes, got %zd", name, items, b->view.len);
            return nullptr;
        }
    }
    int64_t* out_hit = nullptr;
    if (ohit_o != Py_None) {
        if (PyObject_GetBuffer(ohit_o, &bohit.view, PyBUF_C_CONTIGUOUS | PyBUF_WRITABLE) != 0) return nullptr;
        bohit.held = true;
        if (bohit.view.len != 4 * n * 8) {
            PyErr_Format(PyExc_ValueError, "hit out: expected %zd bytes, got %zd", 4 * n * 8, bohit.view.len);
            return nullptr;
        }
        out_hit = static_cast<int64_t*>(bohit.view.buf);
    }
    const double* t = static_cast<const double*>(bt.view.buf);
    const int32_t* inst = static_cast<const int32_t*>(bi.view.buf);
    const double* closing_t = static_cast<const double*>(bct.view.buf);
    const int32_t* closing_inst = static_cast<const int32_t*>(bci.view.buf);
    const double* scale = static_cast<const double*>(bs.view.buf);
    const uint8_t* category = static_cast<const uint8_t*>(bc.view.buf);
    const int64_t n_inst = bc.view.len;
    float* depth = static_cast<float*>(bd.view.buf);
    uint8_t* out_cat = static_cast<uint8_t*>(bocat.view.buf);
    int32_t* out_inst = static_cast<int32_t*>(boinst.view.buf);
    bool bad = false;
    for (Py_ssize_t i = 0; i < k && !bad; ++i) bad = inst[i] < 0 || inst[i] >= n_inst;
    for (Py_ssize_t r = 0; r < n && !bad; ++r) bad = closing_inst[r] < -1 || closing_inst[r] >= n_inst;
    for (Py_ssize_t r = 0; r < n && !bad; ++r) bad = offsets[r] > offsets[r + 1] || offsets[r] < 0;
    if (bad) {
        PyErr_SetString(PyExc_ValueError, "layer_rules: an instance index outside the labelled instances, or bad offsets");
        return nullptr;
    }
    Py_BEGIN_ALLOW_THREADS
    std::vector<char> visible(n_inst, 0);
    for (Py_ssize_t r = 0; r < n; ++r)
        if (offsets[r + 1] > offsets[r]) visible[inst[offsets[r]]] = 1;
    float* D[5];
    for (int l = 0; l < 5; ++l) D[l] = depth + l * n;
    for (Py_ssize_t r = 0; r < n; ++r) {
        const double s = scale[n_scale == 1 ? 0 : r];
        D[4][r] = static_cast<float>(closing_t[r] * s);
        out_cat[2 * n + r] = closing_inst[r] >= 0 ? category[closing_inst[r]] : 0;
        const int64_t lo = offsets[r], hi = offsets[r + 1];
        if (lo == hi) continue;
        // D1: the first object hit; D2: the last hit of its instance
        const int32_t i1 = inst[lo];
        int64_t last = lo;
        for (int64_t h = lo + 1; h < hi; ++h)
            if (inst[h] == i1) last = h;
        D[0][r] = static_cast<float>(t[lo] * s);
        D[1][r] = static_cast<float>(t[last] * s);
        out_cat[r] = category[i1];
        out_inst[r] = i1;
        if (out_hit) out_hit[r] = lo, out_hit[n + r] = last;
        // D3: the first hit of another visible instance at or after D2; D4: its instance's last hit
        const double from = t[last] - same_instance;
        int64_t third = -1;
        for (int64_t h = lo + 1; h < hi; ++h)
            if (inst[h] != i1 && visible[inst[h]] && t[h] >= from) {
                third = h;
                break;
            }
        if (third < 0) continue;
        const int32_t i3 = inst[third];
        last = third;
        for (int64_t h = third + 1; h < hi; ++h)
            if (inst[h] == i3) last = h;
        D[2][r] = static_cast<float>(t[third] * s);
        D[3][r] = static_cast<float>(t[last] * s);
        out_cat[n + r] = category[i3];
        out_inst[n + r] = i3;
        if (out_hit) out_hit[2 * n + r] = third, out_hit[3 * n + r] = last;
    }
    Py_END_ALLOW_THREADS
    Py_RETURN_NONE;
}

// ------------------------------------------------------------------ depth -> triangles

// The edge rule of one pixel pair: |d_i - d_j| exceeds a x the footprint of the nearer
// pixel (sceneforge.depth_mesh._jumps, the same float64 operations).
inline bool jump(double di, double dj, double fi, double fj, double a) {
    double near = di <= dj ? fi : fj;
    near *= a;
    return std::fabs(di - dj) > near;
}

// The block corners 0 = (r, c), 1 = (r, c+1), 2 = (r+1, c), 3 = (r+1, c+1) and the four
// triangle shapes (0 2 1), (0 3 1), (0 2 3), (1 2 3), as in depth_mesh._TRIANGLES
constexpr int kBlockTriangles[4][3] = {{0, 2, 1}, {0, 3, 1}, {0, 2, 3}, {1, 2, 3}};
// The corners (bit k: corner k) a block's kept triangles use, by its shape bits
constexpr uint8_t kShapeCorners[16] = {0, 0b0111, 0b1011, 15, 0b1101, 15, 15, 15, 0b1110, 15, 15, 15, 15, 15, 15, 15};
// A block's shape bits spread into four 16-bit counters
constexpr uint64_t spread_shapes(unsigned e) {
    return (e & 1) | (uint64_t(e >> 1 & 1) << 16) | (uint64_t(e >> 2 & 1) << 32) | (uint64_t(e >> 3 & 1) << 48);
}
constexpr uint64_t kShapeCounters[16] = {
    spread_shapes(0),  spread_shapes(1),  spread_shapes(2),  spread_shapes(3),  spread_shapes(4),  spread_shapes(5),
    spread_shapes(6),  spread_shapes(7),  spread_shapes(8),  spread_shapes(9),  spread_shapes(10), spread_shapes(11),
    spread_shapes(12), spread_shapes(13), spread_shapes(14), spread_shapes(15)};

// Which pixels of a row of w depths d (footprints f) are vertices (finite), and the edge
// rule between each and its right neighbour.
void row_edges(const double* __restrict d, const double* __restrict f, int64_t w, double a, uint8_t* __restrict ok,
               uint8_t* __restrict across) {
    for (int64_t c = 0; c < w; ++c) ok[c] = std::fabs(d[c]) <= std::numeric_limits<double>::max();
    for (int64_t c = 0; c + 1 < w; ++c) across[c] = jump(d[c], d[c + 1], f[c], f[c + 1], a);
}

// One row of 2x2 blocks between pixel rows 0 and 1 of w pixels (depths d, footprints f,
// row_edges ok and across h): the shapes each block keeps (bit s: shape s) into `row`, their
// counts added to `count`, and into `up` and `down` the corners by which the blocks below
// (row 0's pixels) and above (row 1's) use each pixel. The block rule and the edge rule
// without a branch (which diagonal splits a block is often noise): every edge rule of the
// block, then the shapes of its vertices, less those with an edge that jumps.
void block_row(const double* __restrict d0, const double* __restrict f0, const uint8_t* __restrict ok0,
               const uint8_t* __restrict h0, const double* __restrict d1, const double* __restrict f1,
               const uint8_t* __restrict ok1, const uint8_t* __restrict h1, int64_t w, double a, double diagonal_a,
               uint8_t* __restrict row, uint8_t* __restrict up, uint8_t* __restrict down, int64_t* count) {
    uint64_t counters = 0;  // 16 bits per shape, added to count every 65535 blocks
    int budget = 65535;
    unsigned left = 0;  // the corners block c - 1 uses
    for (int64_t c = 0; c + 1 < w; ++c) {
        const unsigned j01 = h0[c], j23 = h1[c];
        const unsigned j02 = jump(d0[c], d1[c], f0[c], f1[c], a);
        const unsigned j13 = jump(d0[c + 1], d1[c + 1], f0[c + 1], f1[c + 1], a);
        const unsigned j03 = jump(d0[c], d1[c + 1], f0[c], f1[c + 1], diagonal_a);
        const unsigned j12 = jump(d0[c + 1], d1[c], f0[c + 1], f1[c], diagonal_a);
        const bool along_03 = std::fabs(d0[c] - d1[c + 1]) < std::fabs(d0[c + 1] - d1[c]);
        const unsigned ok = ok0[c] | ok0[c + 1] << 1 | ok1[c] << 2 | ok1[c + 1] << 3;
        // four vertices: split along the diagonal whose corners differ less; three (corner
        // k missing): the triangle of those, shape 3 - k
        const unsigned missing = ~ok & 15u;
        const unsigned three = (missing & 1) << 3 | (missing & 2) << 1 | (missing & 4) >> 1 | (missing & 8) >> 3;
        const unsigned shapes = ok == 15 ? (along_03 ? 2u | 4u : 1u | 8u) : (missing & (missing - 1)) == 0 ? three : 0u;
        const unsigned jumps = (j01 | j02 | j12) | (j01 | j03 | j13) << 1 | (j02 | j03 | j23) << 2 | (j12 | j13 | j23) << 3;
        const unsigned e = shapes & ~jumps;
        row[c] = static_cast<uint8_t>(e);
        counters += kShapeCounters[e];
        if (--budget == 0) {
            for (int s = 0; s < 4; ++s) count[s] += static_cast<int64_t>(counters >> (16 * s) & 0xFFFF);
            counters = 0, budget = 65535;
        }
        const unsigned corners = kShapeCorners[e];
        up[c] = static_cast<uint8_t>((corners & 1) | (left & 2));
        down[c] = static_cast<uint8_t>((corners & 4) | (left & 8));
        left = corners;
    }
    up[w - 1] = static_cast<uint8_t>(left & 2);
    down[w - 1] = static_cast<uint8_t>(left & 8);
    for (int s = 0; s < 4; ++s) count[s] += static_cast<int64_t>(counters >> (16 * s) & 0xFFFF);
}

// grid_faces(depth (h,w) f8, footprint (h,w) f8, a, diagonal_a) -> bytearray (m,3) i8:
// sceneforge.depth_mesh.grid_faces in one pass per block shape, the same triangles in the
// same order (every triangle of the first shape, blocks in row-major order, then the
// second...). diagonal_a is a * sqrt(2) as Python computes it.
PyObject* grid_faces(PyObject*, PyObject* args) {
    PyObject *depth_o, *foot_o;
    Py_ssize_t h, w;
    double a, diagonal_a;
    if (!PyArg_ParseTuple(args, "OOnndd", &depth_o, &foot_o, &h, &w, &a, &diagonal_a)) return nullptr;
    Buffer bd, bf;
    if (h < 0 || w < 0 || !get_buffer(depth_o, bd, sizeof(double), h * w, "depth") ||
        !get_buffer(foot_o, bf, sizeof(double), h * w, "footprint"))
        return nullptr;
    const double* D = static_cast<const double*>(bd.view.buf);
    const double* P = static_cast<const double*>(bf.view.buf);
    // pass 1 decides every block (a bit per triangle shape it keeps), pass 2 writes the
    // faces straight into the result, shape by shape
    std::vector<uint8_t> shape_of(h >= 2 && w >= 2 ? (h - 1) * (w - 1) : 0);
    int64_t counts[4] = {0, 0, 0, 0};
    Py_BEGIN_ALLOW_THREADS
    if (h >= 2 && w >= 2) {
        // row_edges of rows r and r + 1; the corners block_row finds are not needed here
        std::vector<uint8_t> flags(6 * w);
        uint8_t *ok0 = flags.data(), *h0 = ok0 + w, *ok1 = h0 + w, *h1 = ok1 + w, *unused = h1 + w;
        row_edges(D, P, w, a, ok0, h0);
        for (Py_ssize_t r = 0; r + 1 < h; ++r) {
            row_edges(D + (r + 1) * w, P + (r + 1) * w, w, a, ok1, h1);
            block_row(D + r * w, P + r * w, ok0, h0, D + (r + 1) * w, P + (r + 1) * w, ok1, h1, w, a, diagonal_a,
                      &shape_of[r * (w - 1)], unused, unused + w, counts);
            std::swap(ok0, ok1);
            std::swap(h0, h1);
        }
    }
    Py_END_ALLOW_THREADS
    const int64_t m = counts[0] + counts[1] + counts[2] + counts[3];
    PyObject* out = PyByteArray_FromStringAndSize(nullptr, static_cast<Py_ssize_t>(3 * m * sizeof(int64_t)));
    if (!out) return nullptr;
    int64_t* faces = reinterpret_cast<int64_t*>(PyByteArray_AS_STRING(out));
    Py_BEGIN_ALLOW_THREADS
    const int64_t offset[4] = {0, 1, w, w + 1};
    int64_t* cursor[4];  // where the next triangle of each shape goes
    cursor[0] = faces;
    for (int s = 1; s < 4; ++s) cursor[s] = cursor[s - 1] + 3 * counts[s - 1];
    for (Py_ssize_t r = 0; r + 1 < h && m; ++r) {
        const uint8_t* row = shape_of.data() + r * (w - 1);
        for (Py_ssize_t c = 0; c + 1 < w; ++c) {
            const uint8_t emit = row[c];
            if (!emit) continue;
            const int64_t top_left = r * w + c;
            for (int s = 0; s < 4; ++s) {
                if (!(emit & (1 << s))) continue;
                for (int v = 0; v < 3; ++v) *cursor[s]++ = top_left + offset[kBlockTriangles[s][v]];
            }
        }
    }
    Py_END_ALLOW_THREADS
    return out;
}

// compact_faces(faces (m,3) i8, n_pixels) -> (used (k,) i8, faces (m,3) i8) bytearrays: the
// pixels the faces use, ascending, and the faces renumbered to index them
// (sceneforge.depth_mesh.compact without the points).
PyObject* compact_faces(PyObject*, PyObject* args) {
    PyObject* faces_o;
    Py_ssize_t n;
    if (!PyArg_ParseTuple(args, "On", &faces_o, &n)) return nullptr;
    Buffer bf;
    if (n < 0 || !get_buffer(faces_o, bf, 3 * sizeof(int64_t), -1, "faces")) return nullptr;
    const int64_t* F = static_cast<const int64_t*>(bf.view.buf);
    const Py_ssize_t m3 = bf.view.len / static_cast<Py_ssize_t>(sizeof(int64_t));
    for (Py_ssize_t i = 0; i < m3; ++i)
        if (F[i] < 0 || F[i] >= n) {
            PyErr_SetString(PyExc_IndexError, "compact_faces: a face corner outside the pixels");
            return nullptr;
        }
    std::vector<int64_t> renumber(n, 0);
    for (Py_ssize_t i = 0; i < m3; ++i) renumber[F[i]] = 1;
    int64_t k = 0;
    for (Py_ssize_t p = 0; p < n; ++p) renumber[p] = renumber[p] ? k++ : -1;
    PyObject* used_b = PyByteArray_FromStringAndSize(nullptr, static_cast<Py_ssize_t>(k * sizeof(int64_t)));
    PyObject* faces_b = PyByteArray_FromStringAndSize(nullptr, static_cast<Py_ssize_t>(m3 * sizeof(int64_t)));
    if (!used_b || !faces_b) {
        Py_XDECREF(used_b);
        Py_XDECREF(faces_b);
        return nullptr;
    }
    int64_t* used = reinterpret_cast<int64_t*>(PyByteArray_AS_STRING(used_b));
    int64_t* out = reinterpret_cast<int64_t*>(PyByteArray_AS_STRING(faces_b));
    for (Py_ssize_t p = 0; p < n; ++p)
        if (renumber[p] >= 0) used[renumber[p]] = p;
    for (Py_ssize_t i = 0; i < m3; ++i) out[i] = renumber[F[i]];
    return Py_BuildValue("(NN)", used_b, faces_b);
}

// ------------------------------------------------------------------ depth -> envelope surface

// One element of `x @ M.T` as numpy's float64 matmul computes it for (n, 3) @ (3, 3)
// (OpenBLAS's kernels): the sum starts at +0 and takes the three products by fused
// multiply-adds in k order. A zero is then +0 whatever the signs, where a0 * x0 first would
// leave -0: only a -0 added after would show it.
__attribute__((always_inline)) inline double blas_row3(double a0, double a1, double a2, double x0, double x1, double x2) {
    return std::fma(a2, x2, std::fma(a1, x1, std::fma(a0, x0, 0.0)));
}

// The world points of the pixels in [begin, end) the surface uses (up | down), in pixel
// order from `out`: sceneforge.depth_mesh.perspective_points' (rays * depth) @ R.T + T with
// depth = t * scale. Compiled twice like vertex_codes_loop: the same bits either way.
__attribute__((always_inline)) inline void surface_points_loop(const double* t, const double* scale,
                                                               const double* rays, const double* R, const double* T,
                                                               const uint8_t* up, const uint8_t* down, int64_t begin,
                                                               int64_t end, double* out) {
    for (int64_t p = begin; p < end; ++p) {
        if (!(up[p] | down[p])) continue;
        const double depth = t[p] * scale[p];
        const double x0 = rays[3 * p] * depth, x1 = rays[3 * p + 1] * depth, x2 = rays[3 * p + 2] * depth;
        for (int j = 0; j < 3; ++j) *out++ = blas_row3(R[3 * j], R[3 * j + 1], R[3 * j + 2], x0, x1, x2) + T[j];
    }
}

#if defined(__x86_64__) && defined(__GNUC__)
__attribute__((target("fma"))) void surface_points_fma(const double* t, const double* scale, const double* rays,
                                                        const double* R, const double* T, const uint8_t* up,
                                                        const uint8_t* down, int64_t begin, int64_t end, double* out) {
    surface_points_loop(t, scale, rays, R, T, up, down, begin, end, out);
}
#endif

void surface_points_plain(const double* t, const double* scale, const double* rays, const double* R, const double* T,
                          const uint8_t* up, const uint8_t* down, int64_t begin, int64_t end, double* out) {
    surface_points_loop(t, scale, rays, R, T, up, down, begin, end, out);
}

// depth_surface(t (n,) f8, scale (n,) f8, label (n,) i4, rays (n,3) f8, rot (3,3) f8,
//               translation (3,) f8, h, w, fx, a, diagonal_a, threads)
//   -> (vertices (k,3) f8, faces (m,3) i4, label (m,) i4) bytearrays
//
// sceneforge.depth_mesh.depth_surface: what grid_faces, perspective_points and compact
// make of the depth t * scale (footprint depth / fx), the faces as int32 and each face's
// label that of its first corner pixel, every output written once and no int64 face
// array. Pixel rows in chunks, four passes: the blocks' shapes and the pixels they use
// (depth and footprint computed row by row, elementwise as numpy does), then the vertices
// in pixel order, then the faces (shape by shape, blocks in row-major order). Each chunk's
// place in the outputs follows from the counts of the chunks before it, so the arrays do
// not depend on `threads`.
PyObject* depth_surface(PyObject*, PyObject* args) {
    PyObject *to, *so, *lo, *ro, *rto, *tro;
    Py_ssize_t h, w;
    double fx, a, diagonal_a;
    int threads;
    if (!PyArg_ParseTuple(args, "OOOOOOnndddi", &to, &so, &lo, &ro, &rto, &tro, &h, &w, &fx, &a, &diagonal_a,
                          &threads))
        return nullptr;
    if (h < 0 || w < 0 || h * w > std::numeric_limits<int32_t>::max()) {
        PyErr_SetString(PyExc_ValueError, "depth_surface: h and w must be >= 0, h * w below 2**31");
        return nullptr;
    }
    const int64_t n = static_cast<int64_t>(h) * w;
    Buffer bt, bs, bl, br, brt, btr;
    if (!get_buffer(to, bt, sizeof(double), n, "t") || !get_buffer(so, bs, sizeof(double), n, "scale") ||
        !get_buffer(lo, bl, sizeof(int32_t), n, "label") || !get_buffer(ro, br, 3 * sizeof(double), n, "rays") ||
        !get_buffer(rto, brt, sizeof(double), 9, "rot") || !get_buffer(tro, btr, sizeof(double), 3, "translation"))
        return nullptr;
    const double* t = static_cast<const double*>(bt.view.buf);
    const double* scale = static_cast<const double*>(bs.view.buf);
    const int32_t* label = static_cast<const int32_t*>(bl.view.buf);
    const double* rays = static_cast<const double*>(br.view.buf);
    const double* R = static_cast<const double*>(brt.view.buf);
    const double* T = static_cast<const double*>(btr.view.buf);
    const bool blocks = h >= 2 && w >= 2;
    const int64_t bw = blocks ? w - 1 : 0, bh = blocks ? h - 1 : 0;
    // chunks of block rows, about 16k blocks each; chunk k's pixels are the rows its
    // blocks start in, and the image's last row for the last chunk
    const int64_t rows = std::max<int64_t>(1, 16384 / std::max<int64_t>(1, w));
    const int64_t n_chunks = blocks ? (bh + rows - 1) / rows : 0;
    auto first_row = [&](int64_t k) { return std::min(k * rows, bh); };
    auto pixel_end = [&](int64_t k) { return k + 1 == n_chunks ? n : first_row(k + 1) * w; };
    // emit: the shapes each block keeps; up, down: the corners by which the blocks below
    // and above each pixel use it (zero in the first and last rows)
    std::vector<uint8_t> emit(bh * bw), up(blocks ? n : 0), down(blocks ? n : 0);
    std::vector<int64_t> shape_count(4 * n_chunks), used_count(n_chunks);
    std::vector<int32_t> number(blocks ? n : 0);  // of each used pixel's vertex
    auto count_used = [&](int64_t r) {
        int64_t count = 0;
        for (int64_t p = r * w; p < (r + 1) * w; ++p) count += (up[p] | down[p]) != 0;
        return count;
    };
    Py_BEGIN_ALLOW_THREADS
    parallel_blocks(n_chunks, threads, [&](int64_t k) {
        // pixel rows r and r + 1: depth, footprint, row_edges
        std::vector<double> values(4 * w);
        std::vector<uint8_t> flags(4 * w);
        double *d0 = values.data(), *f0 = d0 + w, *d1 = f0 + w, *f1 = d1 + w;
        uint8_t *ok0 = flags.data(), *h0 = ok0 + w, *ok1 = h0 + w, *h1 = ok1 + w;
        auto fill = [&](int64_t r, double* d, double* f, uint8_t* ok, uint8_t* across) {
            for (int64_t c = 0; c < w; ++c) {
                d[c] = t[r * w + c] * scale[r * w + c];
                f[c] = d[c] / fx;
            }
            row_edges(d, f, w, a, ok, across);
        };
        int64_t* count = &shape_count[4 * k];
        int64_t n_used = 0;
        fill(first_row(k), d0, f0, ok0, h0);
        for (int64_t r = first_row(k); r < first_row(k + 1); ++r) {
            fill(r + 1, d1, f1, ok1, h1);
            block_row(d0, f0, ok0, h0, d1, f1, ok1, h1, w, a, diagonal_a, &emit[r * bw], &up[r * w],
                      &down[(r + 1) * w], count);
            // pixel row r is complete unless the chunk before has the blocks above it (then
            // it is counted below); the image's last row has no blocks below
            if (r > first_row(k)) n_used += count_used(r);
            if (r + 1 == bh) n_used += count_used(r + 1);
            std::swap(d0, d1);
            std::swap(f0, f1);
            std::swap(ok0, ok1);
            std::swap(h0, h1);
        }
        used_count[k] = n_used;
    });
    for (int64_t k = 0; k < n_chunks; ++k) used_count[k] += count_used(first_row(k));
    Py_END_ALLOW_THREADS
    // where each chunk's vertices, and its triangles of each shape, begin
    std::vector<int64_t> vertex_at(n_chunks + 1, 0), face_at(4 * n_chunks);
    int64_t m = 0;
    for (int64_t k = 0; k < n_chunks; ++k) vertex_at[k + 1] = vertex_at[k] + used_count[k];
    for (int s = 0; s < 4; ++s)
        for (int64_t k = 0; k < n_chunks; ++k) {
            face_at[4 * k + s] = m;
            m += shape_count[4 * k + s];
        }
    PyObject* vertices_b = PyByteArray_FromStringAndSize(nullptr, static_cast<Py_ssize_t>(3 * vertex_at[n_chunks] * sizeof(double)));
    PyObject* faces_b = PyByteArray_FromStringAndSize(nullptr, static_cast<Py_ssize_t>(3 * m * sizeof(int32_t)));
    PyObject* label_b = PyByteArray_FromStringAndSize(nullptr, static_cast<Py_ssize_t>(m * sizeof(int32_t)));
    if (!vertices_b || !faces_b || !label_b) {
        Py_XDECREF(vertices_b);
        Py_XDECREF(faces_b);
        Py_XDECREF(label_b);
        return nullptr;
    }
    double* V = reinterpret_cast<double*>(PyByteArray_AS_STRING(vertices_b));
    int32_t* F = reinterpret_cast<int32_t*>(PyByteArray_AS_STRING(faces_b));
    int32_t* L = reinterpret_cast<int32_t*>(PyByteArray_AS_STRING(label_b));
    Py_BEGIN_ALLOW_THREADS
#if defined(__x86_64__) && defined(__GNUC__)
    const bool fma = __builtin_cpu_supports("fma");
#endif
    parallel_blocks(n_chunks, threads, [&](int64_t k) {
        const int64_t begin = first_row(k) * w, end = pixel_end(k);
        int32_t next = static_cast<int32_t>(vertex_at[k]);
        for (int64_t p = begin; p < end; ++p)
            if (up[p] | down[p]) number[p] = next++;
        double* out = V + 3 * vertex_at[k];
#if defined(__x86_64__) && defined(__GNUC__)
        if (fma) surface_points_fma(t, scale, rays, R, T, up.data(), down.data(), begin, end, out);
        else
#endif
            surface_points_plain(t, scale, rays, R, T, up.data(), down.data(), begin, end, out);
    });
    parallel_blocks(n_chunks, threads, [&](int64_t k) {
        int64_t at[4];  // where chunk k's next triangle of each shape goes
        for (int s = 0; s < 4; ++s) at[s] = face_at[4 * k + s];
        // A block keeps shapes of one diagonal's pair only, 0 and 3 or 1 and 2: both of the
        // pair are written for every block, one it does not keep into a scratch face, with
        // no branch on the diagonal.
        int32_t scratch[4];
        for (int64_t r = first_row(k); r < first_row(k + 1); ++r)
            for (int64_t c = 0; c < bw; ++c) {
                const unsigned e = emit[r * bw + c];
                if (!e) continue;
                const int64_t p = r * w + c;
                const int32_t n0 = number[p], n1 = number[p + 1], n2 = number[p + w], n3 = number[p + w + 1];
                const bool split_03 = (e & 6) != 0;
                // (0 2 1) or (0 3 1), then (1 2 3) or (0 2 3)
                const int s0 = split_03 ? 1 : 0, s1 = split_03 ? 2 : 3;
                const unsigned keep0 = e >> s0 & 1, keep1 = e >> s1 & 1;
                int32_t* face = keep0 ? F + 3 * at[s0] : scratch;
                face[0] = n0, face[1] = split_03 ? n3 : n2, face[2] = n1;
                *(keep0 ? L + at[s0] : scratch + 3) = label[p];
                at[s0] += keep0;
                face = keep1 ? F + 3 * at[s1] : scratch;
                face[0] = split_03 ? n0 : n1, face[1] = n2, face[2] = n3;
                *(keep1 ? L + at[s1] : scratch + 3) = label[split_03 ? p : p + 1];
                at[s1] += keep1;
            }
    });
    Py_END_ALLOW_THREADS
    return Py_BuildValue("(NNN)", vertices_b, faces_b, label_b);
}

// ------------------------------------------------------------------ frustum: settling faces

// numpy's float64 -> int64 cast (x86's cvttsd2si): truncation, INT64_MIN where the value
// is NaN or out of range (the vertices _project gives garbage pixels: behind the camera)
__attribute__((always_inline)) inline int64_t numpy_int64(double x) {
    if (!(x >= -9.2233720368547758e18 && x < 9.2233720368547758e18)) return std::numeric_limits<int64_t>::min();
    return static_cast<int64_t>(x);
}


// The loop of vertex_codes. It is compiled twice, inlined into a function for CPUs with FMA
// instructions (std::fma one instruction) and into one for those without (a libm call):
// the same bits either way.
__attribute__((always_inline)) inline void vertex_codes_loop(
    const double* V, const double* P, const double* R, const double* C, const double* L, double fx, double skew,
    double cx, double fy, double cy, Py_ssize_t width, Py_ssize_t height, double tolerance, Py_ssize_t n,
    uint8_t* code) {
    const double border_u = static_cast<double>(width - 1), border_v = static_cast<double>(height - 1);
    const uint64_t last = static_cast<uint64_t>(width * height - 1);
    for (Py_ssize_t i = 0; i < n; ++i) {
        const double* p = V + 3 * i;
        uint8_t bits = 0;
        for (int k = 0; k < 5; ++k) {
            const double* q = P + 4 * k;
            double d = blas_row3(q[0], q[1], q[2], p[0], p[1], p[2]);
            d += q[3];
            bits |= static_cast<uint8_t>(d >= -tolerance) << k;
        }
        // the camera frame: (p - centre) @ rot, i.e. rot.T @ (p - centre)
        const double x0 = p[0] - C[0], x1 = p[1] - C[1], x2 = p[2] - C[2];
        const double x = blas_row3(R[0], R[3], R[6], x0, x1, x2);
        const double y = blas_row3(R[1], R[4], R[7], x0, x1, x2);
        const double z = blas_row3(R[2], R[5], R[8], x0, x1, x2);
        double u = fx * x;
        if (skew != 0.0) u += skew * y;
        u /= z;
        u += cx;
        double v = fy * y;
        v /= z;
        v += cy;
        // np.maximum / np.minimum propagate NaN
        if (!std::isnan(u)) u = std::min(std::max(u, 0.0), border_u);
        if (!std::isnan(v)) v = std::min(std::max(v, 0.0), border_v);
        // pixel v * width + u in int64 (wrapping, as numpy's), then take(mode="clip")
        const uint64_t flat = static_cast<uint64_t>(numpy_int64(v)) * static_cast<uint64_t>(width) +
                              static_cast<uint64_t>(numpy_int64(u));
        const int64_t signed_flat = static_cast<int64_t>(flat);
        const uint64_t pixel = signed_flat < 0 ? 0 : std::min(static_cast<uint64_t>(signed_flat), last);
        bits |= static_cast<uint8_t>(!(z > L[pixel])) << 5;
        code[i] = bits;
    }
}

#if defined(__x86_64__) && defined(__GNUC__)
__attribute__((target("fma"))) void vertex_codes_fma(const double* V, const double* P, const double* R,
                                                      const double* C, const double* L, double fx, double skew,
                                                      double cx, double fy, double cy, Py_ssize_t width,
                                                      Py_ssize_t height, double tolerance, Py_ssize_t n,
                                                      uint8_t* code) {
    vertex_codes_loop(V, P, R, C, L, fx, skew, cx, fy, cy, width, height, tolerance, n, code);
}
#endif

void vertex_codes_plain(const double* V, const double* P, const double* R, const double* C, const double* L,
                        double fx, double skew, double cx, double fy, double cy, Py_ssize_t width,
                        Py_ssize_t height, double tolerance, Py_ssize_t n, uint8_t* code) {
    vertex_codes_loop(V, P, R, C, L, fx, skew, cx, fy, cy, width, height, tolerance, n, code);
}

// vertex_codes(vertices (n,3) f8, planes (5,4) f8, rot (3,3) f8, centre (3,) f8, fx, skew,
//              cx, fy, cy, width, height, limit (height*width,) f8, tolerance) -> bytearray
//              (n,) u8: sceneforge.frustum._vertex_codes, bit p inside plane p within the
//              tolerance, bit 5 not behind the envelope (the same float64 operations)
PyObject* vertex_codes(PyObject*, PyObject* args) {
    PyObject *vo, *po, *ro, *co, *lo;
    double fx, skew, cx, fy, cy, tolerance;
    Py_ssize_t width, height;
    if (!PyArg_ParseTuple(args, "OOOOdddddnnOd", &vo, &po, &ro, &co, &fx, &skew, &cx, &fy, &cy, &width, &height,
                          &lo, &tolerance))
        return nullptr;
    Buffer bv, bp, br, bc, bl;
    if (width < 1 || height < 1 || !get_buffer(vo, bv, 3 * sizeof(double), -1, "vertices") ||
        !get_buffer(po, bp, sizeof(double), 20, "planes") || !get_buffer(ro, br, sizeof(double), 9, "rot") ||
        !get_buffer(co, bc, sizeof(double), 3, "centre") ||
        !get_buffer(lo, bl, sizeof(double), width * height, "limit"))
        return nullptr;
    const double* V = static_cast<const double*>(bv.view.buf);
    const double* P = static_cast<const double*>(bp.view.buf);
    const double* R = static_cast<const double*>(br.view.buf);
    const double* C = static_cast<const double*>(bc.view.buf);
    const double* L = static_cast<const double*>(bl.view.buf);
    const Py_ssize_t n = bv.view.len / static_cast<Py_ssize_t>(3 * sizeof(double));
    PyObject* out = PyByteArray_FromStringAndSize(nullptr, n);
    if (!out) return nullptr;
    uint8_t* code = reinterpret_cast<uint8_t*>(PyByteArray_AS_STRING(out));
    Py_BEGIN_ALLOW_THREADS
#if defined(__x86_64__) && defined(__GNUC__)
    if (__builtin_cpu_supports("fma"))
        vertex_codes_fma(V, P, R, C, L, fx, skew, cx, fy, cy, width, height, tolerance, n, code);
    else
#endif
        vertex_codes_plain(V, P, R, C, L, fx, skew, cx, fy, cy, width, height, tolerance, n, code);
    Py_END_ALLOW_THREADS
    return out;
}

// face_classes(code (n,) u8, corners (m,3) i8) -> (kept, hidden, cross) i8 bytearrays:
// the faces every corner of which is inside every plane and in front of the envelope, those
// inside every plane with a corner behind, and those inside each plane at some corner but
// outside some plane at some corner (sceneforge.frustum._face_classes)
PyObject* face_classes(PyObject*, PyObject* args) {
    PyObject *co, *fo;
    if (!PyArg_ParseTuple(args, "OO", &co, &fo)) return nullptr;
    Buffer bc, bf;
    if (!get_buffer(co, bc, 1, -1, "code") || !get_buffer(fo, bf, 3 * sizeof(int64_t), -1, "corners")) return nullptr;
    const uint8_t* code = static_cast<const uint8_t*>(bc.view.buf);
    const int64_t* F = static_cast<const int64_t*>(bf.view.buf);
    const Py_ssize_t n = bc.view.len, m = bf.view.len / static_cast<Py_ssize_t>(3 * sizeof(int64_t));
    for (Py_ssize_t i = 0; i < 3 * m; ++i)
        if (F[i] < 0 || F[i] >= n) {
            PyErr_SetString(PyExc_IndexError, "face_classes: a face corner outside the vertices");
            return nullptr;
        }
    // pass 1: each face's class (0 kept, 1 hidden, 2 cross, 3 none); pass 2 writes them
    std::vector<uint8_t> cls(m);
    size_t count[4] = {0, 0, 0, 0};
    Py_BEGIN_ALLOW_THREADS
    constexpr uint8_t inside = 0x1F, front = 0x20;
    for (Py_ssize_t f = 0; f < m; ++f) {
        const uint8_t a = code[F[3 * f]], b = code[F[3 * f + 1]], c = code[F[3 * f + 2]];
        const uint8_t every = a & b & c, some = a | b | c;
        const uint8_t k = every == (inside | front) ? 0
                          : every == inside          ? 1
                          : ((some & inside) == inside && (every & inside) != inside) ? 2
                                                                                     : 3;
        cls[f] = k;
        ++count[k];
    }
    Py_END_ALLOW_THREADS
    PyObject* out[3];
    int64_t* cursor[3];
    for (int k = 0; k < 3; ++k) {
        out[k] = PyByteArray_FromStringAndSize(nullptr, static_cast<Py_ssize_t>(count[k] * sizeof(int64_t)));
        if (!out[k]) {
            for (int j = 0; j < k; ++j) Py_DECREF(out[j]);
            return nullptr;
        }
        cursor[k] = reinterpret_cast<int64_t*>(PyByteArray_AS_STRING(out[k]));
    }
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t f = 0; f < m; ++f)
        if (cls[f] < 3) *cursor[cls[f]]++ = f;
    Py_END_ALLOW_THREADS
    return Py_BuildValue("(NNN)", out[0], out[1], out[2]);
}

// weld_faces(corners (m,3) i8, kept (k,) i8, tail (p,3) i8, n_vertices) -> (used (u,) i8,
// faces (k+p,3) i4) bytearrays: the faces corners[kept] then tail, as indices into the
// vertices they use (ascending) -- the end of sceneforge.frustum._weld_pieces
PyObject* weld_faces(PyObject*, PyObject* args) {
    PyObject *co, *ko, *to;
    Py_ssize_t n;
    if (!PyArg_ParseTuple(args, "OOOn", &co, &ko, &to, &n)) return nullptr;
    Buffer bc, bk, bt;
    if (n < 0 || !get_buffer(co, bc, 3 * sizeof(int64_t), -1, "corners") ||
        !get_buffer(ko, bk, sizeof(int64_t), -1, "kept") || !get_buffer(to, bt, 3 * sizeof(int64_t), -1, "tail"))
        return nullptr;
    const int64_t* F = static_cast<const int64_t*>(bc.view.buf);
    const int64_t* K = static_cast<const int64_t*>(bk.view.buf);
    const int64_t* T = static_cast<const int64_t*>(bt.view.buf);
    const Py_ssize_t m = bc.view.len / static_cast<Py_ssize_t>(3 * sizeof(int64_t));
    const Py_ssize_t k = bk.view.len / static_cast<Py_ssize_t>(sizeof(int64_t));
    const Py_ssize_t p3 = bt.view.len / static_cast<Py_ssize_t>(sizeof(int64_t));
    for (Py_ssize_t i = 0; i < k; ++i)
        if (K[i] < 0 || K[i] >= m) {
            PyErr_SetString(PyExc_IndexError, "weld_faces: a kept face outside the faces");
            return nullptr;
        }
    std::vector<int32_t> renumber(n, 0);
    bool bad = false;
    auto mark = [&](int64_t v) {
        if (v < 0 || v >= n) bad = true;
        else renumber[v] = 1;
    };
    for (Py_ssize_t i = 0; i < k; ++i)
        for (int a = 0; a < 3; ++a) mark(F[3 * K[i] + a]);
    for (Py_ssize_t i = 0; i < p3; ++i) mark(T[i]);
    if (bad) {
        PyErr_SetString(PyExc_IndexError, "weld_faces: a face corner outside the vertices");
        return nullptr;
    }
    int64_t u = 0;
    for (Py_ssize_t v = 0; v < n; ++v) renumber[v] = renumber[v] ? static_cast<int32_t>(u++) : -1;
    PyObject* used_b = PyByteArray_FromStringAndSize(nullptr, static_cast<Py_ssize_t>(u * sizeof(int64_t)));
    PyObject* faces_b = PyByteArray_FromStringAndSize(nullptr, static_cast<Py_ssize_t>((3 * k + p3) * sizeof(int32_t)));
    if (!used_b || !faces_b) {
        Py_XDECREF(used_b);
        Py_XDECREF(faces_b);
        return nullptr;
    }
    int64_t* used = reinterpret_cast<int64_t*>(PyByteArray_AS_STRING(used_b));
    int32_t* out = reinterpret_cast<int32_t*>(PyByteArray_AS_STRING(faces_b));
    for (Py_ssize_t v = 0; v < n; ++v)
        if (renumber[v] >= 0) used[renumber[v]] = v;
    for (Py_ssize_t i = 0; i < k; ++i)
        for (int a = 0; a < 3; ++a) *out++ = renumber[F[3 * K[i] + a]];
    for (Py_ssize_t i = 0; i < p3; ++i) *out++ = renumber[T[i]];
    return Py_BuildValue("(NN)", used_b, faces_b);
}

PyMethodDef module_methods[] = {
    {"layer_rules", layer_rules, METH_VARARGS,
     "layer_rules(offsets, t, instance, closing_t, closing_instance, depth_scale, category, same_instance, "
     "depth_out, category_out, instance_out[, hit_out]): docs/spec.md §4.2-§4.3, as sceneforge.layers.apply_rules"},
    {"grid_faces", grid_faces, METH_VARARGS,
     "grid_faces(depth, footprint, h, w, a, diagonal_a) -> (m, 3) int64 faces (bytes), as "
     "sceneforge.depth_mesh.grid_faces"},
    {"vertex_codes", vertex_codes, METH_VARARGS,
     "vertex_codes(vertices, planes, rot, centre, fx, skew, cx, fy, cy, width, height, limit, tolerance) -> "
     "(n,) uint8 (bytes), as sceneforge.frustum._vertex_codes"},
    {"face_classes", face_classes, METH_VARARGS,
     "face_classes(code, corners) -> (kept, hidden, cross) int64 (bytes), as sceneforge.frustum._face_classes"},
    {"weld_faces", weld_faces, METH_VARARGS,
     "weld_faces(corners, kept, tail, n_vertices) -> (used int64, faces int32) (bytes), as the end of "
     "sceneforge.frustum._weld_pieces"},
    {"compact_faces", compact_faces, METH_VARARGS,
     "compact_faces(faces, n_pixels) -> (used pixels, renumbered faces) int64 (bytes), as "
     "sceneforge.depth_mesh.compact"},
    {"depth_surface", depth_surface, METH_VARARGS,
     "depth_surface(t, scale, label, rays, rot, translation, h, w, fx, a, diagonal_a, threads) -> (vertices "
     "float64, faces int32, label int32) (bytes), as sceneforge.depth_mesh.depth_surface"},
    {nullptr, nullptr, 0, nullptr},
};

PyMethodDef engine_methods[] = {
    {"add_scene", reinterpret_cast<PyCFunction>(engine_add_scene), METH_VARARGS,
     "add_scene(members, first_vertex) -> scene id"},
    {"first", reinterpret_cast<PyCFunction>(engine_first), METH_VARARGS,
     "first(scene_ids, n, origins, directions) -> nearest face per ray (int64 bytes)"},
    {"closing", reinterpret_cast<PyCFunction>(engine_closing), METH_VARARGS,
     "closing(scene_ids, n, origins, directions, near) -> closing hit arrays (bytes)"},
    {"collect", reinterpret_cast<PyCFunction>(engine_collect), METH_VARARGS,
     "collect(scene_ids, n, origins, directions, cutoff, margin, same_instance, raw) -> hit arrays (bytes)"},
    {"nearest", reinterpret_cast<PyCFunction>(engine_nearest), METH_VARARGS,
     "nearest(scene_ids, n, origins, directions, k, spare, margin, same_instance, t_out, face_out, front_out) -> "
     "(longer, single): each ray's first k merged, sorted hits"},
    {"frontal_nearest", reinterpret_cast<PyCFunction>(engine_frontal_nearest), METH_VARARGS,
     "frontal_nearest(object_ids, closing_ids, objects, n, origins, directions, margin, same_instance, slack, k, "
     "spare, depth_scale, rotation, labels, depth_out, normal_out, instance_out, label_out, front_out) -> (hits, "
     "closing face, t, instance, triangle, front_facing, (longer, single)): the frontal query and nearest_surfaces "
     "in one traversal per ray"},
    {"nearest_surfaces", reinterpret_cast<PyCFunction>(engine_nearest_surfaces), METH_VARARGS,
     "nearest_surfaces(scene_ids, n, origins, directions, k, spare, margin, same_instance, depth_scale, rotation, "
     "labels, depth_out, normal_out, instance_out, label_out, front_out) -> (longer, single): the same hits as "
     "a view's layers"},
    {"closest", reinterpret_cast<PyCFunction>(engine_closest), METH_VARARGS,
     "closest(scene_ids, points) -> distance per point (float64 bytes)"},
    {nullptr, nullptr, 0, nullptr},
};

PyGetSetDef engine_getset[] = {
    {"packet", reinterpret_cast<getter>(engine_packet), nullptr, "rays per first-hit packet (1: ray by ray)", nullptr},
    {nullptr, nullptr, nullptr, nullptr, nullptr},
};

PyTypeObject EngineType = {PyVarObject_HEAD_INIT(nullptr, 0)};

PyModuleDef module_def = {PyModuleDef_HEAD_INIT, "_embree",
                          "Every hit of a ray in one Embree traversal; see sceneforge.raytrace.embree_backend.",
                          -1, module_methods};

}  // namespace

PyMODINIT_FUNC PyInit__embree(void) {
    EngineType.tp_name = "sceneforge.raytrace._embree.Engine";
    EngineType.tp_basicsize = sizeof(EngineObject);
    EngineType.tp_flags = Py_TPFLAGS_DEFAULT;
    EngineType.tp_doc = "Engine(threads, vertices, faces, instance, first_face, normal_xyz, offset, shift[, packet])";
    EngineType.tp_new = PyType_GenericNew;
    EngineType.tp_init = reinterpret_cast<initproc>(engine_init);
    EngineType.tp_dealloc = reinterpret_cast<destructor>(engine_dealloc);
    EngineType.tp_methods = engine_methods;
    EngineType.tp_getset = engine_getset;
    if (PyType_Ready(&EngineType) < 0) return nullptr;
    PyObject* m = PyModule_Create(&module_def);
    if (!m) return nullptr;
    Py_INCREF(&EngineType);
    if (PyModule_AddObject(m, "Engine", reinterpret_cast<PyObject*>(&EngineType)) < 0) {
        Py_DECREF(&EngineType);
        Py_DECREF(m);
        return nullptr;
    }
    // the float32 tie window of first hits, which sceneforge.conventions.tol.tie_window must round to
    if (PyModule_AddObject(m, "CANDIDATE_WINDOW", PyFloat_FromDouble(kCandidateWindow)) < 0) {
        Py_DECREF(m);
        return nullptr;
    }
    if (PyModule_AddStringConstant(m, "EMBREE_VERSION", RTC_VERSION_STRING) < 0) {
        Py_DECREF(m);
        return nullptr;
    }
    return m;
}
