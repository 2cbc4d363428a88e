// The part of Embree 4's C API (libembree4) that jaxloc's native ray engine calls.
//
// Written for jaxloc from Embree's API documentation (the rtc*(3) manual pages: rtcNewDevice,
// rtcNewScene, rtcSetSceneFlags, rtcNewGeometry, rtcSetNewGeometryBuffer, rtcIntersect1,
// rtcIntersect4/8/16, rtcInitIntersectArguments, RTCRay, RTCHit, RTCRayHit, RTCRayHitN,
// rtcGetDeviceProperty, rtcGetDeviceError). Nothing here is linked: the functions are looked up
// by name in the library that the embreex wheel ships (dlopen/dlsym), so the types below are
// function-pointer types. Only the members jaxloc reads or writes are named; the structs are
// sized and aligned so that everything Embree may write fits.
#pragma once

#include <cstddef>
#include <cstdint>
#include <sys/types.h>

namespace jaxloc::embree {

using Device = struct DeviceOpaque*;
using Scene = struct SceneOpaque*;
using Geometry = struct GeometryOpaque*;

// enum RTCError: RTC_ERROR_NONE is 0.
constexpr int kErrorNone = 0;
// enum RTCDeviceProperty: RTC_DEVICE_PROPERTY_VERSION and NATIVE_RAY{4,8,16}_SUPPORTED.
constexpr int kPropertyVersion = 0;
constexpr int kPropertyNativeRay4 = 32;
constexpr int kPropertyNativeRay8 = 33;
constexpr int kPropertyNativeRay16 = 34;
// enum RTCSceneFlags: RTC_SCENE_FLAG_ROBUST (watertight traversal, no cracks along shared edges).
constexpr int kSceneFlagRobust = 1 << 2;
// enum RTCGeometryType: RTC_GEOMETRY_TYPE_TRIANGLE.
constexpr int kGeometryTriangle = 0;
// enum RTCBufferType: RTC_BUFFER_TYPE_INDEX, RTC_BUFFER_TYPE_VERTEX.
constexpr int kBufferIndex = 0;
constexpr int kBufferVertex = 1;
// enum RTCFormat: RTC_FORMAT_UINT3 (triangle corners), RTC_FORMAT_FLOAT3 (vertices).
constexpr int kFormatUint3 = 0x5003;
constexpr int kFormatFloat3 = 0x9003;
// enum RTCRayQueryFlags: RTC_RAY_QUERY_FLAG_INCOHERENT (0) and RTC_RAY_QUERY_FLAG_COHERENT.
constexpr uint32_t kQueryIncoherent = 0;
constexpr uint32_t kQueryCoherent = 1u << 16;
// enum RTCFeatureFlags: RTC_FEATURE_FLAG_ALL.
constexpr uint32_t kFeatureAll = 0xffffffffu;
// RTC_INVALID_GEOMETRY_ID: what geomID holds before a hit and after a miss.
constexpr uint32_t kInvalidGeometryId = 0xffffffffu;

// struct RTCRay (16-byte aligned).
struct alignas(16) Ray {
  float org_x, org_y, org_z, tnear;
  float dir_x, dir_y, dir_z, time;
  float tfar;
  uint32_t mask, id, flags;
};

// struct RTCHit (16-byte aligned): normal, barycentric u/v, ids; then the instance stack
// (instID, and instPrimID where the library has instance arrays), one level each.
struct alignas(16) Hit {
  float Ng_x, Ng_y, Ng_z;
  float u, v;
  uint32_t primID, geomID;
  uint32_t instance_stack[2];
};

// struct RTCRayHit.
struct alignas(16) RayHit {
  Ray ray;
  Hit hit;
};

// struct RTCRayHit4 / RTCRayHit8 / RTCRayHit16: the same members, structure of arrays, aligned to
// the packet's width in bytes (16, 32, 64).
template <int N>
struct alignas(4 * N) RayHitPacket {
  float org_x[N], org_y[N], org_z[N], tnear[N];
  float dir_x[N], dir_y[N], dir_z[N], time[N];
  float tfar[N];
  uint32_t mask[N], id[N], flags[N];
  float Ng_x[N], Ng_y[N], Ng_z[N];
  float u[N], v[N];
  uint32_t primID[N], geomID[N];
  uint32_t instance_stack[2][N];
};

// struct RTCIntersectArguments, as rtcInitIntersectArguments leaves it apart from `flags`:
// no context, filter or user-geometry callback (the trailing float is the min-width factor of
// libraries built with it; zero either way).
struct alignas(16) IntersectArguments {
  uint32_t flags;
  uint32_t feature_mask;
  void* context;
  void* filter;
  void* intersect;
  float min_width_distance_factor;
};

// The functions, as pointer types (see the manual page of each).
using NewDeviceFn = Device (*)(const char* config);
using ReleaseDeviceFn = void (*)(Device);
using GetDeviceErrorFn = int (*)(Device);
using GetDevicePropertyFn = ssize_t (*)(Device, int property);
using NewSceneFn = Scene (*)(Device);
using ReleaseSceneFn = void (*)(Scene);
using SetSceneFlagsFn = void (*)(Scene, int flags);
using CommitSceneFn = void (*)(Scene);
using NewGeometryFn = Geometry (*)(Device, int type);
using SetNewGeometryBufferFn = void* (*)(Geometry, int type, unsigned int slot, int format,
                                         size_t byte_stride, size_t item_count);
using CommitGeometryFn = void (*)(Geometry);
using AttachGeometryFn = unsigned int (*)(Scene, Geometry);
using ReleaseGeometryFn = void (*)(Geometry);
using Intersect1Fn = void (*)(Scene, RayHit*, IntersectArguments*);
using IntersectPacketFn = void (*)(const int* valid, Scene, void* packet, IntersectArguments*);

}  // namespace jaxloc::embree
