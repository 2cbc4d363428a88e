"""Spreading work over several devices with ``jax.sharding``: the mesh and placement helpers.

Nothing here changes how jaxloc computes: the helpers place arrays on a 1-D device
:class:`~jax.sharding.Mesh` (axis :data:`AXIS`) and the jitted functions of the library then run
sharded by XLA's sharding propagation. Three kinds of work split cleanly, each with its method:

* **particles** of one filter (:mod:`jaxloc.sg2loc.sharded`): the padded particle state is split
  along its capacity; each device renders and scores its own shard under ``jax.shard_map``;
  the weight normalisation, the KLD bin count and resampling are global (XLA inserts the
  collectives). :func:`jaxloc.sg2loc.localize` takes the same split with its ``mesh=`` argument.
* **independent sequences** (sweeps over seeds, episodes or settings):
  :func:`jaxloc.sg2loc.sharded.sharded_run_passes` splits a leading batch axis over the devices.
* **LiDAR queries**: :func:`jaxloc.m2loc.localize_scans` pads a list of scans to one capacity and
  runs the jitted query vmapped over the batch, split over the devices.

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
process feeding its own part of the batch) is described in the docs ("Many devices and hosts").
"""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

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


def place(tree, sharding: NamedSharding):
    """``jax.device_put`` of every array leaf of ``tree`` (static fields untouched)."""
    return jax.tree.map(lambda x: jax.device_put(x, sharding) if eqx.is_array(x) else x, tree)


def replicate(tree, mesh: Mesh):
    """Copy every array leaf of ``tree`` (a map, frames, a config) to every device of ``mesh``."""
    return place(tree, replicated_sharding(mesh))


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
    return place(tree, split_sharding(mesh))


def pin_split(tree, mesh: Mesh):
    """Inside a traced function: keep every array of ``tree`` split along its leading axis."""
    return jax.lax.with_sharding_constraint(tree, split_sharding(mesh))
