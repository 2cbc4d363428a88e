"""The described instance map (:class:`TripletMap`), built once by :func:`build_map` for every
query."""

from __future__ import annotations

import dataclasses
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from jaxloc._traced import concrete
from jaxloc.m2loc._config import TripletConfig, m2loc_config
from jaxloc.m2loc._descriptors import describe_map
from jaxloc.m2loc._hypotheses import MapGrid, host_map_grid, map_grid
from jaxloc.m2loc._road_normals import RoadNormals


def _per_scale(descriptors) -> tuple[Array, ...]:
    """(S, Nm, D) stacked descriptors, or S arrays (Nm, D), as a tuple of S arrays."""
    if isinstance(descriptors, (tuple, list)):
        return tuple(descriptors)
    return tuple(descriptors[s] for s in range(descriptors.shape[0]))


class TripletMap(eqx.Module):
    """A described instance map (a pytree; build with :func:`build_map`).

    Attributes:
        points: (Nm, 3) float32 vertices, map frame minus ``origin`` (metres).
        classes: (Nm,) int32 class positions (index into ``config.descriptor.classes``).
        descriptors: S arrays (Nm, D) float32, one per scale (a stacked (S, Nm, D) array is split
            on construction: each scale's matching then reads its own buffer, where slicing a
            stacked array under jit copies it, 3x the matching time on DCC04); valid: (S, Nm)
            bool.
        origin: (3,) float32, subtracted from map coordinates (precision).
        rsn_xy: (M, 2) float32 RSN cell centres minus origin; rsn_normals: (M, 3) unit normals;
            rsn_sigma: (M,) float32 prior sigma (radians, the cell's normal std plus
            ``config.rot_delta_deg``). M = 1 dummy cell when absent.
        has_rsn: static bool.
        config: the configuration the queries run with: its description settings
            (``config.descriptor``) are the descriptors', its query settings can be swapped
            (:func:`with_config`).
        grid: the vertices sorted into XY cells (of static side ``grid.cell``, at least
            ``config.verify_radius``) for the hypotheses' verification (:func:`map_grid`;
            :func:`build_map`, :func:`~jaxloc.io.load_triplet_map` and :func:`with_config` build
            it). Rebuild it if you replace ``points`` or ``classes``.
    """

    points: Array
    classes: Array
    descriptors: tuple[Array, ...] = eqx.field(converter=_per_scale)
    valid: Array
    origin: Array
    rsn_xy: Array
    rsn_normals: Array
    rsn_sigma: Array
    has_rsn: bool = eqx.field(static=True)
    config: TripletConfig
    grid: MapGrid | None = None


#: The smallest sigma (radians) of the road-normal prior.
RSN_MIN_SIGMA = 1e-4


class SmallMapWarning(UserWarning):
    """A per-map size of the configuration (``top_k``) was larger than the map and was clamped
    to what the map holds."""


def fit_config_to_map(
    config: TripletConfig, num_vertices: int, stacklevel: int = 2
) -> TripletConfig:
    """``config`` with ``top_k`` clamped to ``num_vertices`` (a map of 19 vertices cannot give 25
    matches per scan vertex), with a :class:`SmallMapWarning` when it changes anything; the
    other sizes (clique seeds, hypotheses, the clique solver's tiers) are bounded by the
    association count where they are used."""
    if config.top_k <= num_vertices or num_vertices < 1:
        return config
    warnings.warn(
        f"top_k={config.top_k} exceeds the {num_vertices} map vertices; using top_k={num_vertices}",
        SmallMapWarning,
        stacklevel=stacklevel + 1,
    )
    return dataclasses.replace(config, top_k=num_vertices)


def with_config(triplet_map: TripletMap, config: TripletConfig) -> TripletMap:
    """``triplet_map`` with ``config``'s query settings (thresholds, radii, losses, switches and
    sizes of the query; its ``config`` replaced): what :func:`~jaxloc.m2loc.localize_scan`,
    :func:`~jaxloc.m2loc.query` and the batch and drive calls run with when given a config.

    Only the description settings must agree with the map's (``config.descriptor``: the
    descriptors were computed with them). Swapping configurations that differ only in traced
    settings compiles nothing; ``config`` may hold tracers (inside a user's ``jit`` or ``vmap``).
    ``top_k`` is fitted to the map (:func:`fit_config_to_map`), the road-normal prior's sigmas
    follow ``rot_delta_deg``, and a concrete ``verify_radius`` larger than the map grid's cell
    gets a grid of that cell, built on the host (a new static shape, compiled once). A traced
    radius uses the map's grid as it is: exact up to ``triplet_map.grid.cell``, above it the
    hypotheses' verification can only count fewer vertices.

    Raises:
        ValueError: ``config.descriptor`` differs from the map's, naming both.
    """
    old = triplet_map.config
    if config.descriptor != old.descriptor:
        raise ValueError(
            f"the config's descriptor settings {config.descriptor} differ from the map's "
            f"{old.descriptor}: describe the map again (build_map) with them"
        )
    config = fit_config_to_map(config, int(triplet_map.points.shape[0]), stacklevel=2)
    sigma = triplet_map.rsn_sigma
    if not (concrete(config.rot_delta_deg) and np.all(config.rot_delta_deg == old.rot_delta_deg)):
        shift = jnp.deg2rad(jnp.asarray(config.rot_delta_deg) - old.rot_delta_deg)
        sigma = jnp.maximum(sigma + shift, RSN_MIN_SIGMA)
    grid = triplet_map.grid
    radius = config.verify_radius
    if concrete(radius) and (grid is None or grid.cell < float(radius)):
        if concrete(triplet_map.points, triplet_map.classes):
            grid = host_map_grid(
                np.asarray(triplet_map.points), np.asarray(triplet_map.classes), float(radius)
            )
        else:
            grid = map_grid(triplet_map.points, triplet_map.classes, float(radius))
    return dataclasses.replace(triplet_map, config=config, rsn_sigma=sigma, grid=grid)


def verification_grid(triplet_map: TripletMap) -> MapGrid:
    """The map's grid for verifying poses with ``config.verify_radius``: ``triplet_map.grid``,
    or, where it is missing or its cell is smaller than a concrete radius, one built under the
    trace.

    Raises:
        ValueError: the map has no grid and the radius is traced.
    """
    grid, radius = triplet_map.grid, triplet_map.config.verify_radius
    if grid is not None and not (concrete(radius) and grid.cell < float(radius)):
        return grid
    if not concrete(radius):
        raise ValueError("a TripletMap without a grid needs a concrete verify_radius (build_map)")
    return map_grid(triplet_map.points, triplet_map.classes, float(radius))


def check_points_labels(
    points, labels, classes: tuple[int, ...], what: str
) -> tuple[np.ndarray, np.ndarray]:
    """Validated (N, 3) float64 points and (N,) int64 labels of a map or scan (``what`` names it
    in errors): shapes, finite values, known classes, no duplicate points. Raises ValueError."""
    points = np.asarray(points)
    labels = np.asarray(labels)
    if points.ndim != 2 or points.shape[-1] != 3:
        raise ValueError(f"{what} points must have shape (N, 3), got {points.shape}")
    if labels.shape != (points.shape[0],):
        raise ValueError(f"{what} labels must have shape ({points.shape[0]},), got {labels.shape}")
    if not np.issubdtype(labels.dtype, np.integer):
        raise ValueError(f"{what} labels must be integer class ids, got dtype {labels.dtype}")
    if not np.all(np.isfinite(points)):
        raise ValueError(f"{what} points contain NaN or inf")
    unknown = np.setdiff1d(np.unique(labels), np.asarray(classes))
    if unknown.size:
        raise ValueError(f"{what} labels {unknown.tolist()} are not in the classes {classes}")
    if points.shape[0] > 1:
        unique = np.unique(points, axis=0)
        if unique.shape[0] != points.shape[0]:
            raise ValueError(
                f"{what} has {points.shape[0] - unique.shape[0]} duplicate point(s); fuse "
                "coincident instances first (jaxloc.m2loc.fuse_instances)"
            )
    return points.astype(np.float64), labels.astype(np.int64)


def build_map(
    map_points: np.ndarray,
    map_labels: np.ndarray,
    config: TripletConfig | None = None,
    road_normals: RoadNormals | None = None,
) -> TripletMap:
    """Describe an instance map once, for reuse by every query.

    Args:
        map_points: (N, 3) instance centroids, map frame, metres.
        map_labels: (N,) int class ids (e.g. 15 trunk, 17 pole, 18 traffic sign).
        config: localization configuration (default M2Loc, ``m2loc_config(3)``; TripletLoc is
            ``tripletloc_config()``).
        road_normals: optional RSN cells for the roll/pitch prior.

    Raises:
        ValueError: bad shapes, NaN/inf, unknown labels, duplicates, or fewer than 3 vertices.

    Warns:
        SmallMapWarning: ``config.top_k`` exceeds the vertex count; the map keeps a copy of
            ``config`` with ``top_k`` equal to the vertex count (:func:`fit_config_to_map`).
    """
    config = m2loc_config(3) if config is None else config
    classes = config.descriptor.classes
    points, labels = check_points_labels(map_points, map_labels, classes, "map")
    if points.shape[0] < 3:
        raise ValueError(f"a map needs at least 3 vertices, got {points.shape[0]}")
    config = fit_config_to_map(config, points.shape[0], stacklevel=2)
    positions = np.searchsorted(np.sort(classes), labels)
    positions = np.argsort(classes)[positions]
    origin = points.mean(axis=0)
    descriptors, valid = describe_map(points - origin, positions, config.descriptor)
    if road_normals is not None and len(road_normals.xy):
        rsn_xy = road_normals.xy - origin[:2]
        normals = road_normals.normals
        sigma = np.deg2rad(road_normals.std_deg + config.rot_delta_deg)
        has_rsn = True
    else:
        rsn_xy, normals, sigma, has_rsn = (
            np.zeros((1, 2)),
            np.array([[0.0, 0, 1]]),
            np.ones(1),
            False,
        )

    # Host arrays go to the device as they are (device_put): jnp.asarray would compile a small
    # conversion program per array shape, each costing a first run ~10-30 ms.
    def device(array, dtype):
        return jax.device_put(np.asarray(array, dtype))

    centred = np.asarray(points - origin, np.float32)
    positions = np.asarray(positions, np.int32)
    return TripletMap(
        points=jax.device_put(centred),
        classes=jax.device_put(positions),
        descriptors=tuple(device(d, np.float32) for d in descriptors),
        valid=device(valid, bool),
        origin=device(origin, np.float32),
        rsn_xy=device(rsn_xy, np.float32),
        rsn_normals=device(normals, np.float32),
        rsn_sigma=device(np.maximum(sigma, RSN_MIN_SIGMA), np.float32),
        has_rsn=has_rsn,
        config=config,
        grid=host_map_grid(centred, positions, float(config.verify_radius)),
    )


def triplet_map_spec(
    map_points: np.ndarray,
    map_labels: np.ndarray,
    config: TripletConfig,
    road_normals: RoadNormals | None = None,
) -> TripletMap:
    """What :func:`build_map` of the same arguments will return, before it describes the map: a
    :class:`TripletMap` of ``jax.ShapeDtypeStruct`` leaves with the same static parts (``config``
    fitted to the map, ``has_rsn``, the grid's cell), for compiling the query programs while the
    map is described (:func:`~jaxloc.m2loc.prepare_queries`).

    Raises:
        ValueError: as :func:`build_map` for a map it refuses (checked in milliseconds).
    """
    classes = config.descriptor.classes
    num_vertices = check_points_labels(map_points, map_labels, classes, "map")[0].shape[0]
    if num_vertices < 3:
        raise ValueError(f"a map needs at least 3 vertices, got {num_vertices}")
    with warnings.catch_warnings():  # build_map warns about a clamped top_k itself
        warnings.simplefilter("ignore", SmallMapWarning)
        config = fit_config_to_map(config, num_vertices)
    cells = 0 if road_normals is None else len(road_normals.xy)
    rows = max(cells, 1)  # one dummy cell without normals

    def shape(*dims: int, dtype=np.float32) -> jax.ShapeDtypeStruct:
        return jax.ShapeDtypeStruct(dims, dtype)

    points, classes = shape(num_vertices, 3), shape(num_vertices, dtype=np.int32)
    scales = config.descriptor.num_scales
    return TripletMap(
        points=points,
        classes=classes,
        descriptors=tuple(shape(num_vertices, config.descriptor.dim) for _ in range(scales)),
        valid=shape(scales, num_vertices, dtype=bool),
        origin=shape(3),
        rsn_xy=shape(rows, 2),
        rsn_normals=shape(rows, 3),
        rsn_sigma=shape(rows),
        has_rsn=cells > 0,
        config=config,
        grid=jax.eval_shape(map_grid, points, classes, float(config.verify_radius)),
    )
