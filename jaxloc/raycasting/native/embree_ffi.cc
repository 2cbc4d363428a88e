// jaxloc's native CPU ray engine: Embree 4 called from an XLA FFI handler, in native threads.
//
// The handler serves the custom-call target "jaxloc_embree_nearest" with the signature of the
// Python engine it replaces (jaxloc/raycasting/embree.py), so a program in JAX's persistent
// compilation cache runs with either:
//
//   operands  key (*L, 2) uint32          fingerprint of the map's triangles (the scene cache key)
//             triangles (*L, T, 3, 3) f32 the map, all-zero rows are padding (left out)
//             origins, directions (*L, R, 3) f32 (finite; unit directions)
//             valid (*L, R) bool          the other rays are not traced and miss
//   results   faces (*L, R) int32 map index of the nearest triangle, -1 on a miss
//             [t, u, v (*L, R) f32]       distance and barycentric weights, recomputed on the hit
//                                         triangle in double precision (values-only)
//             status (*L, 1) int32        0 done, 1 failed (the results are then not to be used)
//
// with size-1 leading axes where an operand is not batched (jax's "expand_dims" vmap method).
// Camera rays sharing an origin and pointing close together are traced as packets of 8 (of 4
// where the CPU has no 8-wide kernels; rtcIntersect8/4, coherent flag), any other ray alone
// (rtcIntersect1); a camera's raster of rays (row-major lines, found from the directions) is
// cast in tiles of 2 lines x 4 rays, so that a packet holds neighbours in both directions. The
// work is cut into pieces that a small pool of native threads and the calling thread take in
// turn; no GIL, no Python. Scenes (robust, watertight traversal, as the
// Python engine builds them) are kept in a bounded LRU cache.
// No floating-point mode is changed.
//
// Embree is not linked: jaxloc_native_init() loads the library that the embreex wheel ships.
#include <dlfcn.h>
#include <sched.h>

#include <algorithm>
#include <cmath>
#include <atomic>
#include <condition_variable>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <deque>
#include <functional>
#include <limits>
#include <list>
#include <memory>
#include <mutex>
#include <stdexcept>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "embree_api.h"
#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;
namespace rtc = jaxloc::embree;

namespace {

// ----------------------------------------------------------------------------------------------
// Embree, loaded at run time.

struct EmbreeApi {
  rtc::NewDeviceFn new_device = nullptr;
  rtc::GetDeviceErrorFn get_device_error = nullptr;
  rtc::GetDevicePropertyFn get_device_property = nullptr;
  rtc::NewSceneFn new_scene = nullptr;
  rtc::ReleaseSceneFn release_scene = nullptr;
  rtc::SetSceneFlagsFn set_scene_flags = nullptr;
  rtc::CommitSceneFn commit_scene = nullptr;
  rtc::NewGeometryFn new_geometry = nullptr;
  rtc::SetNewGeometryBufferFn set_new_geometry_buffer = nullptr;
  rtc::CommitGeometryFn commit_geometry = nullptr;
  rtc::AttachGeometryFn attach_geometry = nullptr;
  rtc::ReleaseGeometryFn release_geometry = nullptr;
  rtc::Intersect1Fn intersect1 = nullptr;
  rtc::IntersectPacketFn intersect4 = nullptr;
  rtc::IntersectPacketFn intersect8 = nullptr;
  rtc::IntersectPacketFn intersect16 = nullptr;
  rtc::Device device = nullptr;
  int packet_width = 1;  // 16, 8, 4, or 1 (single rays only)
};

EmbreeApi g_api;
std::mutex g_init_mutex;
bool g_ready = false;

template <typename Fn>
bool Find(void* library, const char* name, Fn* out, std::string* error) {
  *out = reinterpret_cast<Fn>(dlsym(library, name));
  if (*out == nullptr) *error = std::string("Embree has no ") + name;
  return *out != nullptr;
}

void CheckDevice(const char* what) {
  int code = g_api.get_device_error(g_api.device);
  if (code != rtc::kErrorNone) {
    throw std::runtime_error(std::string("Embree error ") + std::to_string(code) + " " + what);
  }
}

// ----------------------------------------------------------------------------------------------
// A pool of native threads. A job is a number of chunks; the caller queues it, works on it
// itself, and waits until the chunks the workers took are done. Jobs of concurrent callers queue
// up and are served first come, first served.

struct Job {
  std::function<void(int64_t)> body;
  int64_t chunks = 0;
  std::atomic<int64_t> next{0};
  std::atomic<int64_t> done{0};
  std::atomic<bool> failed{false};
  std::string error;  // the first failure (written once, by whoever set `failed`)
  std::mutex mutex;
  std::condition_variable finished;

  // Run chunks until none is left; whether this thread ran any.
  void Work() {
    for (int64_t i = next.fetch_add(1); i < chunks; i = next.fetch_add(1)) {
      try {
        body(i);
      } catch (const std::exception& e) {
        if (!failed.exchange(true)) error = e.what();
      }
      if (done.fetch_add(1) + 1 == chunks) {
        std::lock_guard<std::mutex> lock(mutex);
        finished.notify_all();
      }
    }
  }
};

class Pool {
 public:
  explicit Pool(int workers) {
    for (int i = 0; i < workers; ++i) threads_.emplace_back([this] { Serve(); });
  }
  int size() const { return static_cast<int>(threads_.size()) + 1; }  // the caller works too

  // Run body(0..chunks-1) on the pool and the calling thread; rethrows the first failure.
  void Run(int64_t chunks, std::function<void(int64_t)> body) {
    auto job = std::make_shared<Job>();
    job->body = std::move(body);
    job->chunks = chunks;
    if (chunks > 1 && !threads_.empty()) {
      {
        std::lock_guard<std::mutex> lock(mutex_);
        queue_.push_back(job);
      }
      wake_.notify_all();
    }
    job->Work();
    {
      std::unique_lock<std::mutex> lock(job->mutex);
      job->finished.wait(lock, [&] { return job->done.load() >= job->chunks; });
    }
    if (job->failed.load()) throw std::runtime_error(job->error);
  }

 private:
  void Serve() {
    for (;;) {
      std::shared_ptr<Job> job;
      {
        std::unique_lock<std::mutex> lock(mutex_);
        wake_.wait(lock, [&] { return !queue_.empty(); });
        job = queue_.front();
        if (job->next.load() >= job->chunks) {  // every chunk taken: the job leaves the queue
          queue_.pop_front();
          continue;
        }
      }
      job->Work();
    }
  }

  std::vector<std::thread> threads_;
  std::mutex mutex_;
  std::condition_variable wake_;
  std::deque<std::shared_ptr<Job>> queue_;
};

Pool* g_pool = nullptr;  // created by jaxloc_native_init, never destroyed (threads idle at exit)

// ----------------------------------------------------------------------------------------------
// Scenes: a map's real triangles in one Embree scene, and the map index of each.

struct MapScene {
  rtc::Scene scene = nullptr;
  std::vector<int32_t> ids;  // map index of each Embree primitive
  std::vector<float> corners;  // the 9 coordinates of each Embree primitive (v0, v1, v2)
  bool prefix = true;        // ids are 0..K-1 (maps pad at the end): no translation
  ~MapScene() {
    if (scene != nullptr) g_api.release_scene(scene);
  }
};

std::shared_ptr<MapScene> BuildScene(const float* triangles, int64_t count) {
  auto map = std::make_shared<MapScene>();
  for (int64_t i = 0; i < count; ++i) {
    const float* row = triangles + 9 * i;
    if (std::any_of(row, row + 9, [](float x) { return x != 0.0f; })) {
      map->ids.push_back(static_cast<int32_t>(i));
    }
  }
  for (size_t k = 0; k < map->ids.size(); ++k) map->prefix &= map->ids[k] == int32_t(k);
  map->corners.resize(9 * map->ids.size());
  for (size_t k = 0; k < map->ids.size(); ++k) {
    std::memcpy(&map->corners[9 * k], triangles + 9 * int64_t(map->ids[k]), 9 * sizeof(float));
  }
  map->scene = g_api.new_scene(g_api.device);
  CheckDevice("creating a scene");
  g_api.set_scene_flags(map->scene, rtc::kSceneFlagRobust);
  if (!map->ids.empty()) {
    rtc::Geometry mesh = g_api.new_geometry(g_api.device, rtc::kGeometryTriangle);
    CheckDevice("creating a triangle mesh");
    size_t n = map->ids.size();
    auto* vertices = static_cast<float*>(g_api.set_new_geometry_buffer(
        mesh, rtc::kBufferVertex, 0, rtc::kFormatFloat3, 3 * sizeof(float), 3 * n));
    auto* corners = static_cast<uint32_t*>(g_api.set_new_geometry_buffer(
        mesh, rtc::kBufferIndex, 0, rtc::kFormatUint3, 3 * sizeof(uint32_t), n));
    if (vertices == nullptr || corners == nullptr) {
      g_api.release_geometry(mesh);
      CheckDevice("allocating the mesh buffers");
      throw std::runtime_error("Embree gave no mesh buffer");
    }
    for (size_t k = 0; k < n; ++k) {
      std::memcpy(vertices + 9 * k, &map->corners[9 * k], 9 * sizeof(float));
      for (uint32_t c = 0; c < 3; ++c) corners[3 * k + c] = uint32_t(3 * k + c);
    }
    g_api.commit_geometry(mesh);
    g_api.attach_geometry(map->scene, mesh);
    g_api.release_geometry(mesh);  // the scene holds it
  }
  g_api.commit_scene(map->scene);
  CheckDevice("building the scene");
  return map;
}

// A small thread-safe LRU of scenes by (fingerprint, triangle rows). The fingerprint comes from
// the traced program (jaxloc/raycasting/_cache.py): edited triangles give a new key.
class SceneCache {
 public:
  static constexpr size_t kCapacity = 8;

  std::shared_ptr<MapScene> Get(uint64_t fingerprint, int64_t count, const float* triangles) {
    std::lock_guard<std::mutex> lock(mutex_);
    for (auto it = items_.begin(); it != items_.end(); ++it) {
      if (it->fingerprint == fingerprint && it->count == count) {
        items_.splice(items_.begin(), items_, it);  // most recently used first
        return items_.front().scene;
      }
    }
    items_.push_front({fingerprint, count, BuildScene(triangles, count)});
    while (items_.size() > kCapacity) items_.pop_back();  // a scene in use lives on (shared_ptr)
    return items_.front().scene;
  }
  void Clear() {
    std::lock_guard<std::mutex> lock(mutex_);
    items_.clear();
  }
  size_t Size() {
    std::lock_guard<std::mutex> lock(mutex_);
    return items_.size();
  }

 private:
  struct Item {
    uint64_t fingerprint;
    int64_t count;
    std::shared_ptr<MapScene> scene;
  };
  std::mutex mutex_;
  std::list<Item> items_;
};

SceneCache g_scenes;

// ----------------------------------------------------------------------------------------------
// Casting.

// One batch row's rays and where their results go (t, u, v null for the faces-only call).
struct RowRays {
  const MapScene* map;
  const float* origins;
  const float* directions;
  const bool* valid;
  int32_t* faces;
  float* t;
  float* u;
  float* v;
};

constexpr float kInf = std::numeric_limits<float>::infinity();

// Moller-Trumbore's determinant below which a ray counts as parallel (triangle.py's DET_EPS).
constexpr double kDetEps = 1e-12;

// Where the compiler can, HitValues is built twice, for AVX2 and for any x86-64, and the loader
// picks the one the CPU runs (GCC's and Clang's target_clones, which need glibc's ifunc): on this
// project's CPU the AVX2 build takes 5.1 ns a ray instead of 7.6 (one thread, cache-hot), with
// the same results to the bit (no FMA is allowed either way).
#if defined(__x86_64__) && defined(__GLIBC__) && \
    (defined(__clang__) ? __clang_major__ >= 14 : defined(__GNUC__) && __GNUC__ >= 8)
#define JAXLOC_TARGET_CLONES __attribute__((target_clones("avx2", "default")))
#else
#define JAXLOC_TARGET_CLONES
#endif

// t, u, v of N rays on their hit triangles, by the formulas jaxloc.raycasting.hits recomputes
// them with in JAX, in double precision (never less accurate than JAX's float32 recompute): t in
// the plane form n . (v0 - o) / (n . d), n = e1 x e2 (far more accurate than Embree's own t for
// small, distant triangles, which can be ~1e-4 relative off), u, v by Moller-Trumbore, clipped to
// [0, 1]. c: the triangles' 9 coordinates (v0, v1, v2), each (coordinate, lane); o, d: the rays,
// an array of N lanes for each coordinate (x, y, z).
// The inputs are widened to double in loops of their own and the arithmetic is branch-free over
// the lanes, so that the compiler vectorizes both (GCC 12 vectorizes no loop that mixes float
// loads with double arithmetic: 10.3 ns a ray so; the guarded divisions need -fno-trapping-math,
// which _native.py builds with).
template <int N>
JAXLOC_TARGET_CLONES void HitValues(const float (&c)[9][N], const float* const (&o)[3],
                                    const float* const (&d)[3], float* t, float* u, float* v) {
  alignas(64) double corner[9][N], origin[3][N], direction[3][N];
  for (int j = 0; j < 9; ++j) {
    for (int k = 0; k < N; ++k) corner[j][k] = c[j][k];
  }
  for (int a = 0; a < 3; ++a) {
    for (int k = 0; k < N; ++k) origin[a][k] = o[a][k], direction[a][k] = d[a][k];
  }
  for (int k = 0; k < N; ++k) {
    double dx = direction[0][k], dy = direction[1][k], dz = direction[2][k];
    double e1x = corner[3][k] - corner[0][k], e1y = corner[4][k] - corner[1][k];
    double e1z = corner[5][k] - corner[2][k];
    double e2x = corner[6][k] - corner[0][k], e2y = corner[7][k] - corner[1][k];
    double e2z = corner[8][k] - corner[2][k];
    double px = dy * e2z - dz * e2y, py = dz * e2x - dx * e2z, pz = dx * e2y - dy * e2x;
    double det = e1x * px + e1y * py + e1z * pz;
    double inv = 1.0 / (std::fabs(det) > kDetEps ? det : 1.0);
    double sx = origin[0][k] - corner[0][k], sy = origin[1][k] - corner[1][k];
    double sz = origin[2][k] - corner[2][k];
    double uk = (sx * px + sy * py + sz * pz) * inv;
    double qx = sy * e1z - sz * e1y, qy = sz * e1x - sx * e1z, qz = sx * e1y - sy * e1x;
    double vk = (dx * qx + dy * qy + dz * qz) * inv;
    u[k] = float(std::min(std::max(uk, 0.0), 1.0));
    v[k] = float(std::min(std::max(vk, 0.0), 1.0));
    double nx = e1y * e2z - e1z * e2y, ny = e1z * e2x - e1x * e2z, nz = e1x * e2y - e1y * e2x;
    double facing = nx * dx + ny * dy + nz * dz;
    facing = std::fabs(facing) > kDetEps ? facing : 1.0;
    t[k] = float(-(nx * sx + ny * sy + nz * sz) / facing);
  }
}

// A triangle and a ray that stand in for the lanes without a hit (their values are dropped).
constexpr float kStandInTriangle[9] = {0, 0, 1, 1, 0, 1, 0, 1, 1};
constexpr float kStandInOrigin[3] = {0.25f, 0.25f, 0};
constexpr float kStandInDirection[3] = {0, 0, 1};

// The results of rays index[0 .. n - 1] of a row (n <= N) from Embree's hit ids (`geom` the
// invalid id on a miss); lanes whose ray was not traced (`traced` false) are written as misses.
// `packet`: the rays as they were traced in a packet (its lanes hold rays index[0 .. n - 1]), or
// null for rays traced alone.
template <int N>
void StoreLanes(const RowRays& row, const int64_t* index, int n, const bool* traced,
                const uint32_t* geom, const uint32_t* prim, const rtc::RayHitPacket<N>* packet) {
  bool hit[N];
  for (int k = 0; k < n; ++k) {
    hit[k] = traced[k] && geom[k] != rtc::kInvalidGeometryId;
    row.faces[index[k]] = !hit[k]            ? -1
                          : row.map->prefix ? int32_t(prim[k])
                                            : row.map->ids[prim[k]];
  }
  if (row.t == nullptr) return;
  alignas(64) float c[9][N], o[3][N], d[3][N], t[N], u[N], v[N];
  for (int k = 0; k < N; ++k) {
    bool real = k < n && hit[k];
    const float* tri = real ? &row.map->corners[9 * size_t(prim[k])] : kStandInTriangle;
    for (int j = 0; j < 9; ++j) c[j][k] = tri[j];
  }
  // The lanes' rays: as the packet holds them (a lane without a hit may hold an invalid ray or a
  // copy of another; its values are dropped, every division is guarded, NaN only propagates), or
  // gathered here for rays traced alone.
  const float* origin[3] = {o[0], o[1], o[2]};
  const float* direction[3] = {d[0], d[1], d[2]};
  if (packet != nullptr) {
    origin[0] = packet->org_x, origin[1] = packet->org_y, origin[2] = packet->org_z;
    direction[0] = packet->dir_x, direction[1] = packet->dir_y, direction[2] = packet->dir_z;
  } else {
    for (int k = 0; k < N; ++k) {
      bool real = k < n && hit[k];
      const float* ok = real ? row.origins + 3 * index[k] : kStandInOrigin;
      const float* dk = real ? row.directions + 3 * index[k] : kStandInDirection;
      for (int a = 0; a < 3; ++a) o[a][k] = ok[a], d[a][k] = dk[a];
    }
  }
  HitValues<N>(c, origin, direction, t, u, v);
  for (int k = 0; k < n; ++k) {
    int64_t i = index[k];
    row.t[i] = hit[k] ? t[k] : kInf;
    row.u[i] = hit[k] ? u[k] : 0.0f;
    row.v[i] = hit[k] ? v[k] : 0.0f;
  }
}

// Ray i of a row alone; its hit ids into geom, prim.
void CastOne(const RowRays& row, int64_t i, uint32_t* geom, uint32_t* prim) {
  rtc::RayHit rh;
  const float* o = row.origins + 3 * i;
  const float* d = row.directions + 3 * i;
  rh.ray.org_x = o[0], rh.ray.org_y = o[1], rh.ray.org_z = o[2];
  rh.ray.dir_x = d[0], rh.ray.dir_y = d[1], rh.ray.dir_z = d[2];
  rh.ray.tnear = 0.0f, rh.ray.tfar = kInf, rh.ray.mask = 0xffffffffu;
  rh.ray.time = 0.0f, rh.ray.id = 0, rh.ray.flags = 0;
  rh.hit.geomID = rh.hit.primID = rtc::kInvalidGeometryId;
  rh.hit.instance_stack[0] = rtc::kInvalidGeometryId;
  rtc::IntersectArguments args{};
  args.flags = rtc::kQueryIncoherent;
  args.feature_mask = rtc::kFeatureAll;
  g_api.intersect1(row.map->scene, &rh, &args);
  *geom = rh.hit.geomID, *prim = rh.hit.primID;
}

std::atomic<int64_t> g_packets{0};  // packets traced so far (tests check the path is taken)
std::atomic<int64_t> g_bands{0};    // bands of raster lines cast in tiles so far (likewise)

// How far (chord of unit directions) a packet's rays may point from its first ray: wider packets
// are traced ray by ray. Measured at 960 x 540 and 60 degrees, 1 thread, on filter_step.py's room
// (41k triangles, 500 poses near one place): rows of 8 rays 4 and 8 pixels apart (chords 0.03 and
// 0.07) traced 1.7x and 1.2x faster as packets than alone, rows 20 pixels apart (0.17) 15 %
// slower; tiles of 2 x 4 rays 20 pixels apart (0.076) 11 % slower there, but 16 % faster on
// engines.py's room (60k triangles, 2500 poses all over it), as the filter's first frame has them.
constexpr float kMaxPacketSpread = 0.1f;

// Squared chord between the unit directions of rays a and b of a row.
float Chord2(const RowRays& row, int64_t a, int64_t b) {
  const float* x = row.directions + 3 * a;
  const float* y = row.directions + 3 * b;
  float dx = x[0] - y[0], dy = x[1] - y[1], dz = x[2] - y[2];
  return dx * dx + dy * dy + dz * dz;
}

bool SameOrigin(const RowRays& row, int64_t a, int64_t b) {
  return std::memcmp(row.origins + 3 * a, row.origins + 3 * b, 3 * sizeof(float)) == 0;
}

// Rays index[0 .. n - 1] of a row (n <= N): one packet where the valid ones share an origin (a
// camera's rays) and point within kMaxPacketSpread of each other, else one by one; `planned`: a
// tile of a raster that PlanRow found, a packet without these checks (which rays go into a
// packet only changes the speed). Counts the packets in *packets.
template <int N>
void CastLanes(const RowRays& row, const int64_t* index, int n, rtc::IntersectPacketFn packet,
               int64_t* packets, bool planned) {
  alignas(64) int mask[N];
  bool traced[N];
  uint32_t geom[N], prim[N];
  int lead = -1;
  bool coherent = packet != nullptr;
  for (int k = 0; k < n; ++k) {
    traced[k] = row.valid[index[k]];
    if (!traced[k]) continue;
    if (lead < 0) {
      lead = k;
    } else if (coherent && !planned) {
      coherent = SameOrigin(row, index[k], index[lead]) &&
                 Chord2(row, index[k], index[lead]) <= kMaxPacketSpread * kMaxPacketSpread;
    }
  }
  if (lead < 0) {
    // nothing to trace: every lane is written as a miss
  } else if (!coherent) {
    for (int k = 0; k < n; ++k) {
      if (traced[k]) CastOne(row, index[k], &geom[k], &prim[k]);
    }
  } else {
    rtc::RayHitPacket<N> rays;
    rtc::IntersectArguments args{};
    args.flags = rtc::kQueryCoherent;
    args.feature_mask = rtc::kFeatureAll;
    for (int k = 0; k < N; ++k) {
      int64_t i = index[std::min(k, n - 1)];
      mask[k] = (k < n && traced[k]) ? -1 : 0;
      const float* o = row.origins + 3 * i;
      const float* d = row.directions + 3 * i;
      rays.org_x[k] = o[0], rays.org_y[k] = o[1], rays.org_z[k] = o[2], rays.tnear[k] = 0.0f;
      rays.dir_x[k] = d[0], rays.dir_y[k] = d[1], rays.dir_z[k] = d[2], rays.time[k] = 0.0f;
      rays.tfar[k] = kInf, rays.mask[k] = 0xffffffffu, rays.id[k] = uint32_t(k);
      rays.flags[k] = 0;
      rays.geomID[k] = rays.primID[k] = rays.instance_stack[0][k] = rtc::kInvalidGeometryId;
    }
    packet(mask, row.map->scene, &rays, &args);
    ++*packets;
    for (int k = 0; k < n; ++k) geom[k] = rays.geomID[k], prim[k] = rays.primID[k];
    StoreLanes<N>(row, index, n, traced, geom, prim, &rays);
    return;
  }
  StoreLanes<N>(row, index, n, traced, geom, prim, nullptr);
}

// A share of the work: `count` rays of batch row `row` from `begin`, either in their own order
// (`width` 0) or `lines` raster lines of `width` rays each, cast band by band (2 lines) in tiles
// of 2 lines x N/2 rays: packets of neighbours in both directions (on filter_step.py's room, 1
// thread, tiles of 2 x 4 traced 11 % faster than rows of 8 at strides 4 and 8).
struct Piece {
  int64_t row;
  int64_t begin;
  int64_t count;
  int64_t width;
  int64_t lines;
};

//! Rays per piece (about; a multiple of every packet width where they go in their own order).
constexpr int64_t kChunk = 512;
// The narrowest and the widest raster line looked for. Narrower "rasters" keep their own order:
// rays already in tile order read as lines of 4 (a 4 x 4 tile), and go as packets as they come.
constexpr int64_t kMinWidth = 16;
constexpr int64_t kMaxWidth = 8192;

// The width of the raster (lines of camera rays, row-major) that starts at ray `first` of a row,
// or 0 where there is none or its tiles of 2 x `columns` rays would not go as packets. A line
// ends where the direction turns back; the next line starts beside its start.
int64_t RasterWidth(const RowRays& row, int64_t first, int64_t end, int columns) {
  if (end - first < 2 * columns + 2) return 0;
  const float* a = row.directions + 3 * first;
  float step[3] = {a[3] - a[0], a[4] - a[1], a[5] - a[2]};
  int64_t last = std::min(end, first + kMaxWidth) - 1;
  int64_t width = 0;
  for (int64_t j = first + 1; j < last; ++j) {
    const float* p = row.directions + 3 * j;
    float dot = (p[3] - p[0]) * step[0] + (p[4] - p[1]) * step[1] + (p[5] - p[2]) * step[2];
    if (!(dot > 0.0f)) {
      width = j + 1 - first;
      break;
    }
  }
  if (width < std::max<int64_t>(kMinWidth, columns) || first + width + columns > end) return 0;
  for (int64_t line = 0; line < 2; ++line) {
    for (int64_t c = 0; c < columns; ++c) {
      int64_t i = first + line * width + c;
      if (!SameOrigin(row, i, first) ||
          !(Chord2(row, i, first) <= kMaxPacketSpread * kMaxPacketSpread)) {
        return 0;
      }
    }
  }
  return width;
}

// The pieces of rays [0, num_rays) of batch row `r`: rasters found from a view's first ray as
// bands of 2 lines, everything else in pieces of kChunk rays in their own order. Which rays go
// into a packet only changes the speed; every ray is cast exactly once either way.
void PlanRow(const RowRays& row, int64_t r, int64_t num_rays, int columns,
             std::vector<Piece>* pieces) {
  int64_t i = 0;
  while (i < num_rays) {
    int64_t width = columns > 1 ? RasterWidth(row, i, num_rays, columns) : 0;
    int64_t lines = width > 0 ? 1 : 0;
    while (width > 0 && i + (lines + 1) * width <= num_rays &&
           SameOrigin(row, i + lines * width, i) &&
           Chord2(row, i + lines * width, i + (lines - 1) * width) <=
               kMaxPacketSpread * kMaxPacketSpread) {
      ++lines;
    }
    if (lines >= 2) {
      int64_t per_piece = std::max<int64_t>(2, kChunk / width / 2 * 2);  // whole bands
      for (int64_t l = 0; l < lines; l += per_piece) {
        int64_t count = std::min(per_piece, lines - l);
        pieces->push_back({r, i + l * width, count * width, width, count});
      }
      g_bands.fetch_add((lines + 1) / 2, std::memory_order_relaxed);
      i += lines * width;
    } else {
      int64_t count = std::min(kChunk, num_rays - i);
      pieces->push_back({r, i, count, 0, 1});
      i += count;
    }
  }
}

template <int N>
void CastPiece(const RowRays& row, const Piece& piece, rtc::IntersectPacketFn packet) {
  int64_t index[N];
  int64_t packets = 0;
  if (piece.width == 0) {
    int64_t end = piece.begin + piece.count;
    for (int64_t first = piece.begin; first < end; first += N) {
      int n = int(std::min<int64_t>(N, end - first));
      for (int k = 0; k < n; ++k) index[k] = first + k;
      CastLanes<N>(row, index, n, packet, &packets, false);
    }
  } else {
    constexpr int kColumns = N / 2;
    for (int64_t line = 0; line < piece.lines; line += 2) {
      int64_t band = std::min<int64_t>(2, piece.lines - line);
      int64_t start = piece.begin + line * piece.width;
      for (int64_t c0 = 0; c0 < piece.width; c0 += kColumns) {
        int n = 0;
        int64_t stop = std::min<int64_t>(c0 + kColumns, piece.width);
        for (int64_t l = 0; l < band; ++l) {
          for (int64_t c = c0; c < stop; ++c) index[n++] = start + l * piece.width + c;
        }
        CastLanes<N>(row, index, n, packet, &packets, true);
      }
    }
  }
  if (packets > 0) g_packets.fetch_add(packets, std::memory_order_relaxed);
}

void Cast(const RowRays& row, const Piece& piece) {
  switch (g_api.packet_width) {
    case 16:
      return CastPiece<16>(row, piece, g_api.intersect16);
    case 8:
      return CastPiece<8>(row, piece, g_api.intersect8);
    case 4:
      return CastPiece<4>(row, piece, g_api.intersect4);
    default:
      return CastPiece<4>(row, piece, nullptr);
  }
}

// Cast every row's rays on the pool.
void CastRows(const std::vector<RowRays>& rows, int64_t num_rays) {
  int columns = g_api.packet_width > 1 ? g_api.packet_width / 2 : 0;
  std::vector<Piece> pieces;
  for (size_t r = 0; r < rows.size(); ++r) PlanRow(rows[r], int64_t(r), num_rays, columns, &pieces);
  if (pieces.empty()) return;
  g_pool->Run(int64_t(pieces.size()), [&](int64_t c) { Cast(rows[pieces[c].row], pieces[c]); });
}

// ----------------------------------------------------------------------------------------------
// The FFI handler.

// The leading (batch) axes of an operand of base rank `base`, checked against the batch shape.
std::vector<int64_t> Lead(const ffi::AnyBuffer& buffer, size_t base, size_t lead_rank) {
  auto dims = buffer.dimensions();
  if (dims.size() != base + lead_rank) throw std::runtime_error("operands of unequal batch rank");
  return std::vector<int64_t>(dims.begin(), dims.begin() + lead_rank);
}

// Offset (in rows) of batch element `flat` of an operand with leading axes `lead` (size 1 where
// it is broadcast) in a batch of shape `batch`.
int64_t RowOf(int64_t flat, const std::vector<int64_t>& batch, const std::vector<int64_t>& lead) {
  int64_t offset = 0, stride = 1;
  for (size_t a = batch.size(); a-- > 0;) {
    int64_t index = flat % batch[a];
    flat /= batch[a];
    if (lead[a] != 1) offset += index * stride;
    stride *= lead[a];
  }
  return offset;
}

void NearestOrThrow(const ffi::AnyBuffer& key, const ffi::AnyBuffer& triangles,
                    const ffi::AnyBuffer& origins, const ffi::AnyBuffer& directions,
                    const ffi::AnyBuffer& valid, const std::vector<ffi::AnyBuffer>& out) {
  if (!g_ready) throw std::runtime_error("jaxloc_native_init was not called");
  if (key.element_type() != ffi::DataType::U32 || triangles.element_type() != ffi::DataType::F32 ||
      origins.element_type() != ffi::DataType::F32 ||
      directions.element_type() != ffi::DataType::F32 ||
      valid.element_type() != ffi::DataType::PRED) {
    throw std::runtime_error("operand dtypes are not (uint32, f32, f32, f32, bool)");
  }
  if (out.size() != 1 && out.size() != 4) throw std::runtime_error("1 or 4 results expected");
  size_t lead_rank = key.dimensions().size() - 1;
  auto key_lead = Lead(key, 1, lead_rank), tri_lead = Lead(triangles, 3, lead_rank);
  auto o_lead = Lead(origins, 2, lead_rank), d_lead = Lead(directions, 2, lead_rank);
  auto v_lead = Lead(valid, 1, lead_rank);
  auto tri_dims = triangles.dimensions();
  int64_t count = tri_dims[lead_rank];
  int64_t num_rays = origins.dimensions()[lead_rank];
  std::vector<int64_t> batch(lead_rank);
  int64_t size = 1;
  for (size_t a = 0; a < lead_rank; ++a) {
    batch[a] = std::max({key_lead[a], tri_lead[a], o_lead[a], d_lead[a], v_lead[a]});
    size *= batch[a];
  }
  for (const auto& r : out) {
    if (int64_t(r.element_count()) != size * num_rays) throw std::runtime_error("result size");
  }
  const auto* key_data = static_cast<const uint32_t*>(key.untyped_data());
  const auto* tri_data = static_cast<const float*>(triangles.untyped_data());
  std::vector<std::shared_ptr<MapScene>> maps;  // keep the scenes alive for the call
  std::vector<std::pair<int64_t, const MapScene*>> seen;  // triangle row -> scene
  std::vector<RowRays> rows(size);
  for (int64_t b = 0; b < size; ++b) {
    int64_t k = RowOf(b, batch, key_lead), m = RowOf(b, batch, tri_lead);
    const MapScene* map = nullptr;
    for (const auto& [row, scene] : seen) {
      if (row == m) map = scene;
    }
    if (map == nullptr) {
      uint64_t fingerprint = (uint64_t(key_data[2 * k]) << 32) | key_data[2 * k + 1];
      maps.push_back(g_scenes.Get(fingerprint, count, tri_data + 9 * count * m));
      map = maps.back().get();
      seen.emplace_back(m, map);
    }
    int64_t o = RowOf(b, batch, o_lead), d = RowOf(b, batch, d_lead), v = RowOf(b, batch, v_lead);
    auto at = [&](int i) { return static_cast<float*>(out[i].untyped_data()) + b * num_rays; };
    rows[b] = RowRays{map,
                      static_cast<const float*>(origins.untyped_data()) + 3 * num_rays * o,
                      static_cast<const float*>(directions.untyped_data()) + 3 * num_rays * d,
                      static_cast<const bool*>(valid.untyped_data()) + num_rays * v,
                      static_cast<int32_t*>(out[0].untyped_data()) + b * num_rays,
                      out.size() == 4 ? at(1) : nullptr,
                      out.size() == 4 ? at(2) : nullptr,
                      out.size() == 4 ? at(3) : nullptr};
  }
  CastRows(rows, num_rays);
}

std::atomic<int> g_reported{0};

ffi::Error Nearest(ffi::AnyBuffer key, ffi::AnyBuffer triangles, ffi::AnyBuffer origins,
                   ffi::AnyBuffer directions, ffi::AnyBuffer valid, ffi::RemainingRets rets) {
  if (rets.size() < 2) return ffi::Error::InvalidArgument("a result and the status expected");
  std::vector<ffi::AnyBuffer> out;
  for (size_t i = 0; i < rets.size(); ++i) {
    auto ret = rets.get<ffi::AnyBuffer>(i);
    if (ret.has_error()) return ret.error();
    out.push_back(**ret);
  }
  ffi::AnyBuffer status = out.back();
  out.pop_back();
  auto* status_data = static_cast<int32_t*>(status.untyped_data());
  std::fill(status_data, status_data + status.element_count(), 1);
  try {
    NearestOrThrow(key, triangles, origins, directions, valid, out);
    std::fill(status_data, status_data + status.element_count(), 0);
  } catch (const std::exception& e) {  // reported in the status; the first few on stderr
    if (g_reported.fetch_add(1) < 5) {
      std::fprintf(stderr, "jaxloc: the native Embree engine failed: %s\n", e.what());
    }
  }
  return ffi::Error::Success();
}

}  // namespace

XLA_FFI_DEFINE_HANDLER_SYMBOL(jaxloc_embree_nearest_native, Nearest,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .RemainingRets());

extern "C" {

int jaxloc_native_set_packet_width(int width);

// Load Embree from `library` (a path), make its device, start `threads` - 1 workers (0: as many
// CPUs as this process's affinity allows). Returns 0, or 1 with a message in `error`.
int jaxloc_native_init(const char* library, int threads, char* error, int error_size) {
  std::lock_guard<std::mutex> lock(g_init_mutex);
  if (g_ready) return 0;
  std::string message;
  void* handle = dlopen(library, RTLD_NOW | RTLD_LOCAL);
  bool ok = handle != nullptr;
  if (!ok) message = dlerror();
  ok = ok && Find(handle, "rtcNewDevice", &g_api.new_device, &message) &&
       Find(handle, "rtcGetDeviceError", &g_api.get_device_error, &message) &&
       Find(handle, "rtcGetDeviceProperty", &g_api.get_device_property, &message) &&
       Find(handle, "rtcNewScene", &g_api.new_scene, &message) &&
       Find(handle, "rtcReleaseScene", &g_api.release_scene, &message) &&
       Find(handle, "rtcSetSceneFlags", &g_api.set_scene_flags, &message) &&
       Find(handle, "rtcCommitScene", &g_api.commit_scene, &message) &&
       Find(handle, "rtcNewGeometry", &g_api.new_geometry, &message) &&
       Find(handle, "rtcSetNewGeometryBuffer", &g_api.set_new_geometry_buffer, &message) &&
       Find(handle, "rtcCommitGeometry", &g_api.commit_geometry, &message) &&
       Find(handle, "rtcAttachGeometry", &g_api.attach_geometry, &message) &&
       Find(handle, "rtcReleaseGeometry", &g_api.release_geometry, &message) &&
       Find(handle, "rtcIntersect1", &g_api.intersect1, &message) &&
       Find(handle, "rtcIntersect4", &g_api.intersect4, &message) &&
       Find(handle, "rtcIntersect8", &g_api.intersect8, &message) &&
       Find(handle, "rtcIntersect16", &g_api.intersect16, &message);
  if (ok) {
    g_api.device = g_api.new_device(nullptr);
    ok = g_api.device != nullptr;
    if (!ok) message = "rtcNewDevice failed";
  }
  if (ok) {
    ssize_t version = g_api.get_device_property(g_api.device, rtc::kPropertyVersion);
    if (version < 40000 || version >= 50000) {
      ok = false;
      message = "Embree " + std::to_string(version) + " is not Embree 4";
    }
  }
  if (!ok) {
    std::snprintf(error, size_t(error_size), "%s", message.c_str());
    return 1;
  }
  // Packets of 8 even where the CPU has 16-wide kernels: on an AVX-512 CPU (filter_step.py's
  // room, 1 thread) rows of 16 rays 4 and 8 pixels apart traced 12 % and 21 % slower than of 8.
  jaxloc_native_set_packet_width(8);
  if (threads <= 0) {
    cpu_set_t set;
    threads = sched_getaffinity(0, sizeof(set), &set) == 0 ? CPU_COUNT(&set) : 1;
  }
  g_pool = new Pool(std::max(0, threads - 1));
  g_ready = true;
  return 0;
}

// The packet width in use (16, 8, 4; 1: single rays only) and the threads that cast (the
// caller's included).
int jaxloc_native_packet_width() { return g_api.packet_width; }
int jaxloc_native_threads() { return g_pool == nullptr ? 0 : g_pool->size(); }

// Force a packet width (16, 8, 4 or 1) up to the CPU's widest; returns the width now in use.
int jaxloc_native_set_packet_width(int width) {
  int native = 1;
  for (int w : {16, 8, 4}) {
    if (native == 1 && g_api.device != nullptr &&
        g_api.get_device_property(g_api.device, w == 16  ? rtc::kPropertyNativeRay16
                                                : w == 8 ? rtc::kPropertyNativeRay8
                                                         : rtc::kPropertyNativeRay4) > 0) {
      native = w;
    }
  }
  g_api.packet_width = std::min(width, native);
  if (g_api.packet_width != 16 && g_api.packet_width != 8 && g_api.packet_width != 4) {
    g_api.packet_width = 1;
  }
  return g_api.packet_width;
}

void jaxloc_native_clear_cache() { g_scenes.Clear(); }
int64_t jaxloc_native_packets_traced() { return g_packets.load(); }
int64_t jaxloc_native_raster_bands() { return g_bands.load(); }
int jaxloc_native_cached_scenes() { return int(g_scenes.Size()); }

// The engine on plain arrays, without XLA (the load-time self-test): triangles (T, 3, 3),
// origins and directions (R, 3), valid (R,) as bytes; faces (R,), and t, u, v (R,) unless null.
// Returns 0, or 1 with a message in `error`.
int jaxloc_native_cast(const float* triangles, int64_t count, const float* origins,
                       const float* directions, const uint8_t* valid, int64_t num_rays,
                       int32_t* faces, float* t, float* u, float* v, char* error,
                       int error_size) {
  try {
    if (!g_ready) throw std::runtime_error("jaxloc_native_init was not called");
    auto map = BuildScene(triangles, count);
    static_assert(sizeof(bool) == sizeof(uint8_t), "bool is one byte");
    RowRays row{map.get(), origins, directions, reinterpret_cast<const bool*>(valid), faces,
                t, u, v};
    CastRows({row}, num_rays);
    return 0;
  } catch (const std::exception& e) {
    std::snprintf(error, size_t(error_size), "%s", e.what());
    return 1;
  }
}

}  // extern "C"
