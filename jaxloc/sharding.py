"""Spreading particles, sequences and LiDAR queries over several devices with ``jax.sharding``.

Nothing here changes how jaxloc computes: the helpers place arrays on a 1-D device
:class:`~jax.sharding.Mesh` (axis :data:`AXIS`) and the jitted functions of the library then run
sharded by XLA's sharding propagation. Three kinds of work split cleanly:

* **particles** of one filter: :func:`shard_particles` splits a padded
  :class:`~jaxloc.particles.ParticleState` along its capacity ``N`` (``N`` divisible by the device
  count); :func:`sharded_step` / :func:`sharded_run_pass` are :func:`jaxloc.filter.step` /
  :func:`jaxloc.filter.run_pass` with the state pinned to that sharding (the map, the frames and
  the configuration are replicated); :func:`jaxloc.sg2loc.localize` takes the same split with its
  ``mesh=`` argument. Rendering and scoring, the bulk of the work, are per particle: each device
  renders and scores its own shard under ``jax.shard_map`` (``StepConfig.mesh``), so it calls
  the nearest-hit engine (Embree, Warp or the JAX traversal) on its own rays; the weight
  normalisation, the KLD bin count and resampling are global (XLA inserts the collectives).
* **independent sequences** (sweeps over seeds, episodes or settings): :func:`sharded_run_passes`
  vmaps :func:`~jaxloc.filter.run_pass` over a leading batch axis split over the devices, each
  device running its own passes under ``jax.shard_map``.
* **LiDAR queries**: :func:`localize_scans` pads a list of scans to one capacity and runs the
  jitted :func:`~jaxloc.triplet.describe_query` / :func:`~jaxloc.triplet.register_query` vmapped
  over the batch, split over the devices.

Equality with one device (tested in ``tests/test_sharding.py`` on 4 CPU devices):

* random draws do not depend on the sharding (``jax_threefry_partitionable``, the default), so a
  sharded run consumes exactly the same random numbers as a single-device run with the same key;
* sequences and queries are independent per batch element: results are bit-identical to running
  each one alone on one device with the same key, up to the rounding of the batched (vmapped)
  kernels (poses equal to 1e-5 m; particle counts, cliques and inliers identical);
* particles of one filter: each device reduces its own shard first, so the float32 sums of the
  weight normalisation and the weighted mean are added in another order (differences of a few ulp
  in log-weights). Every discrete result (resampled indices, KLD particle counts, MLE slot) is
  identical unless two cumulative weights straddle a stratified draw within those few ulp, which
  is possible but rare; the test checks exact equality of the discrete outputs and 1e-5 closeness
  of the continuous ones over several frames.

Multi-host use (``jax.distributed.initialize()``, a global mesh over ``jax.devices()``, each
process feeding its own part of the batch) is described in the README.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from jaxloc.filter import Frame, StepConfig, StepInfo, run_pass, step
from jaxloc.particles import ParticleState
from jaxloc.scene import SceneGraph
from jaxloc.triplet._pipeline import (
    LocalizationResult,
    TripletMap,
    _check_points_labels,
    _invalid_result,
    describe_query,
    register_query,
)

#: The name of the single mesh axis that particles, sequences and queries are split along.
AXIS = "shards"


def device_mesh(devices: Sequence[jax.Device] | None = None) -> Mesh:
    """A 1-D mesh (axis :data:`AXIS`) over ``devices`` (default: every device, all hosts)."""
    devices = jax.devices() if devices is None else list(devices)
    if not devices:
        raise ValueError("device_mesh needs at least one device")
    return Mesh(np.asarray(devices), (AXIS,))


def split_sharding(mesh: Mesh) -> NamedSharding:
    """Leading axis split over the mesh, other axes whole."""
    return NamedSharding(mesh, PartitionSpec(AXIS))


def replicated_sharding(mesh: Mesh) -> NamedSharding:
    """Every device holds the whole array."""
    return NamedSharding(mesh, PartitionSpec())


def check_divisible(size: int, mesh: Mesh, what: str) -> None:
    """Raise a ValueError naming ``what`` and the padded size if ``size`` does not split evenly."""
    count = mesh.devices.size
    if size % count:
        raise ValueError(
            f"{what} ({size}) must be a multiple of the mesh's {count} devices to be split "
            f"evenly; pad it up to {-(-size // count) * count}"
        )


def _place(tree, sharding: NamedSharding):
    """``jax.device_put`` of every array leaf of ``tree`` (static fields untouched)."""
    return jax.tree.map(lambda x: jax.device_put(x, sharding) if eqx.is_array(x) else x, tree)


def replicate(tree, mesh: Mesh):
    """Copy every array leaf of ``tree`` (a map, frames, a config) to every device of ``mesh``."""
    return _place(tree, replicated_sharding(mesh))


def shard_particles(state: ParticleState, mesh: Mesh) -> ParticleState:
    """Split a particle state (N slots) over the mesh, N / D slots per device.

    Raises:
        ValueError: the capacity N is not a multiple of the number of devices D.
    """
    if not isinstance(state, ParticleState):
        raise TypeError(f"state must be a ParticleState, got {type(state).__name__}")
    check_divisible(state.capacity, mesh, "the particle capacity")
    return _place(state, split_sharding(mesh))


def shard_batch(tree, mesh: Mesh):
    """Split every array leaf of ``tree`` along its leading (batch) axis over the mesh.

    Raises:
        ValueError: a leaf has no leading axis or its size is not a multiple of the device count.
    """
    for leaf in jax.tree.leaves(tree):
        if eqx.is_array(leaf):
            if leaf.ndim == 0:
                raise ValueError("shard_batch needs a leading batch axis on every array")
            check_divisible(leaf.shape[0], mesh, "the batch size")
    return _place(tree, split_sharding(mesh))


def pin_split(tree, mesh: Mesh):
    """Inside a traced function: keep every array of ``tree`` split along its leading axis."""
    return jax.lax.with_sharding_constraint(tree, split_sharding(mesh))


@eqx.filter_jit
def sharded_step(
    key: Array,
    state: ParticleState,
    frame: Frame,
    scene: SceneGraph,
    config: StepConfig,
    mesh: Mesh,
) -> tuple[ParticleState, StepInfo]:
    """:func:`jaxloc.filter.step` with the particle state split over ``mesh`` in and out.

    Pass a state from :func:`shard_particles`; ``frame``, ``scene`` and ``config`` may be host
    arrays or :func:`replicate` d ones.
    """
    config = dataclasses.replace(config, mesh=mesh)
    state, info = step(key, pin_split(state, mesh), frame, scene, config)
    return pin_split(state, mesh), info


@eqx.filter_jit
def sharded_run_pass(
    key: Array,
    state: ParticleState,
    frames: Frame,
    scene: SceneGraph,
    config: StepConfig,
    mesh: Mesh,
) -> tuple[ParticleState, StepInfo]:
    """:func:`jaxloc.filter.run_pass` (``lax.scan`` over T frames) with the particles split over
    ``mesh``; same keys, same result as the single-device pass (see the module docstring)."""
    config = dataclasses.replace(config, mesh=mesh)
    state, info = run_pass(key, pin_split(state, mesh), frames, scene, config)
    return pin_split(state, mesh), info


@eqx.filter_jit
def sharded_run_passes(
    keys: Array,
    states: ParticleState,
    frames: Frame,
    scene: SceneGraph,
    config: StepConfig,
    mesh: Mesh,
) -> tuple[ParticleState, StepInfo]:
    """B independent filter passes, vmapped, with the batch split over ``mesh``.

    Args:
        keys: (B,) PRNG keys; states: particle states stacked on a leading B axis; frames: frames
            stacked (B, T, ...); scene and config shared. B must be a multiple of the device
            count. Element b equals ``run_pass(keys[b], states[b], frames[b], scene, config)``.

    Returns:
        Final states (B, ...) and per-frame infos (B, T, ...), split over ``mesh``.
    """
    split, whole = PartitionSpec(AXIS), PartitionSpec()
    per_device = jax.shard_map(  # each device runs its own passes, engine calls included
        jax.vmap(run_pass, in_axes=(0, 0, 0, None, None)),
        mesh=mesh,
        in_specs=(split, split, split, whole, whole),
        out_specs=split,
        check_vma=False,
    )
    return per_device(keys, states, frames, scene, config)


def localize_scans(
    triplet_map: TripletMap,
    scans: Sequence[tuple[np.ndarray, np.ndarray]],
    mesh: Mesh,
    capacity: int | None = None,
) -> list[LocalizationResult]:
    """:func:`jaxloc.triplet.localize_scan` for many scans at once, split over ``mesh``.

    Every scan is validated as :func:`~jaxloc.triplet.localize_scan` does, padded to one
    capacity (default: the map config's ``query_capacity``, else the next power of two >= 32 of
    the largest scan) and the batch is padded with empty scans to a multiple of the device count;
    one vmapped, jitted call describes and registers them all. Scans with fewer than 3 vertices
    give ``valid = False``.

    Args:
        triplet_map: a map from :func:`jaxloc.triplet.build_map`.
        scans: a list of (points (Nq, 3) scan frame metres, labels (Nq,) int class ids).
        mesh: the device mesh (:func:`device_mesh`).
        capacity: static padded query size (must hold the largest scan).

    Returns:
        One :class:`~jaxloc.triplet.LocalizationResult` per scan; its ``descriptor_time_ms`` and
        ``match_time_ms`` are the batch's times divided by the number of scans.

    Raises:
        ValueError: a bad scan (as :func:`~jaxloc.triplet.localize_scan`), or a scan larger than
            ``capacity`` (naming the capacity to raise).
    """
    config = triplet_map.config
    classes = config.descriptor.classes
    checked = [
        _check_points_labels(p, lab, classes, f"scan {i}") for i, (p, lab) in enumerate(scans)
    ]
    if not checked:
        return []
    largest = max(points.shape[0] for points, _ in checked)
    if capacity is None:
        capacity = config.query_capacity or max(32, 1 << max(largest - 1, 0).bit_length())
    if largest > capacity:
        raise ValueError(
            f"a scan has {largest} vertices, above the query capacity {capacity}: raise "
            "capacity= (or TripletConfig.query_capacity)"
        )
    count = mesh.devices.size
    batch = -(-len(checked) // count) * count
    points = np.zeros((batch, capacity, 3), np.float32)
    positions = np.zeros((batch, capacity), np.int32)
    mask = np.zeros((batch, capacity), bool)
    for b, (p, labels) in enumerate(checked):
        n = p.shape[0]
        points[b, :n] = p
        positions[b, :n] = [classes.index(int(label)) for label in labels]
        mask[b, :n] = n >= 3
    points, positions, mask = shard_batch(
        (jnp.asarray(points), jnp.asarray(positions), jnp.asarray(mask)), mesh
    )
    start = time.perf_counter()
    descriptors, valid = jax.block_until_ready(
        _describe_batch(points, positions, mask, config.descriptor)
    )
    middle = time.perf_counter()
    out = jax.block_until_ready(_register_batch(triplet_map, points, positions, descriptors, valid))
    end = time.perf_counter()
    out = jax.tree.map(np.asarray, out)
    results = []
    for b, (p, _) in enumerate(checked):
        if p.shape[0] < 3:
            results.append(_invalid_result())
            continue
        clique = out.clique[b]
        inliers = np.stack([out.association_query[b][clique], out.association_map[b][clique]], 1)
        results.append(
            LocalizationResult(
                pose=out.T_map_scan[b].astype(np.float64),
                valid=bool(out.valid[b]),
                clique_size=int(clique.sum()),
                inliers=inliers.astype(np.int64),
                scales_used=int(out.scales_used[b]),
                clique_exact=bool(out.clique_exact[b]),
                num_associations=int(out.association_valid[b].sum()),
                inlier_fraction=float(out.inlier_fraction[b]),
                descriptor_time_ms=1e3 * (middle - start) / len(checked),
                match_time_ms=1e3 * (end - middle) / len(checked),
            )
        )
    return results


@eqx.filter_jit
def _describe_batch(points, positions, mask, descriptor_config):
    return jax.vmap(describe_query, in_axes=(0, 0, 0, None))(
        points, positions, mask, descriptor_config
    )


@eqx.filter_jit
def _register_batch(triplet_map, points, positions, descriptors, valid):
    return jax.vmap(register_query, in_axes=(None, 0, 0, 0, 0))(
        triplet_map, points, positions, descriptors, valid
    )
