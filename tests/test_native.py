"""The native Embree engine (jaxloc/raycasting/native/, the default where it builds): its build,
self-test and fallback, its hits against a float64 brute force and the Python engine, and its
programs in the persistent compilation cache (run by either implementation)."""

from __future__ import annotations

import functools
import shutil
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import random_scene

import jaxloc
from jaxloc.raycasting import _native, embree

pytest.importorskip("embreex")
if shutil.which("c++") is None and shutil.which("g++") is None:
    pytest.skip("no C++ compiler: the native engine cannot be built here", allow_module_level=True)


@pytest.fixture(scope="module")
def engine():
    return _native.engine()


def test_mode_reads_the_environment(monkeypatch):
    monkeypatch.delenv(_native.ENV_MODE, raising=False)
    assert _native.mode() == "auto"
    for value, expected in (("1", "auto"), ("auto", "auto"), ("0", "off"), ("require", "require")):
        monkeypatch.setenv(_native.ENV_MODE, value)
        assert _native.mode() == expected
    monkeypatch.setenv(_native.ENV_MODE, "maybe")
    with pytest.raises(ValueError, match="JAXLOC_NATIVE"):
        _native.mode()
    monkeypatch.setenv(_native.ENV_THREADS, "-2")
    with pytest.raises(ValueError, match="JAXLOC_NATIVE_THREADS"):
        _native.threads()


def test_without_a_compiler_it_falls_back_with_one_warning(monkeypatch, tmp_path):
    monkeypatch.setenv(_native.ENV_MODE, "1")
    monkeypatch.setenv(_native.ENV_DIR, str(tmp_path))  # nothing built there yet
    monkeypatch.setenv("PATH", str(tmp_path))
    monkeypatch.delenv("CXX", raising=False)
    monkeypatch.setattr(_native, "engine", functools.cache(_native.engine.__wrapped__))
    _native.load.cache_clear()
    try:
        with pytest.warns(RuntimeWarning, match="no C\\+\\+ compiler"):
            assert _native.load() is None
        monkeypatch.setenv(_native.ENV_MODE, "require")
        _native.load.cache_clear()
        with pytest.raises(_native.NativeUnavailable, match="require"):
            _native.load()
        monkeypatch.setenv(_native.ENV_MODE, "0")
        _native.load.cache_clear()
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            assert _native.load() is None
    finally:
        _native.load.cache_clear()


def test_build_is_cached_under_its_key(engine):
    assert engine.path.exists() and engine.path.parent.name == _native.build_key(
        _native.compiler(), _native.embree_library()
    )
    assert _native.build() == engine.path  # a second build finds it


def test_cast_matches_a_float64_brute_force_on_adversarial_rays(engine):
    """Random rays plus rays through shared vertices and edges, grazing rays, origins inside a
    box and misses, against a box mesh with padding rows, packets and single rays."""
    import trimesh

    box = trimesh.creation.box((1.0, 2.0, 1.5))
    tri = np.asarray(box.triangles, np.float32)
    tri = np.concatenate([tri[:6], np.zeros((3, 3, 3), np.float32), tri[6:]])  # padding rows
    rng = np.random.default_rng(0)
    n = 4096
    origins = rng.uniform(-3, 3, (n, 3)).astype(np.float32)
    origins[: n // 4] = [0.05, -0.1, 0.02]  # inside the box, shared: packets
    origins[n // 4 : n // 2] = [2.5, 0.3, 0.1]  # outside, shared: packets
    targets = rng.uniform(-0.6, 0.6, (n, 3)) * [1, 2, 1.5]
    corners = np.unique(np.asarray(box.vertices), axis=0)
    targets[::7] = corners[rng.integers(0, len(corners), len(targets[::7]))]  # vertices
    edges = np.asarray(box.vertices)[np.asarray(box.edges_unique)]
    mid = edges.mean(1)
    targets[3::11] = mid[rng.integers(0, len(mid), len(targets[3::11]))]  # edges and diagonals
    directions = targets - origins
    directions[5::13, 2] = 0.0  # some grazing the top and bottom faces' planes
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    directions = directions.astype(np.float32)
    valid = rng.random(n) > 0.05
    faces, t, u, v = engine.cast(tri, origins, directions, valid)
    assert np.all(faces[~valid] == -1)
    # the analytic (slab) distance to the box's surface, float64; an axis the ray runs parallel
    # to bounds it everywhere (origin within that slab) or nowhere
    o, d = origins.astype(np.float64), directions.astype(np.float64)
    half = np.array([0.5, 1.0, 0.75])
    moving = d != 0
    safe = np.where(moving, d, 1.0)
    near = np.where(moving, (-np.sign(safe) * half - o) / safe, -np.inf)
    far = np.where(moving, (np.sign(safe) * half - o) / safe, np.inf)
    within = np.all(moving | (np.abs(o) < half), 1)
    enter, leave = near.max(1), far.min(1)
    slab_t = np.where(enter > 0, enter, leave)
    slab_hit = within & (enter < leave) & (leave > 0) & valid
    inside = np.all(np.abs(o) < half, 1) & valid
    assert inside.sum() > 900 and np.all(faces[inside] >= 0), "watertight: every ray out hits"
    clear = (leave - enter > 1e-3) | (leave < enter - 1e-3)  # not tangent to an edge or corner
    sure = slab_hit & clear
    assert sure.sum() > 2000 and np.all(faces[sure] >= 0)
    np.testing.assert_allclose(t[sure], slab_t[sure], rtol=1e-5, atol=1e-6)
    sure_miss = valid & ~slab_hit & clear & within
    assert sure_miss.sum() > 150 and np.all(faces[sure_miss] == -1)
    # faces, t, u, v against the float64 brute force on the random (non-adversarial) rays
    ref_faces, ref_t, ref_u, ref_v = _native.reference_hits(tri, origins, directions, valid)
    plain = np.ones(n, bool)
    plain[::7] = plain[3::11] = plain[5::13] = False
    assert np.mean(faces[plain] == ref_faces[plain]) >= 0.999
    same = plain & (faces == ref_faces) & (faces >= 0)
    np.testing.assert_allclose(t[same], ref_t[same], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(u[same], ref_u[same], atol=1e-5)
    np.testing.assert_allclose(v[same], ref_v[same], atol=1e-5)
    assert np.all(np.isinf(t[faces < 0])) and np.all(u[faces < 0] == 0)


def _camera_directions(camera, yaws) -> np.ndarray:
    """(len(yaws), R, 3) float32 world directions of ``camera``'s full pixel grid, turned by each
    yaw (camera z forward -> world x at yaw 0, camera y down -> world -z)."""
    d_cam = np.asarray(camera.directions(jaxloc.stride_grid(camera, 1).uv))
    c, s = np.cos(yaws), np.sin(yaws)
    zero, one = np.zeros_like(yaws), np.ones_like(yaws)
    yawed = np.stack([[c, -s, zero], [s, c, zero], [zero, zero, one]]).transpose(2, 0, 1)
    to_world = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]])
    return np.einsum("nij,jk,rk->nri", yawed, to_world, d_cam).astype(np.float32)


def _cast_single(engine, *rays) -> tuple[np.ndarray, ...]:
    """``engine.cast(*rays)`` with every ray alone (no packets, no tiles)."""
    width = engine.packet_width
    try:
        engine.set_packet_width(1)
        return engine.cast(*rays)
    finally:
        engine.set_packet_width(width)


def test_packets_equal_single_rays_on_camera_rays(engine):
    """A camera's rays (one origin, a 128 x 96 grid at 60 degrees: rows of 8 within the packets'
    spread) as packets and one by one, in a furnished room: the same faces (up to ties on shared
    edges) and t, u, v; the packet path is really taken for such rays, and not for scattered
    ones or for a sparser grid."""
    from jaxloc.synthetic.indoor import RoomConfig, make_room, scene_graph

    scene = scene_graph(make_room(3, RoomConfig(num_objects=(8, 8))))
    tris = np.asarray(scene.triangles)
    lo, hi = np.asarray(scene.bounds)
    camera = jaxloc.Camera.from_fov(128, 96, 60.0)
    yaws = np.linspace(0, 2 * np.pi, 6, endpoint=False)
    directions = _camera_directions(camera, yaws).reshape(-1, 3)
    origins = np.tile(((lo + hi) / 2).astype(np.float32), (len(directions), 1))
    if engine.packet_width == 1:
        pytest.skip("this CPU has no packet kernels")
    before = engine.packets_traced()
    packed = engine.cast(tris, origins, directions)
    assert engine.packets_traced() - before >= len(directions) // engine.packet_width // 2
    single = _cast_single(engine, tris, origins, directions)
    assert np.mean(packed[0] >= 0) > 0.99  # a closed room
    same = packed[0] == single[0]
    assert same.mean() >= 0.999
    for a, b in zip(packed[1:], single[1:], strict=True):
        np.testing.assert_array_equal(a[same], b[same])  # one formula on the same triangle
    rng = np.random.default_rng(0)
    scattered = origins + rng.uniform(-0.5, 0.5, origins.shape).astype(np.float32)
    before = engine.packets_traced()
    engine.cast(tris, scattered, directions)
    assert engine.packets_traced() == before
    sparse = directions.reshape(6, 96, 128, 3)[:, :, ::6].reshape(-1, 3)  # 3 degrees apart
    engine.cast(tris, origins[: len(sparse)], sparse)
    assert engine.packets_traced() == before  # tiles span 9 degrees, rows 21: one by one


def test_camera_rasters_cast_in_tiles_equal_single_rays(engine):
    """Four views of a 45 x 13 raster (no multiple of the tile's 4 columns, an odd number of
    lines; from four origins) back to back, then scattered rays, some rays invalid: the views are
    cast in tiles of 2 lines (bands counted), with the same faces as single rays (up to ties on
    shared edges) and the same t, u, v; every ray is cast once (an invalid one is a miss)."""
    from jaxloc.synthetic.indoor import RoomConfig, make_room, scene_graph

    if engine.packet_width == 1:
        pytest.skip("this CPU has no packet kernels")
    scene = scene_graph(make_room(5, RoomConfig(num_objects=(8, 8))))
    tris = np.asarray(scene.triangles)
    lo, hi = np.asarray(scene.bounds)
    camera = jaxloc.Camera.from_fov(45, 13, 30.0)  # 0.67 degrees per pixel
    assert jaxloc.stride_grid(camera, 1).shape == (13, 45)
    views = list(_camera_directions(camera, np.linspace(0.3, 2 * np.pi + 0.3, 4, endpoint=False)))
    origins = [
        np.tile((lo + hi) / 2 + [0.1 * k, -0.05 * k, 0.0], (view.shape[0], 1))
        for k, view in enumerate(views)
    ]
    rng = np.random.default_rng(1)
    scattered = rng.normal(size=(100, 3))
    views.append(scattered / np.linalg.norm(scattered, axis=1, keepdims=True))
    origins.append((lo + hi) / 2 + rng.uniform(-0.5, 0.5, (100, 3)))
    directions = np.concatenate(views).astype(np.float32)
    origins = np.concatenate(origins).astype(np.float32)
    valid = rng.random(len(origins)) > 0.05
    bands = engine.raster_bands()
    tiled = engine.cast(tris, origins, directions, valid)
    assert engine.raster_bands() - bands == 4 * 7  # 13 lines: 6 bands of 2 and one of 1 per view
    single = _cast_single(engine, tris, origins, directions, valid)
    assert np.all(tiled[0][~valid] == -1) and np.all(np.isinf(tiled[1][~valid]))
    assert np.mean(tiled[0][valid] >= 0) > 0.99  # a closed room
    same = tiled[0] == single[0]
    assert same.mean() >= 0.999
    for a, b in zip(tiled[1:], single[1:], strict=True):
        np.testing.assert_array_equal(a[same], b[same])


def test_handler_matches_the_python_engine_in_raycast(engine, monkeypatch):
    """jaxloc.raycast through the native handler and through the Python one: same faces on
    >= 99.9 % of rays, t within float32 rounding, vmapped calls equal to a loop, gradients equal
    (the native forward pass takes t from the engine, its derivatives from the JAX recompute)."""
    scene = random_scene(3, num_objects=12)
    rng = np.random.default_rng(1)
    lo, hi = np.asarray(scene.bounds)
    origins = np.tile(((lo + hi) / 2).astype(np.float32), (2, 300, 1))  # batch 0: one origin
    origins[1] += rng.uniform(-0.5, 0.5, (300, 3)).astype(np.float32)  # batch 1: scattered
    tris = np.asarray(scene.triangles)[: scene.num_triangles]
    aims = tris[rng.integers(0, len(tris), (2, 300))]  # points on random triangles
    weights = rng.dirichlet(np.ones(3), (2, 300))[..., None]
    directions = (np.sum(weights * aims, -2) - origins).astype(np.float32)
    directions /= np.linalg.norm(directions, axis=-1, keepdims=True)

    def cast(o, d):
        return jaxloc.raycast(scene, o, d, engine="embree")

    def loss(o):
        t = cast(o, directions[0]).t
        return jnp.sum(jnp.where(jnp.isfinite(t), t, 0.0))

    def run(target):
        monkeypatch.setattr(embree, "_target", lambda: target)
        batched = jax.tree.map(np.asarray, jax.jit(jax.vmap(cast))(origins, directions))
        looped = [
            jax.tree.map(np.asarray, jax.jit(cast)(origins[i], directions[i])) for i in range(2)
        ]
        grad = np.asarray(jax.grad(loss)(jnp.asarray(origins[0])))
        return batched, looped, grad

    native = run(embree.native_target())
    python = run(embree.python_target())
    for i in range(2):
        np.testing.assert_array_equal(native[0].triangle_id[i], native[1][i].triangle_id)
        np.testing.assert_array_equal(native[0].t[i], native[1][i].t)
    assert np.mean(native[0].triangle_id == python[0].triangle_id) >= 0.999
    same = (native[0].triangle_id == python[0].triangle_id) & python[0].hit
    assert same.mean() > 0.5
    # the native t is the recompute in double precision, JAX's in float32
    np.testing.assert_allclose(native[0].t[same], python[0].t[same], rtol=1e-4)
    tris = np.asarray(scene.triangles)[: scene.num_triangles]
    ref_faces, ref_t, _, _ = _native.reference_hits(
        tris, origins.reshape(-1, 3), directions.reshape(-1, 3), np.ones(600, bool)
    )
    exact = same.ravel() & (ref_faces == native[0].triangle_id.ravel())
    # (up to raycast's float32 re-normalisation of the directions, amplified on grazing rays)
    np.testing.assert_allclose(native[0].t.ravel()[exact], ref_t[exact], rtol=1e-5)
    np.testing.assert_allclose(native[2], python[2], rtol=1e-5, atol=1e-6)


#: A process that enables the compilation cache, casts rays with the Embree engine and reports the
#: implementation, the persistent-cache hits and the faces.
CACHED_CAST = """
import json, sys
import jax, jax.numpy as jnp, numpy as np
import jaxloc
from jaxloc.raycasting import embree
from jaxloc.synthetic.indoor import make_room, scene_graph

jaxloc.enable_compilation_cache(sys.argv[1])
hits = []
jax.monitoring.register_event_listener(
    lambda event, **kw: hits.append(event) if event.endswith("cache_hits") else None
)
scene = scene_graph(make_room(3))
rng = np.random.default_rng(0)
lo, hi = np.asarray(scene.bounds)
origins = jnp.asarray(np.tile((lo + hi) / 2, (64, 1)), jnp.float32)
directions = rng.normal(size=(64, 3))
directions[::4] = 0.0  # no direction: these miss
directions = jnp.asarray(directions, jnp.float32)
cast = jax.jit(lambda s, o, d: jaxloc.raycast(s, o, d, engine="embree", differentiable=False))
faces = np.asarray(cast(scene, origins, directions).triangle_id)
print(json.dumps({"impl": embree.implementation(), "hits": len(hits), "faces": faces.tolist()}))
"""


def test_handler_programs_go_to_the_persistent_cache_and_run_with_either(engine, tmp_path):
    """A program that calls the native handler is written to the persistent cache and loaded by
    the next process, and a process on the Python implementation (JAXLOC_NATIVE=0) loads and runs
    the same entry: one target name and signature for both."""
    import json
    import os
    import subprocess
    import sys

    def run(mode):
        env = dict(os.environ)
        for name in [k for k in env if k.startswith(("JAX_COMPILATION", "JAXLOC_"))]:
            del env[name]
        env.update({_native.ENV_MODE: mode, "JAX_PLATFORMS": "cpu"})
        done = subprocess.run(
            [sys.executable, "-c", CACHED_CAST, str(tmp_path / "xla")],
            env=env, capture_output=True, text=True, timeout=300,
        )  # fmt: skip
        assert done.returncode == 0, done.stderr[-3000:]
        return json.loads(done.stdout.strip().splitlines()[-1])

    first, second, python = run("require"), run("require"), run("0")
    assert (first["impl"], second["impl"], python["impl"]) == ("native", "native", "python")
    assert first["hits"] == 0 and second["hits"] >= 1 and python["hits"] >= 1
    assert first["faces"] == second["faces"] == python["faces"]
    faces = np.asarray(first["faces"])  # inside a closed room: every ray with a direction hits
    assert np.all(faces[::4] == -1) and np.all(np.delete(faces, np.s_[::4]) >= 0)
