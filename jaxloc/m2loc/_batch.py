"""Many LiDAR queries at once: one vmapped, jitted call per batch, split over the devices."""

from __future__ import annotations

import time
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh

from jaxloc.m2loc._localization import (
    LocalizationResult,
    check_points_labels,
    invalid_result,
    query_capacity,
)
from jaxloc.m2loc._map import TripletMap
from jaxloc.m2loc._query import describe_query, register_query
from jaxloc.sharding import shard_batch


def localize_scans(
    triplet_map: TripletMap,
    scans: Sequence[tuple[np.ndarray, np.ndarray]],
    mesh: Mesh,
    capacity: int | None = None,
) -> list[LocalizationResult]:
    """:func:`jaxloc.m2loc.localize_scan` for many scans at once, split over ``mesh``.

    Every scan is validated as :func:`~jaxloc.m2loc.localize_scan` does, padded to one
    capacity (default: the map config's ``query_capacity``, else the next power of two >= 32 of
    the largest scan) and the batch is padded with empty scans to a multiple of the device count;
    one vmapped, jitted call describes and registers them all. Scans with fewer than 3 vertices
    give ``valid = False``.

    Args:
        triplet_map: a map from :func:`jaxloc.m2loc.build_map`.
        scans: a list of (points (Nq, 3) scan frame metres, labels (Nq,) int class ids).
        mesh: the device mesh (:func:`jaxloc.sharding.device_mesh`).
        capacity: static padded query size (must hold the largest scan).

    Returns:
        One :class:`~jaxloc.m2loc.LocalizationResult` per scan; its ``descriptor_time_ms`` and
        ``match_time_ms`` are the batch's times divided by the number of scans.

    Raises:
        ValueError: a bad scan (as :func:`~jaxloc.m2loc.localize_scan`), or a scan larger than
            ``capacity`` (naming the capacity to raise).
    """
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
            results.append(invalid_result())
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
                ambiguous=bool(out.ambiguous[b]),
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
