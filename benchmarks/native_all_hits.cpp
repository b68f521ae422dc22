// The physical limit of sceneforge's ray work: plain Embree doing the same queries.
//
// bench_ground_truth.py writes the house and each view's queries to a file, compiles this
// program with the system compiler and runs it. Per query (a view's frontal rays, then its
// overhead rays) it does what a frontal query must at the least: a first-hit pass against
// the closing instances (from `near` on), in ray packets of the widest width the CPU runs
// natively, then ONE traversal per ray of the object instances up to the closing hit +
// slack, whose filter callback collects every hit; each ray's hits are sorted by distance
// and written out in CSR layout. A query without object instances (the envelope surface's
// rays) is its first-hit pass alone. No float64 distances, no merging, no layer rules, no
// second look at ties: only the traversals and the hit lists.
//
//   native_all_hits INPUT    prints: "<best seconds> <its CPU seconds> <hits> <rays>": the
//                            seconds for all the queries, from the round with the best wall
//                            time; the hits and rays of the queries with object instances
//
// INPUT (little-endian): int64 n_vertices, n_faces, n_instances, n_queries, rounds, threads;
// float32 vertices (n_vertices, 3); uint32 faces (n_faces, 3); int64 first_vertex and
// first_face (n_instances + 1 each); then per query: int64 n_rays; uint8 objects and
// closing masks (n_instances each); float32 near, slack; float32 rays (n_rays, 6).

#ifdef SF_EMBREE4
#include <embree4/rtcore.h>
#else
#include <embree3/rtcore.h>
#endif

#include <algorithm>
#include <atomic>
#include <chrono>
#include <ctime>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <limits>
#include <map>
#include <string>
#include <thread>
#include <vector>

#if RTC_VERSION_MAJOR >= 4
#define FILTER_FLAG RTC_SCENE_FLAG_FILTER_FUNCTION_IN_ARGUMENTS
typedef RTCRayQueryContext ContextBase;
#else
#define FILTER_FLAG RTC_SCENE_FLAG_CONTEXT_FILTER_FUNCTION
typedef RTCIntersectContext ContextBase;
#endif

struct Hit {
    float t;
    unsigned geom, prim;
};

struct Context {
    ContextBase base;
    std::vector<Hit>* out;
};

static void collect(const RTCFilterFunctionNArguments* args) {
    Context* c = reinterpret_cast<Context*>(args->context);
    for (unsigned i = 0; i < args->N; ++i) {
        if (args->valid[i] != -1) continue;
        c->out->push_back({RTCRayN_tfar(args->ray, args->N, i), RTCHitN_geomID(args->hit, args->N, i),
                           RTCHitN_primID(args->hit, args->N, i)});
        args->valid[i] = 0;
    }
}

// The nearest hit of rays lo..hi-1 from `near` on (tfar, geometry, primitive per ray,
// indexed from lo), K rays per rtcIntersectK packet, or one by one (K = 1).
template <int K, class RayHitK>
static void first_hits_k(RTCScene scene, const float* rays, int64_t lo, int64_t hi, float near, float* t,
                         unsigned* geom, unsigned* prim) {
    for (int64_t r0 = lo; r0 < hi; r0 += K) {
        const int lanes = static_cast<int>(std::min<int64_t>(K, hi - r0));
        alignas(64) int valid[K];
        RayHitK rh;
        for (int j = 0; j < K; ++j) {
            const float* ray = rays + 6 * (r0 + (j < lanes ? j : 0));
            valid[j] = j < lanes ? -1 : 0;
            rh.ray.org_x[j] = ray[0], rh.ray.org_y[j] = ray[1], rh.ray.org_z[j] = ray[2];
            rh.ray.dir_x[j] = ray[3], rh.ray.dir_y[j] = ray[4], rh.ray.dir_z[j] = ray[5];
            rh.ray.tnear[j] = near, rh.ray.tfar[j] = std::numeric_limits<float>::infinity();
            rh.ray.mask[j] = 0xFFFFFFFFu, rh.ray.flags[j] = 0, rh.ray.time[j] = 0, rh.ray.id[j] = 0;
            rh.hit.geomID[j] = RTC_INVALID_GEOMETRY_ID;
            rh.hit.instID[0][j] = RTC_INVALID_GEOMETRY_ID;
        }
#if RTC_VERSION_MAJOR >= 4
        RTCIntersectArguments args;
        rtcInitIntersectArguments(&args);
        args.flags = RTC_RAY_QUERY_FLAG_COHERENT;
        if constexpr (K == 16) rtcIntersect16(valid, scene, &rh, &args);
        else if constexpr (K == 8) rtcIntersect8(valid, scene, &rh, &args);
        else rtcIntersect4(valid, scene, &rh, &args);
#else
        RTCIntersectContext context;
        rtcInitIntersectContext(&context);
        context.flags = RTC_INTERSECT_CONTEXT_FLAG_COHERENT;
        if constexpr (K == 16) rtcIntersect16(valid, scene, &context, &rh);
        else if constexpr (K == 8) rtcIntersect8(valid, scene, &context, &rh);
        else rtcIntersect4(valid, scene, &context, &rh);
#endif
        for (int j = 0; j < lanes; ++j)
            t[r0 + j - lo] = rh.ray.tfar[j], geom[r0 + j - lo] = rh.hit.geomID[j], prim[r0 + j - lo] = rh.hit.primID[j];
    }
}

static void first_hits(int packet, RTCScene scene, const float* rays, int64_t lo, int64_t hi, float near, float* t,
                       unsigned* geom, unsigned* prim) {
    if (packet == 16) return first_hits_k<16, RTCRayHit16>(scene, rays, lo, hi, near, t, geom, prim);
    if (packet == 8) return first_hits_k<8, RTCRayHit8>(scene, rays, lo, hi, near, t, geom, prim);
    if (packet == 4) return first_hits_k<4, RTCRayHit4>(scene, rays, lo, hi, near, t, geom, prim);
    for (int64_t r = lo; r < hi; ++r) {
        const float* ray = rays + 6 * r;
        RTCRayHit rh;
        rh.ray.org_x = ray[0], rh.ray.org_y = ray[1], rh.ray.org_z = ray[2];
        rh.ray.dir_x = ray[3], rh.ray.dir_y = ray[4], rh.ray.dir_z = ray[5];
        rh.ray.tnear = near, rh.ray.tfar = std::numeric_limits<float>::infinity();
        rh.ray.mask = 0xFFFFFFFFu, rh.ray.flags = 0, rh.ray.time = 0, rh.ray.id = 0;
        rh.hit.geomID = RTC_INVALID_GEOMETRY_ID;
        rh.hit.instID[0] = RTC_INVALID_GEOMETRY_ID;
#if RTC_VERSION_MAJOR >= 4
        rtcIntersect1(scene, &rh);
#else
        RTCIntersectContext plain;
        rtcInitIntersectContext(&plain);
        rtcIntersect1(scene, &plain, &rh);
#endif
        t[r - lo] = rh.ray.tfar, geom[r - lo] = rh.hit.geomID, prim[r - lo] = rh.hit.primID;
    }
}

struct Query {
    std::vector<uint8_t> objects, closing;
    float near = 0, slack = 0;
    std::vector<float> rays;
    int64_t n = 0;
    RTCScene object_scene = nullptr, closing_scene = nullptr;
    bool first_only = false;  // no object instance: the closing hit is the query's answer
};

template <class T>
static void read(FILE* f, T* p, size_t n) {
    if (fread(p, sizeof(T), n, f) != n) {
        fprintf(stderr, "native_all_hits: short input\n");
        exit(2);
    }
}

int main(int argc, char** argv) {
    if (argc != 2) {
        fprintf(stderr, "usage: native_all_hits INPUT\n");
        return 2;
    }
    FILE* f = fopen(argv[1], "rb");
    if (!f) return 2;
    int64_t head[6];
    read(f, head, 6);
    const int64_t nv = head[0], nf = head[1], ni = head[2], nq = head[3], rounds = head[4], threads = head[5];
    std::vector<float> V(3 * nv);
    std::vector<uint32_t> F(3 * nf);
    std::vector<int64_t> fv(ni + 1), ff(ni + 1);
    read(f, V.data(), V.size());
    read(f, F.data(), F.size());
    read(f, fv.data(), fv.size());
    read(f, ff.data(), ff.size());
    std::vector<Query> queries(nq);
    for (auto& q : queries) {
        read(f, &q.n, 1);
        q.objects.resize(ni), q.closing.resize(ni);
        read(f, q.objects.data(), ni);
        read(f, q.closing.data(), ni);
        read(f, &q.near, 1);
        read(f, &q.slack, 1);
        q.rays.resize(6 * q.n);
        read(f, q.rays.data(), q.rays.size());
    }
    fclose(f);

    const std::string config = "threads=" + std::to_string(threads);
    RTCDevice device = rtcNewDevice(config.c_str());
    // first-hit passes in packets of the widest width the CPU runs natively (as sceneforge's
    // extension does); PACKET=1 in the environment traces them ray by ray
    const char* packet_env = getenv("PACKET");
    const int packet = packet_env ? atoi(packet_env)
                       : rtcGetDeviceProperty(device, RTC_DEVICE_PROPERTY_NATIVE_RAY16_SUPPORTED) ? 16
                       : rtcGetDeviceProperty(device, RTC_DEVICE_PROPERTY_NATIVE_RAY8_SUPPORTED)  ? 8
                       : rtcGetDeviceProperty(device, RTC_DEVICE_PROPERTY_NATIVE_RAY4_SUPPORTED)  ? 4
                                                                                                 : 1;
    std::map<std::vector<uint8_t>, RTCScene> scenes;  // one per instance subset, built once
    std::map<RTCScene, std::vector<int64_t>> first_face_of;  // per scene: each geometry's first face
    auto scene_of = [&](const std::vector<uint8_t>& mask) {
        auto it = scenes.find(mask);
        if (it != scenes.end()) return it->second;
        RTCScene s = rtcNewScene(device);
        rtcSetSceneFlags(s, static_cast<RTCSceneFlags>(RTC_SCENE_FLAG_ROBUST | FILTER_FLAG));
        for (int64_t i = 0; i < ni; ++i) {
            if (!mask[i]) continue;
            RTCGeometry g = rtcNewGeometry(device, RTC_GEOMETRY_TYPE_TRIANGLE);
            const int64_t n_v = fv[i + 1] - fv[i], n_f = ff[i + 1] - ff[i];
            float* vb = static_cast<float*>(
                rtcSetNewGeometryBuffer(g, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3, 12, n_v));
            unsigned* ib = static_cast<unsigned*>(
                rtcSetNewGeometryBuffer(g, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3, 12, n_f));
            std::memcpy(vb, V.data() + 3 * fv[i], 12 * n_v);
            for (int64_t k = 0; k < 3 * n_f; ++k) ib[k] = F[3 * ff[i] + k] - static_cast<unsigned>(fv[i]);
            rtcCommitGeometry(g);
            rtcAttachGeometry(s, g);
            rtcReleaseGeometry(g);
            first_face_of[s].push_back(ff[i]);
        }
        rtcCommitScene(s);
        scenes[mask] = s;
        return s;
    };
    for (auto& q : queries) {
        q.first_only = std::find(q.objects.begin(), q.objects.end(), 1) == q.objects.end();
        if (!q.first_only) q.object_scene = scene_of(q.objects);
        q.closing_scene = scene_of(q.closing);
    }

    const int64_t block = 512;
    double best = std::numeric_limits<double>::infinity(), best_cpu = 0;
    auto cpu_now = []() {
        timespec ts;
        clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &ts);
        return ts.tv_sec + 1e-9 * ts.tv_nsec;
    };
    int64_t total_hits = 0, total_rays = 0;
    for (int64_t round = 0; round < rounds; ++round) {
        int64_t hits_this_round = 0, rays_this_round = 0;
        const auto start = std::chrono::steady_clock::now();
        const double cpu_start = cpu_now();
        for (auto& q : queries) {
            const int64_t n_blocks = (q.n + block - 1) / block;
            std::vector<std::vector<Hit>> out(n_blocks);
            std::vector<std::vector<int64_t>> counts(n_blocks);
            std::atomic<int64_t> next{0};
            auto work = [&]() {
                std::vector<Hit> ray_hits;
                std::vector<float> cut(block);
                std::vector<unsigned> geom(block), prim(block);
                for (int64_t b; (b = next.fetch_add(1)) < n_blocks;) {
                    const int64_t lo = b * block, hi = std::min(q.n, lo + block);
                    counts[b].resize(hi - lo);
                    // the first-hit pass against the closing instances, in packets
                    first_hits(packet, q.closing_scene, q.rays.data(), lo, hi, q.near, cut.data(), geom.data(),
                               prim.data());
                    for (int64_t r = lo; r < hi; ++r) {
                        const bool hit = geom[r - lo] != RTC_INVALID_GEOMETRY_ID;
                        if (q.first_only) {
                            if (hit) out[b].push_back({cut[r - lo], geom[r - lo], prim[r - lo]});
                            counts[b][r - lo] = hit ? 1 : 0;
                            continue;
                        }
                        // then ONE traversal of the objects up to the closing hit + slack
                        const float* ray = q.rays.data() + 6 * r;
                        RTCRayHit rh;
                        rh.ray.org_x = ray[0], rh.ray.org_y = ray[1], rh.ray.org_z = ray[2];
                        rh.ray.dir_x = ray[3], rh.ray.dir_y = ray[4], rh.ray.dir_z = ray[5];
                        rh.ray.mask = 0xFFFFFFFFu, rh.ray.flags = 0, rh.ray.time = 0, rh.ray.id = 0;
                        rh.hit.instID[0] = RTC_INVALID_GEOMETRY_ID;
                        rh.ray.tnear = 0, rh.ray.tfar = hit ? cut[r - lo] + q.slack : cut[r - lo];
                        rh.hit.geomID = RTC_INVALID_GEOMETRY_ID;
                        ray_hits.clear();
                        Context c;
                        c.out = &ray_hits;
#if RTC_VERSION_MAJOR >= 4
                        rtcInitRayQueryContext(&c.base);
                        RTCIntersectArguments args;
                        rtcInitIntersectArguments(&args);
                        args.context = &c.base;
                        args.filter = collect;
                        args.flags = static_cast<RTCRayQueryFlags>(args.flags | RTC_RAY_QUERY_FLAG_INVOKE_ARGUMENT_FILTER);
                        rtcIntersect1(q.object_scene, &rh, &args);
#else
                        rtcInitIntersectContext(&c.base);
                        c.base.filter = collect;
                        rtcIntersect1(q.object_scene, &c.base, &rh);
#endif
                        std::sort(ray_hits.begin(), ray_hits.end(), [](const Hit& a, const Hit& b) { return a.t < b.t; });
                        out[b].insert(out[b].end(), ray_hits.begin(), ray_hits.end());
                        counts[b][r - lo] = static_cast<int64_t>(ray_hits.size());
                    }
                }
            };
            std::vector<std::thread> pool;
            for (int64_t t = 0; t < std::max<int64_t>(1, threads); ++t) pool.emplace_back(work);
            for (auto& t : pool) t.join();
            // the CSR arrays
            std::vector<int64_t> offsets(q.n + 1, 0);
            int64_t k = 0;
            for (int64_t b = 0; b < n_blocks; ++b) k += static_cast<int64_t>(out[b].size());
            std::vector<float> t_hit(k);
            std::vector<int64_t> face(k);
            k = 0;
            const std::vector<int64_t>& base = first_face_of[q.first_only ? q.closing_scene : q.object_scene];
            for (int64_t b = 0; b < n_blocks; ++b) {
                for (size_t j = 0; j < counts[b].size(); ++j) offsets[b * block + j + 1] = offsets[b * block + j] + counts[b][j];
                for (const Hit& h : out[b]) t_hit[k] = h.t, face[k] = base[h.geom] + h.prim, ++k;
            }
            if (!q.first_only) hits_this_round += k, rays_this_round += q.n;
        }
        const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
        if (seconds < best) best = seconds, best_cpu = cpu_now() - cpu_start;
        total_hits = hits_this_round, total_rays = rays_this_round;
    }
    printf("%.6f %.6f %lld %lld\n", best, best_cpu, static_cast<long long>(total_hits),
           static_cast<long long>(total_rays));
    for (auto& s : scenes) rtcReleaseScene(s.second);
    rtcReleaseDevice(device);
    return 0;
}
