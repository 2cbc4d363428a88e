"""Shared fixtures and float64 references for the foundation tests (geometry, camera, raycast,
scene, render).

Everything here is deliberately independent of the code under test: the brute-force raycaster is
float64 numpy over every triangle, the peers are trimesh's own intersectors. Sizes are small so the
whole foundation suite runs in a couple of minutes on two shared cores; compiled functions are
shared (module-level ``jax.jit`` objects taking the scene as an argument) so each shape compiles
once per session.
"""

from __future__ import annotations

import functools
import importlib.util
import os
from pathlib import Path

import jax
import numpy as np
import pytest
import trimesh

from jaxloc import raycast, render, render_batch
from jaxloc.scene import SceneGraph

#: XLA's persistent compilation cache, shared by the pytest workers (xdist), the subprocesses the
#: CLI, notebook and sharding tests start (they inherit the environment variable) and later runs.
#: Programs are keyed by their HLO, jax version and backend, so a changed kernel never hits a stale
#: entry; the cache only saves the recompilation of identical programs in another process.
COMPILE_CACHE = Path(__file__).resolve().parents[1] / ".pytest_cache" / "jax_compile"
#: Every program is cached (the tiny test programs compile in well under jax's 1 s default).
os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", str(COMPILE_CACHE))
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
#: The command line run in-process by the tests must not switch the cache to the user's folder
#: (tests/test_compilation_cache.py checks jaxloc's own cache in subprocesses).
os.environ["JAXLOC_NO_CACHE"] = "1"
jax.config.update("jax_compilation_cache_dir", os.environ["JAX_COMPILATION_CACHE_DIR"])
jax.config.update(
    "jax_persistent_cache_min_compile_time_secs",
    float(os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"]),
)

#: Linux refuses a process new memory mappings beyond ``vm.max_map_count`` (65530 by default),
#: and every program XLA:CPU compiles or loads from the cache holds some (a small one about 9; one
#: M2Loc map build and query about 2200, its ~250 programs): a test worker that had run many
#: modules' programs ended in "LLVM ERROR: Unable to allocate section memory" (SIGABRT) in
#: whichever test compiled next. After a module, past this many mappings, the worker drops its
#: compiled programs (``jax.clear_caches``); later modules trace again and load from the cache.
MAX_MAPPINGS = 15_000


def mappings() -> int:
    """This process's memory mappings (Linux; 0 where /proc is absent)."""
    try:
        with open("/proc/self/maps", "rb") as maps:
            return maps.read().count(b"\n")
    except OSError:
        return 0


@pytest.fixture(autouse=True, scope="module")
def _bounded_mappings():
    yield
    if mappings() > MAX_MAPPINGS:
        jax.clear_caches()


#: Number of rays of the standard random batch (one compiled shape for most raycast tests).
NUM_RAYS = 2048

#: Jitted entry points shared by all test modules: one compilation per (shape, capacity).
#: ``cast*`` test the pure-JAX engine (the reference traversal); tests/test_engines.py checks the
#: other engines against the same references.
cast = jax.jit(functools.partial(raycast, engine="jax", packet_size=1))
cast16 = jax.jit(functools.partial(raycast, engine="jax", packet_size=16))
cast64 = jax.jit(functools.partial(raycast, engine="jax", packet_size=64))
render_jit = jax.jit(render)
render_batch_jit = jax.jit(render_batch)


# ----------------------------------------------------------------------------- references


def brute_force(
    triangles: np.ndarray, origins: np.ndarray, directions: np.ndarray, t_min: float = 1e-6
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nearest hit of every ray against every triangle, float64 Moller-Trumbore.

    Args:
        triangles: (T, 3, 3) vertex positions (world frame, metres).
        origins: (R, 3) ray origins; directions: (R, 3) ray directions (any non-zero length).
        t_min: hits closer than this (metres) are ignored, as in jaxloc.

    Returns:
        t (R,) metric distance along the unit direction (inf on a miss), triangle (R,) int index
        (-1 on a miss), and (R, 3) barycentric coordinates of the hit (zeros on a miss).
    """
    tris = np.asarray(triangles, np.float64)
    o = np.asarray(origins, np.float64)
    d = np.asarray(directions, np.float64)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    v0, e1, e2 = tris[:, 0], tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]
    t_out = np.full(o.shape[0], np.inf)
    tri_out = np.full(o.shape[0], -1, np.int64)
    bary_out = np.zeros((o.shape[0], 3))
    for start in range(0, o.shape[0], 128):
        oc, dc = o[start : start + 128, None, :], d[start : start + 128, None, :]
        t, u, v, det = mt_float64(oc, dc, v0[None], e1[None], e2[None])
        ok = (np.abs(det) > 1e-12) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > t_min)
        t = np.where(ok, t, np.inf)
        best = np.argmin(t, axis=1)
        rows = np.arange(best.shape[0])
        tb = t[rows, best]
        hit = np.isfinite(tb)
        sl = slice(start, start + best.shape[0])
        t_out[sl] = tb
        tri_out[sl] = np.where(hit, best, -1)
        ub, vb = u[rows, best], v[rows, best]
        bary_out[sl] = np.where(hit[:, None], np.stack([1 - ub - vb, ub, vb], -1), 0.0)
    return t_out, tri_out, bary_out


def mt_float64(o, d, v0, e1, e2):
    """Float64 Moller-Trumbore on broadcastable (..., 3) arrays: returns t, u, v, det (...)."""
    p = np.cross(d, e2)
    det = np.sum(e1 * p, -1)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.where(np.abs(det) > 0, 1.0 / np.where(det == 0, 1.0, det), np.nan)
        s = o - v0
        u = np.sum(s * p, -1) * inv
        q = np.cross(s, e1)
        v = np.sum(d * q, -1) * inv
        t = np.sum(e2 * q, -1) * inv
    return t, u, v, det


def hits_triangle(triangles, origins, directions, tri_ids, eps=1e-5):
    """Float64 check that each ray meets its given triangle (barycentric margin ``eps``).

    Returns (R,) bool (False where ``tri_ids`` is -1) and the float64 t (R,) on that triangle.
    """
    tris = np.asarray(triangles, np.float64)[np.maximum(tri_ids, 0)]
    d = np.asarray(directions, np.float64)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    t, u, v, _ = mt_float64(
        np.asarray(origins, np.float64),
        d,
        tris[:, 0],
        tris[:, 1] - tris[:, 0],
        tris[:, 2] - tris[:, 0],
    )
    ok = (tri_ids >= 0) & (u >= -eps) & (v >= -eps) & (u + v <= 1 + eps) & (t > 0)
    return ok, t


def edge_margin(triangles, origins, directions, tri_ids):
    """Float64 smallest barycentric coordinate of each ray's hit on its triangle (inf for -1)."""
    tris = np.asarray(triangles, np.float64)[np.maximum(tri_ids, 0)]
    d = np.asarray(directions, np.float64)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    _, u, v, _ = mt_float64(
        np.asarray(origins, np.float64),
        d,
        tris[:, 0],
        tris[:, 1] - tris[:, 0],
        tris[:, 2] - tris[:, 0],
    )
    return np.where(tri_ids >= 0, np.minimum(np.minimum(u, v), 1 - u - v), np.inf)


class _BoxTree:
    """A stand-in for the rtree index trimesh's numpy intersector queries (``bounds`` and
    ``intersection``): exact AABB overlap over all triangles, vectorised in numpy. It only selects
    candidates; the intersection maths is trimesh's own (``ray_triangle_id``)."""

    def __init__(self, triangles: np.ndarray):
        self._lo, self._hi = triangles.min(1), triangles.max(1)
        self.bounds = np.concatenate([self._lo.min(0), self._hi.max(0)])

    def intersection(self, box):
        box = np.asarray(box)
        overlap = np.all(self._lo <= box[3:], axis=1) & np.all(self._hi >= box[:3], axis=1)
        return np.flatnonzero(overlap)


def scene_mesh(scene: SceneGraph) -> trimesh.Trimesh:
    """All real triangles of ``scene`` as one unprocessed trimesh (face i = scene triangle i)."""
    tris = np.asarray(scene.triangles, np.float64)[: scene.num_triangles]
    faces = np.arange(tris.shape[0] * 3).reshape(-1, 3)
    return trimesh.Trimesh(tris.reshape(-1, 3), faces, process=False)


def trimesh_first(mesh: trimesh.Trimesh, origins, directions) -> np.ndarray:
    """trimesh's numpy ray intersector: first triangle per ray (-1 on a miss).

    Uses ``trimesh.ray.ray_triangle.RayMeshIntersector`` when rtree is installed, else the same
    ``ray_triangle_id`` it calls, with an exact AABB candidate search in place of rtree.
    """
    from trimesh.ray import ray_triangle

    o = np.asarray(origins, np.float64)
    d = np.asarray(directions, np.float64)
    if importlib.util.find_spec("rtree") is not None:
        return ray_triangle.RayMeshIntersector(mesh).intersects_first(o, d)
    index_tri, index_ray, _ = ray_triangle.ray_triangle_id(
        triangles=mesh.triangles,
        ray_origins=o,
        ray_directions=d,
        tree=_BoxTree(mesh.triangles),
        multiple_hits=False,
        triangles_normal=mesh.face_normals,
    )
    out = np.full(o.shape[0], -1, np.int64)
    out[index_ray] = index_tri
    return out


# ----------------------------------------------------------------------------- scenes


def random_meshes(seed: int, num_objects: int = 40, spread: float = 3.0) -> list[trimesh.Trimesh]:
    """Many small closed objects (spheres, boxes, cylinders, thin plates), randomly rotated and
    placed in ``[-spread, spread]^3`` (they may interpenetrate); ~2k triangles for 40 objects."""
    rng = np.random.default_rng(seed)
    meshes = []
    for i in range(num_objects):
        kind = i % 4
        if kind == 0:
            mesh = trimesh.creation.icosphere(subdivisions=1, radius=rng.uniform(0.2, 0.6))
        elif kind == 1:
            mesh = trimesh.creation.box(extents=rng.uniform(0.2, 1.2, 3))
        elif kind == 2:
            mesh = trimesh.creation.cylinder(
                radius=rng.uniform(0.1, 0.4), height=rng.uniform(0.3, 1.5), sections=10
            )
        else:  # a thin plate: two nearly coplanar faces close together
            mesh = trimesh.creation.box(
                extents=[rng.uniform(0.5, 1.5), rng.uniform(0.5, 1.5), 0.01]
            )
        transform = trimesh.transformations.random_rotation_matrix(rng.random(3))
        transform[:3, 3] = rng.uniform(-spread, spread, 3)
        meshes.append(mesh.apply_transform(transform))
    return meshes


def random_scene(seed: int, num_objects: int = 40, **kwargs) -> SceneGraph:
    """A :class:`SceneGraph` of :func:`random_meshes` with random labels and 8-d embeddings."""
    rng = np.random.default_rng(seed + 1000)
    meshes = random_meshes(seed, num_objects)
    labels = rng.integers(0, 5, num_objects)
    return SceneGraph.from_meshes(meshes, labels, rng.normal(size=(num_objects, 8)), **kwargs)


def random_rays(scene: SceneGraph, seed: int, num: int = NUM_RAYS):
    """(num, 3) origins and directions, float32: from outside the scene bounds and from inside
    (including object centres, i.e. inside closed meshes), aimed at random surface points or in
    random directions. Direction lengths vary (not unit)."""
    rng = np.random.default_rng(seed)
    tris = np.asarray(scene.triangles)[: scene.num_triangles].astype(np.float64)
    lo, hi = np.asarray(scene.bounds, np.float64)
    centre, radius = (lo + hi) / 2, np.linalg.norm(hi - lo) / 2
    q = num // 4

    def outside(n):
        v = rng.normal(size=(n, 3))
        return centre + 1.5 * radius * v / np.linalg.norm(v, axis=1, keepdims=True)

    def inside(n):
        return rng.uniform(lo - 0.2, hi + 0.2, (n, 3))

    def surface_points(n):
        k = rng.integers(0, tris.shape[0], n)
        w = rng.dirichlet(np.ones(3), n)
        return np.einsum("nc,ncd->nd", w, tris[k])

    tri_obj = np.asarray(scene.triangle_object)[: scene.num_triangles]
    centres = np.stack(
        [tris[tri_obj == i].reshape(-1, 3).mean(0) for i in range(scene.num_objects)]
    )
    inner = centres[rng.integers(0, centres.shape[0], q // 2)]
    origins = np.concatenate(
        [outside(q), inside(q), inside(q - q // 2), inner, outside(num - 3 * q)]
    )
    aimed = surface_points(2 * q) - origins[: 2 * q]
    rand_dir = rng.normal(size=(num - 2 * q, 3))
    directions = np.concatenate([aimed, rand_dir])
    directions *= rng.uniform(0.2, 5.0, (num, 1))
    perm = rng.permutation(num)
    return origins[perm].astype(np.float32), directions[perm].astype(np.float32)


@pytest.fixture(scope="session")
def scene() -> SceneGraph:
    """40 random small objects, ~2k triangles."""
    return random_scene(0)


@pytest.fixture(scope="session")
def rays(scene):
    return random_rays(scene, 1)


@pytest.fixture(scope="session")
def hits(scene, rays):
    """jaxloc's hits of the standard random rays (packet size 1), as numpy arrays."""
    return jax.tree.map(np.asarray, cast(scene, *rays))


@pytest.fixture(scope="session")
def reference(scene, rays):
    """Float64 brute force over all triangles for the standard random rays: (t, tri, bary)."""
    return brute_force(np.asarray(scene.triangles)[: scene.num_triangles], *rays)


ROOM = (6.0, 4.0, 3.0)


def box_room(size=ROOM, colors: str = "wall") -> list[trimesh.Trimesh]:
    """Six axis-aligned walls of a closed room ``[0, Lx] x [0, Ly] x [0, H]``, one object each, in
    the order floor (z=0), ceiling (z=H), x=0, x=Lx, y=0, y=Ly; each a 4 x 4 grid of quads.

    ``colors``: "wall" gives each wall one flat vertex colour; "linear" gives every vertex the
    colour ``(x / Lx, y / Ly, z / H)`` (so an exact interpolation reproduces it at any point)."""
    n = 4
    a, b = np.meshgrid(np.linspace(0, 1, n + 1), np.linspace(0, 1, n + 1), indexing="ij")
    uv = np.stack([a.ravel(), b.ravel()], -1)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    quads = np.stack([idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]], -1).reshape(-1, 4)
    faces = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    meshes = []
    for k, (axis, side) in enumerate([(2, 0), (2, 1), (0, 0), (0, 1), (1, 0), (1, 1)]):
        other = [i for i in range(3) if i != axis]
        verts = np.zeros((uv.shape[0], 3))
        verts[:, axis] = side * size[axis]
        verts[:, other[0]] = uv[:, 0] * size[other[0]]
        verts[:, other[1]] = uv[:, 1] * size[other[1]]
        if colors == "linear":
            rgb = verts / np.asarray(size)
        else:
            rgb = np.broadcast_to([0.1 + 0.15 * k, 0.8 - 0.1 * k, 0.5], verts.shape)
        rgba = np.column_stack([np.round(255 * rgb), np.full(len(verts), 255)]).astype(np.uint8)
        meshes.append(trimesh.Trimesh(verts, faces, vertex_colors=rgba, process=False))
    return meshes


def room_hits(origin, directions, size=ROOM):
    """Analytic float64 raycast from inside the box room: (t, object) per ray (R,), with the
    object order of :func:`box_room`, and the gap to the second-nearest wall (to spot corners)."""
    d = np.asarray(directions, np.float64)
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    o = np.asarray(origin, np.float64)
    ts = np.full(d.shape[:-1] + (6,), np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        for axis, (lo_obj, hi_obj) in enumerate([(2, 3), (4, 5), (0, 1)]):
            t_lo = (0.0 - o[..., axis]) / d[..., axis]
            t_hi = (size[axis] - o[..., axis]) / d[..., axis]
            ts[..., lo_obj] = np.where(d[..., axis] < 0, t_lo, np.inf)
            ts[..., hi_obj] = np.where(d[..., axis] > 0, t_hi, np.inf)
    order = np.sort(ts, -1)
    return order[..., 0], np.argmin(ts, -1), order[..., 1] - order[..., 0]


@pytest.fixture(scope="session")
def room_scene(scene) -> SceneGraph:
    """A closed 6 x 4 x 3 m box room, six wall objects (labels 0..5), padded to the capacity of
    the random ``scene`` so that both share every compiled function."""
    return SceneGraph.from_meshes(box_room(), np.arange(6), np.eye(6, 8), capacity=scene.capacity)


def cast_padded(scene: SceneGraph, origins, directions):
    """``cast`` on up to NUM_RAYS rays, padded with NaN-origin rays to the shared compiled shape;
    returns numpy hits of the given rays only."""
    n = len(origins)
    o = np.full((NUM_RAYS, 3), np.nan, np.float32)
    d = np.ones((NUM_RAYS, 3), np.float32)
    o[:n], d[:n] = origins, directions
    return jax.tree.map(lambda a: np.asarray(a)[:n], cast(scene, o, d))


# -------------------------------------------------------------------- numpy frame reference
# Right-handed elementary rotations and the camera axes in the body frame (x forward, y left, z up):
# camera x (right) = body -y, camera y (down) = body -z, camera z (forward) = body +x.


def rot_z(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def rot_y(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def rot_x(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


BODY_CAM = np.column_stack([[0, -1, 0], [0, 0, -1], [1, 0, 0]]).astype(float)
