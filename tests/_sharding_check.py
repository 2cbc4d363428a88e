"""Multi-device checks of :mod:`jaxloc.sharding`, run in a subprocess by ``tests/test_sharding.py``.

``XLA_FLAGS=--xla_force_host_platform_device_count=4`` must be set before jax is imported, so this
script sets it itself and prints one JSON line of measured differences, which the test asserts on.
Tiny sizes: the room of ``tests/_tiny_world.py`` (16 particles, 108 rays each, 4 frames) and a
2-block sparse synthetic outdoor world with 3 queries and an empty scan (TripletLoc, top-5); and
``jaxloc.sg2loc.localize(..., mesh=)`` on a 3-frame sequence of the same room (one round).
"""

from __future__ import annotations

import os

os.environ["XLA_FLAGS"] = (
    os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=4"
).strip()

import dataclasses  # noqa: E402
import hashlib  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402

import _tiny_world as tiny  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from jaxloc import sg2loc, sharding
from jaxloc.m2loc import build_map, localize_scan, localize_scans, tripletloc_config
from jaxloc.raycasting import embree, engines
from jaxloc.sg2loc import sharded
from jaxloc.sg2loc._resampling import KLDConfig
from jaxloc.synthetic.outdoor import make_outdoor_world, make_query

NUM_FRAMES = tiny.CHUNK
#: The nearest-hit engines installed here.
ENGINES = ["jax"] + [e for e in ("embree", "warp") if engines.is_installed(e)]


def digest(tree) -> str:
    """sha256 of every leaf's bytes (bit-identical results give identical digests)."""
    h = hashlib.sha256()
    for leaf in jax.tree.leaves(tree):
        h.update(np.asarray(leaf).tobytes())
    return h.hexdigest()


def max_abs(a, b) -> float:
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    finite = np.isfinite(a) & np.isfinite(b)
    if not np.array_equal(np.isfinite(a), np.isfinite(b)):
        return float("inf")
    return float(np.max(np.abs(a[finite] - b[finite]), initial=0.0))


def particle_checks(
    mesh, engine: str = "auto", particle_chunk: int | None = None, batch: bool = True
) -> dict:
    """The particles split over the devices against one device: a pass of the filter; with
    ``batch`` also independent sequences, one per device."""
    scene = tiny.scene()
    config = dataclasses.replace(
        tiny.step_config(scene), engine=engine, particle_chunk=particle_chunk
    )
    frames = tiny.frames(NUM_FRAMES)
    state = tiny.initial_state(scene)
    key = jax.random.key(2)

    single_state, single_info = tiny.RUN_PASS(key, state, frames, scene, config)
    sharded_state, sharded_info = sharded.sharded_run_pass(
        key,
        sharded.shard_particles(state, mesh),
        sharding.replicate(frames, mesh),
        sharding.replicate(scene, mesh),
        config,
        mesh,
    )
    out = {
        "single_digest": digest((single_state, single_info)),
        "state_spec": str(sharded_state.poses.sharding.spec),
        "state_devices": len(sharded_state.poses.sharding.device_set),
        "pass_counts_equal": bool(
            np.array_equal(single_info.num_particles, sharded_info.num_particles)
        ),
        "pass_active_equal": bool(np.array_equal(single_state.active, sharded_state.active)),
        "pass_mle_diff": max_abs(single_info.mle, sharded_info.mle),
        "pass_poses_diff": max_abs(single_state.poses, sharded_state.poses),
        "pass_log_weights_diff": max_abs(single_state.log_weights, sharded_state.log_weights),
        "pass_nan": bool(np.any(np.isnan(np.asarray(sharded_info.mle)))),
    }

    if not batch:
        return out
    # independent sequences: B = 4 keys, one per device
    size = 4
    keys = jax.random.split(jax.random.key(3), size)
    states = jax.tree.map(lambda a: jnp.stack([a] * size), state)
    stacked = jax.tree.map(lambda a: jnp.stack([a] * size), frames)
    batch_state, batch_info = sharded.sharded_run_passes(
        keys,
        sharding.shard_batch(states, mesh),
        sharding.shard_batch(stacked, mesh),
        scene,
        config,
        mesh,
    )
    run = tiny.RUN_PASS
    diffs, counts_equal = [], True
    for b in range(size):
        alone_state, alone_info = run(keys[b], state, frames, scene, config)
        diffs.append(max_abs(alone_info.mle, batch_info.mle[b]))
        counts_equal &= bool(np.array_equal(alone_info.num_particles, batch_info.num_particles[b]))
    out["batch_spec"] = str(batch_info.mle.sharding.spec)
    out["batch_mle_diff"] = max(diffs)
    out["batch_counts_equal"] = counts_equal
    return out


def engine_call_checks(mesh) -> dict:
    """Rays per Embree call in a sharded step: each device calls the engine on its own shard.
    Counted in the Python implementation (the native handler has the same target signature, so
    XLA partitions its calls the same way)."""
    scene = tiny.scene()
    config = dataclasses.replace(tiny.step_config(scene), engine="embree")
    state = tiny.initial_state(scene)
    calls = []
    host = embree._embree_host

    def counting(key, triangles, origins, directions, valid, out=None, values=False):
        calls.append(int(np.prod(np.shape(origins)[:-1])))
        return host(key, triangles, origins, directions, valid, out, values)

    embree._embree_host = counting
    target = embree._target
    embree._target = embree.python_target
    try:
        frame = jax.tree.map(lambda a: a[0], tiny.frames(NUM_FRAMES))
        sharded.sharded_step(
            jax.random.key(7), sharded.shard_particles(state, mesh), frame, scene, config, mesh
        )
        jax.effects_barrier()
    finally:
        embree._embree_host = host
        embree._target = target
    return {"embree_rays_per_call": sorted(calls), "rays_per_particle": config.grid.uv.shape[0]}


def localize_checks(mesh, progress: bool = False) -> dict:
    """The user API: ``sg2loc.localize`` with and without ``mesh`` (one round, 3 frames); with
    ``progress`` also the scan with the progress bar's host callback, with ``mesh``."""
    scene = tiny.scene()
    config = sg2loc.SG2LocConfig(
        capacity=tiny.CAPACITY,
        strides=(2,),
        kld=KLDConfig(min_particles=4, max_particles=tiny.CAPACITY),
    )
    sequence = tiny.sequence(3)
    key = jax.random.key(5)
    alone = sg2loc.localize(key, scene, sequence, config)
    split = sg2loc.localize(key, scene, sequence, config, mesh=mesh)
    checks = {
        "localize_counts_equal": bool(np.array_equal(alone.num_particles, split.num_particles)),
        "localize_poses_diff": max_abs(alone.round_mle, split.round_mle),
        "localize_particles_devices": len(split.particles.sharding.device_set),
        "localize_nan": bool(np.any(np.isnan(np.asarray(split.poses)))),
    }
    if progress:
        framed = sg2loc.localize(key, scene, sequence, config, mesh=mesh, progress=True)
        checks["progress_counts_equal"] = bool(
            np.array_equal(split.num_particles, framed.num_particles)
        )
        checks["progress_poses_diff"] = max_abs(split.round_mle, framed.round_mle)
        checks["progress_particles_devices"] = len(framed.particles.sharding.device_set)
    return checks


def query_checks(mesh) -> dict:
    world = make_outdoor_world("sparse", seed=3, blocks=2, bridge_length=100.0)
    config = tripletloc_config(
        query_capacity=32, top_k=5, clique_compact_size=64, clique_max_nodes=500, clique_seeds=16
    )
    triplet_map = build_map(world.points, world.labels, config, world.road_normals)
    rng = np.random.default_rng(11)
    queries = [
        make_query(world.points, world.labels, world.road_normals, rng, max_kept=20)
        for _ in range(3)
    ]
    scans = [(q.points, q.labels) for q in queries] + [(np.zeros((0, 3)), np.zeros(0, int))]
    batched = localize_scans(triplet_map, scans, mesh)
    alone = [localize_scan(triplet_map, None, p, lab) for p, lab in scans]
    pairs = list(zip(alone, batched, strict=True))
    # another configuration's query settings on the same map: the same programs
    strict = dataclasses.replace(config, min_inlier_fraction=1.0, consistency_threshold=0.3)
    batched_strict = localize_scans(triplet_map, scans, mesh, config=strict)
    alone_strict = [localize_scan(triplet_map, None, p, lab, config=strict) for p, lab in scans]
    return {
        "queries_config_equal": all(
            a.valid == b.valid and max_abs(a.pose, b.pose) <= 1e-3
            for a, b in zip(alone_strict, batched_strict, strict=True)
        ),
        "queries_config_changed": [a.valid for a in alone] != [a.valid for a in alone_strict],
        "queries_valid_equal": [a.valid for a in alone] == [b.valid for b in batched],
        "queries_inliers_equal": all(np.array_equal(a.inliers, b.inliers) for a, b in pairs),
        "queries_pose_diff": max(max_abs(a.pose, b.pose) for a, b in pairs),
        "queries_num_valid": sum(b.valid for b in batched),
        "queries_digest": digest([(a.pose, a.inliers) for a in alone]),
    }


def main() -> None:
    mesh = sharding.device_mesh()
    result = {"devices": jax.device_count()}
    start = time.perf_counter()
    result.update(particle_checks(mesh))
    result["particle_seconds"] = time.perf_counter() - start
    result.update(localize_checks(mesh, progress=True))
    result["localize_seconds"] = time.perf_counter() - start - result["particle_seconds"]
    # every installed engine, and the chunk loop (2 particles per chunk, 2 chunks per device):
    # the sharded pass. The batch of sequences and localize's mesh split the same way whatever
    # the step inside does, so the default engine's checks above cover them.
    variants = [(engine, None) for engine in ENGINES] + [("auto", 2)]
    result["engines"] = {
        f"{engine}/{chunk}": particle_checks(mesh, engine, chunk, batch=False)
        for engine, chunk in variants
    }
    if "embree" in ENGINES:
        result.update(engine_call_checks(mesh))
    result.update(query_checks(mesh))
    result["total_seconds"] = time.perf_counter() - start
    print("RESULT " + json.dumps(result))


if __name__ == "__main__":
    main()
