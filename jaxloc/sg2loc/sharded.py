"""The particles of one filter, and independent filter passes, split over several devices.

:func:`shard_particles` splits a padded :class:`~jaxloc.sg2loc.ParticleState` along its
capacity ``N`` (``N`` divisible by the device count); :func:`sharded_step` /
:func:`sharded_run_pass` are :func:`jaxloc.sg2loc.step` /
:func:`~jaxloc.sg2loc.run_pass` with the state pinned to that sharding (the map, the frames
and the configuration are replicated). Rendering and scoring, the bulk of the work, are per
particle: each device renders and scores its own shard under ``jax.shard_map``
(``StepConfig.mesh``), so it calls the nearest-hit engine (Embree, Warp or the JAX traversal) on its
own rays. :func:`sharded_run_passes` vmaps
:func:`~jaxloc.sg2loc.run_pass` over a leading batch axis split over the devices. What
equals a single-device run, and to what precision: :mod:`jaxloc.sharding`.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
from jax import Array
from jax.sharding import Mesh, PartitionSpec

from jaxloc.scene import SceneGraph
from jaxloc.sg2loc._filter import StepConfig, StepInfo, run_pass, step
from jaxloc.sg2loc._particles import ParticleState
from jaxloc.sg2loc._sequence import Frame
from jaxloc.sharding import AXIS, check_divisible, pin_split, place, split_sharding


def shard_particles(state: ParticleState, mesh: Mesh) -> ParticleState:
    """Split a particle state (N slots) over the mesh, N / D slots per device.

    Raises:
        ValueError: the capacity N is not a multiple of the number of devices D.
    """
    if not isinstance(state, ParticleState):
        raise TypeError(f"state must be a ParticleState, got {type(state).__name__}")
    check_divisible(state.capacity, mesh, "the particle capacity")
    return place(state, split_sharding(mesh))


@eqx.filter_jit
def sharded_step(
    key: Array,
    state: ParticleState,
    frame: Frame,
    scene: SceneGraph,
    config: StepConfig,
    mesh: Mesh,
) -> tuple[ParticleState, StepInfo]:
    """:func:`jaxloc.sg2loc.step` with the particle state split over ``mesh`` in and out.

    Pass a state from :func:`shard_particles`; ``frame``, ``scene`` and ``config`` may be host
    arrays or replicated ones (:func:`~jaxloc.sharding.replicate`).
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
    """:func:`jaxloc.sg2loc.run_pass` (``lax.scan`` over T frames) with the particles split
    over ``mesh``; same keys, same result as the single-device pass (see :mod:`jaxloc.sharding`)."""
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
