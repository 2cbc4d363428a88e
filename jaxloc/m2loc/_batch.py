"""Many LiDAR queries at once: one vmapped, jitted call per batch, split over the devices."""

from __future__ import annotations

import time
from collections.abc import Sequence

import equinox as eqx
import jax
import numpy as np
from jax.sharding import Mesh

from jaxloc.m2loc._config import TripletConfig
from jaxloc.m2loc._localization import (
    LocalizationResult,
    check_points_labels,
    host_result,
    invalid_result,
    query_capacity,
    registered,
)
from jaxloc.m2loc._map import TripletMap, with_config
from jaxloc.m2loc._query import describe_query
from jaxloc.sharding import shard_batch


def localize_scans(
    triplet_map: TripletMap,
    scans: Sequence[tuple[np.ndarray, np.ndarray]],
    mesh: Mesh | None = None,
    capacity: int | None = None,
    config: TripletConfig | None = None,
) -> list[LocalizationResult]:
    """:func:`jaxloc.m2loc.localize_scan` for many scans at once, on one device or split over
    ``mesh``.

    Every scan is validated as :func:`~jaxloc.m2loc.localize_scan` does, padded to one
    capacity (default: the config's ``query_capacity``, else the next power of two >= 32 of
    the largest scan) and, with a mesh, the batch is padded with empty scans to a multiple of the
    device count; one vmapped, jitted call describes and registers them all. Scans with fewer
    than 3 vertices give ``valid = False``.

    Args:
        triplet_map: a map from :func:`jaxloc.m2loc.build_map`.
        scans: a list of (points (Nq, 3) scan frame metres, labels (Nq,) int class ids).
        mesh: the device mesh (:func:`jaxloc.sharding.device_mesh`); None: the default device.
        capacity: static padded query size (must hold the largest scan).
        config: the query settings (None: the map's; :func:`~jaxloc.m2loc.with_config`).

    Returns:
        One :class:`~jaxloc.m2loc.LocalizationResult` per scan; its ``descriptor_time_ms`` and
        ``match_time_ms`` are the batch's times divided by the number of scans.

    Raises:
        ValueError: a bad scan (as :func:`~jaxloc.m2loc.localize_scan`), a scan larger than
            ``capacity`` (naming the capacity to raise), a ``config`` whose descriptor settings
            differ from the map's.
    """
    triplet_map = with_config(triplet_map, triplet_map.config if config is None else config)
    config = triplet_map.config
    classes = config.descriptor.classes
    checked = [
        check_points_labels(p, lab, classes, f"scan {i}") for i, (p, lab) in enumerate(scans)
    ]
    if not checked:
        return []
    largest = max(points.shape[0] for points, _ in checked)
    if capacity is None:
        capacity = query_capacity(max(largest, 1), config)
    if largest > capacity:
        raise ValueError(
            f"a scan has {largest} vertices, above the query capacity {capacity}: raise "
            "capacity= (or TripletConfig.query_capacity)"
        )
    count = 1 if mesh is None else mesh.devices.size
    batch = -(-len(checked) // count) * count
    points = np.zeros((batch, capacity, 3), np.float32)
    positions = np.zeros((batch, capacity), np.int32)
    mask = np.zeros((batch, capacity), bool)
    for b, (p, labels) in enumerate(checked):
        n = p.shape[0]
        points[b, :n] = p
        positions[b, :n] = [classes.index(int(label)) for label in labels]
        mask[b, :n] = n >= 3
    padded = jax.device_put((points, positions, mask))
    if mesh is not None:
        padded = shard_batch(padded, mesh)
    start = time.perf_counter()
    descriptors, valid = jax.block_until_ready(_describe_batch(*padded, config.descriptor))
    middle = time.perf_counter()
    out = jax.block_until_ready(_register_batch(triplet_map, *padded, descriptors, valid))
    end = time.perf_counter()
    out = jax.tree.map(np.asarray, out)
    share = 1e3 / len(checked)
    results = []
    for b, (p, _) in enumerate(checked):
        if p.shape[0] < 3:
            results.append(invalid_result())
            continue
        one = jax.tree.map(lambda x, b=b: x[b], out)
        results.append(host_result(one, share * (middle - start), share * (end - middle)))
    return results


@eqx.filter_jit
def _describe_batch(points, positions, mask, descriptor_config):
    return jax.vmap(describe_query, in_axes=(0, 0, 0, None))(
        points, positions, mask, descriptor_config
    )


@eqx.filter_jit
def _register_batch(triplet_map, points, positions, mask, descriptors, valid):
    return jax.vmap(registered, in_axes=(None, 0, 0, 0, 0, 0))(
        triplet_map, points, positions, descriptors, valid, mask
    )
