"""Synthetic outdoor instance maps (roads, poles, trunks, signs) and scan-like queries from maps.

World frame: z up, metres. Class ids as in TripletLoc (15 trunk, 17 pole, 18 traffic sign).

* :func:`make_outdoor_world` builds a road grid with a gently sloped terrain, poles along the
  roadsides, tree rows and clusters (trunks), signs near intersections, and a long repetitive
  "bridge" stretch with poles at a fixed spacing on both sides (the hard case of the paper).
  "sparse" and "dense" presets differ in object spacing. Road-surface-normal cells
  (``RoadNormals``) are sampled along the roads, as in the HeLiPR maps.
* :func:`make_query` turns any instance map with RSN cells (synthetic or the real HeLiPR maps) into
  a query that looks like one scan: a pose on the road, the map vertices within a 40-60 m radius
  with 50-80 % of them dropped, 0.2-0.5 m jitter, 10-30 % spurious vertices with random labels,
  and a random ``T_map_scan`` (uniform yaw, roll/pitch from the road normal plus a little noise).
"""

from __future__ import annotations

from typing import Literal, NamedTuple

import numpy as np

from jaxloc.m2loc import RoadNormals
from jaxloc.m2loc._classes import GRAPH_CLASSES, POLE, TRAFFIC_SIGN, TRUNK


class OutdoorWorld(NamedTuple):
    """A synthetic instance map: ``points`` (N, 3) float64, ``labels`` (N,) int32 class ids,
    ``road_normals`` RSN cells, ``bridge_box`` (4,) xmin, xmax, ymin, ymax of the bridge stretch."""

    points: np.ndarray
    labels: np.ndarray
    road_normals: RoadNormals
    bridge_box: np.ndarray


class Query(NamedTuple):
    """A scan-like query: ``points`` (Nq, 3) float64 in the scan frame, ``labels`` (Nq,) int32,
    ``T_map_scan`` (4, 4) float64 ground truth, ``map_index`` (Nq,) int64 source map vertex or -1
    for a spurious vertex, ``radius`` (m), ``jitter`` (m, rms 3D displacement)."""

    points: np.ndarray
    labels: np.ndarray
    T_map_scan: np.ndarray
    map_index: np.ndarray
    radius: float
    jitter: float


def _terrain_height(xy: np.ndarray) -> np.ndarray:
    return 3.0 * np.sin(xy[..., 0] / 180.0) + 2.0 * np.cos(xy[..., 1] / 140.0)


def _terrain_normal(xy: np.ndarray) -> np.ndarray:
    dzdx = 3.0 / 180.0 * np.cos(xy[..., 0] / 180.0)
    dzdy = -2.0 / 140.0 * np.sin(xy[..., 1] / 140.0)
    normal = np.stack([-dzdx, -dzdy, np.ones_like(dzdx)], axis=-1)
    return normal / np.linalg.norm(normal, axis=-1, keepdims=True)


def _roadside(rng, start, end, spacing, offset, jitter) -> np.ndarray:
    """Points along both sides of a road segment (xy), ``spacing`` apart with random jitter."""
    start, end = np.asarray(start, float), np.asarray(end, float)
    length = np.linalg.norm(end - start)
    direction = (end - start) / length
    side = np.array([-direction[1], direction[0]])
    positions = np.arange(rng.uniform(0, spacing), length, spacing)
    points = []
    for sign in (-1.0, 1.0):
        along = positions + rng.normal(0, jitter, positions.size)
        keep = rng.random(positions.size) > 0.15
        xy = (
            start
            + along[keep, None] * direction
            + sign * (offset + rng.normal(0, 0.3, keep.sum()))[:, None] * side
        )
        points.append(xy)
    return np.concatenate(points)


def make_outdoor_world(
    kind: Literal["sparse", "dense"] = "dense",
    seed: int = 0,
    blocks: int = 3,
    block_size: float = 200.0,
    bridge_length: float = 400.0,
) -> OutdoorWorld:
    """A synthetic outdoor instance map.

    Args:
        kind: "dense" (poles every ~6 m, tree rows every ~5 m, big parks) or "sparse" (poles every
            ~16 m, trees every ~14 m, small parks).
        seed: random seed (deterministic output).
        blocks: road grid of ``blocks x blocks`` city blocks.
        block_size: block edge in metres.
        bridge_length: length of the repetitive bridge stretch east of the grid (0 disables).

    Returns:
        An :class:`OutdoorWorld`.
    """
    if kind not in ("sparse", "dense"):
        raise ValueError(f"kind must be 'sparse' or 'dense', got {kind!r}")
    rng = np.random.default_rng(seed)
    dense = kind == "dense"
    pole_spacing, tree_spacing = (6.0, 5.0) if dense else (16.0, 14.0)
    extent = blocks * block_size
    lines = [((0.0, c), (extent, c)) for c in np.arange(0, extent + 1, block_size)]
    lines += [((c, 0.0), (c, extent)) for c in np.arange(0, extent + 1, block_size)]
    xy, labels = [], []
    for start, end in lines:
        poles = _roadside(rng, start, end, pole_spacing, 6.0, 2.0)
        xy.append(poles)
        labels.append(np.full(len(poles), POLE))
        trees = _roadside(rng, start, end, tree_spacing, 9.0, 3.0)
        trees = trees[rng.random(len(trees)) < (0.8 if dense else 0.5)]
        xy.append(trees)
        labels.append(np.full(len(trees), TRUNK))
    corners = np.array(
        [
            (a, b)
            for a in np.arange(0, extent + 1, block_size)
            for b in np.arange(0, extent + 1, block_size)
        ]
    )
    for corner in corners:
        count = rng.integers(1, 5 if dense else 3)
        signs = corner + rng.choice([-1, 1], (count, 2)) * rng.uniform(6, 14, (count, 2))
        xy.append(signs)
        labels.append(np.full(count, TRAFFIC_SIGN))
    parks = rng.uniform(0.15 * block_size, extent - 0.15 * block_size, (blocks * 2, 2))
    for park in parks:
        count = rng.integers(10, 30) if dense else rng.integers(3, 8)
        xy.append(park + rng.normal(0, 18, (count, 2)))
        labels.append(np.full(count, TRUNK))
    road_cells = [
        np.linspace(s, e, int(np.linalg.norm(np.subtract(e, s)) // 10) + 1) for s, e in lines
    ]
    bridge_box = np.zeros(4)
    if bridge_length > 0:
        y0 = block_size
        start, end = (extent, y0), (extent + bridge_length, y0)
        positions = np.arange(5.0, bridge_length, 15.0)
        for sign in (-1.0, 1.0):
            bridge = np.stack(
                [
                    extent + positions + rng.normal(0, 0.2, positions.size),
                    np.full(positions.size, y0 + sign * 7.0),
                ],
                axis=1,
            )
            xy.append(bridge)
            labels.append(np.full(positions.size, POLE))
        road_cells.append(np.linspace(start, end, int(bridge_length // 10) + 1))
        bridge_box = np.array([extent, extent + bridge_length, y0 - 10.0, y0 + 10.0])
    xy = np.concatenate(xy)
    labels = np.concatenate(labels).astype(np.int32)
    heights = np.where(
        labels == TRUNK,
        rng.uniform(0.8, 2.0, len(labels)),
        np.where(
            labels == POLE, rng.uniform(2.5, 4.5, len(labels)), rng.uniform(2.0, 3.0, len(labels))
        ),
    )
    points = np.column_stack([xy, _terrain_height(xy) + heights])
    points, unique = np.unique(np.round(points, 3), axis=0, return_index=True)
    labels = labels[unique]
    cells = np.unique(np.round(np.concatenate(road_cells), 3), axis=0)
    normals = _terrain_normal(cells)
    std = rng.uniform(0.3, 1.2, len(cells))
    return OutdoorWorld(points, labels, RoadNormals(cells, normals, std), bridge_box)


def _rotation_to(normal: np.ndarray) -> np.ndarray:
    """Smallest rotation (3, 3) taking +z to the unit ``normal``."""
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(z, normal)
    s, c = np.linalg.norm(axis), float(np.dot(z, normal))
    if s < 1e-12:
        return np.eye(3)
    k = axis / s
    skew = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + s * skew + (1 - c) * skew @ skew


def _rot_z(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def make_query(
    map_points: np.ndarray,
    map_labels: np.ndarray,
    road_normals: RoadNormals,
    rng: np.random.Generator,
    *,
    radius_range: tuple[float, float] = (40.0, 60.0),
    drop_range: tuple[float, float] = (0.5, 0.8),
    jitter_range: tuple[float, float] = (0.2, 0.5),
    spurious_range: tuple[float, float] = (0.1, 0.3),
    tilt_noise_deg: float = 1.0,
    max_kept: int | None = None,
    classes: tuple[int, ...] = GRAPH_CLASSES,
) -> Query:
    """A scan-like query cut from an instance map around a random pose on the road.

    The sensor sits at a random RSN cell (plus up to 2 m), at the median height of the map vertices
    within 30 m; its up axis is the cell's road normal tilted by ``tilt_noise_deg`` (std per axis);
    yaw is uniform. Kept vertices get isotropic Gaussian jitter with rms 3D displacement drawn from
    ``jitter_range``; spurious vertices are uniform in the disc (heights 0.5-5 m above the sensor's
    ground height) with labels drawn uniformly from ``classes``.

    Args:
        map_points: (N, 3) map vertices (map frame). map_labels: (N,) class ids.
        road_normals: the map's RSN cells (query positions are drawn from them).
        rng: numpy random generator (the only source of randomness).
        max_kept: optional cap on the kept map vertices (a random subset), applied after the
            drop; the dense HeLiPR maps give 5x more vertices than a real scan holds without it.

    Returns:
        A :class:`Query` (points in the scan frame: ``p_scan = R^T (p_map - t)``).
    """
    map_points = np.asarray(map_points, np.float64)
    cell = rng.integers(len(road_normals.xy))
    centre_xy = road_normals.xy[cell] + rng.uniform(-2.0, 2.0, 2)
    pose = _sensor_pose(map_points, road_normals, cell, centre_xy, rng, tilt_noise_deg)
    cut = _Cut(radius_range, drop_range, jitter_range, spurious_range, max_kept, classes)
    return _cut_scan(map_points, map_labels, pose, rng, cut)


def make_drive(
    map_points: np.ndarray,
    map_labels: np.ndarray,
    road_normals: RoadNormals,
    rng: np.random.Generator,
    num_scans: int,
    *,
    spacing: float = 5.0,
    tilt_noise_deg: float = 1.0,
    **cut_options,
) -> list[Query]:
    """``num_scans`` consecutive scans of a drive, oldest first, each cut as :func:`make_query`.

    The first pose is drawn as in :func:`make_query`; each next one is ``spacing`` metres further
    along the heading (yaw plus a little steering noise), at the road cell nearest to it. Every
    scan draws its own radius, drop, jitter and spurious vertices (independent noise per scan;
    ``cut_options``: ``radius_range``, ``drop_range``, ``jitter_range``, ``spurious_range``,
    ``max_kept``, ``classes``, as in :func:`make_query`);
    ``T_map_scan`` of each is its ground truth, so ``inv(T_map_scan[j]) @ T_map_scan[i]`` is the
    odometry between two scans.
    """
    map_points = np.asarray(map_points, np.float64)
    cut = _Cut(**cut_options)
    cell = rng.integers(len(road_normals.xy))
    centre_xy = road_normals.xy[cell] + rng.uniform(-2.0, 2.0, 2)
    heading = rng.uniform(-np.pi, np.pi)
    scans = []
    for _ in range(num_scans):
        pose = _sensor_pose(map_points, road_normals, cell, centre_xy, rng, tilt_noise_deg, heading)
        scans.append(_cut_scan(map_points, map_labels, pose, rng, cut))
        heading += rng.normal(0.0, np.deg2rad(3.0))
        centre_xy = centre_xy + spacing * np.array([np.cos(heading), np.sin(heading)])
        cell = int(np.argmin(np.sum((road_normals.xy - centre_xy) ** 2, axis=1)))
    return scans


class _Cut(NamedTuple):
    """How a scan is cut from the map (see :func:`make_query`)."""

    radius_range: tuple[float, float] = (40.0, 60.0)
    drop_range: tuple[float, float] = (0.5, 0.8)
    jitter_range: tuple[float, float] = (0.2, 0.5)
    spurious_range: tuple[float, float] = (0.1, 0.3)
    max_kept: int | None = None
    classes: tuple[int, ...] = GRAPH_CLASSES


def _sensor_pose(map_points, road_normals, cell, centre_xy, rng, tilt_noise_deg, heading=None):
    """(4, 4) T_map_scan of a sensor at ``centre_xy`` on road cell ``cell`` (yaw ``heading`` or
    uniform), 1.8 m above the ground height (2 m under the median height of the map vertices
    within 30 m), and that ground height."""
    planar = np.linalg.norm(map_points[:, :2] - centre_xy, axis=1)
    near = planar < 30.0
    z = float(np.median(map_points[near, 2])) if near.any() else float(np.median(map_points[:, 2]))
    tilt = np.deg2rad(rng.normal(0.0, tilt_noise_deg, 2))
    small = _rotation_to(
        np.array([np.sin(tilt[0]), np.sin(tilt[1]), 1.0])
        / np.linalg.norm([np.sin(tilt[0]), np.sin(tilt[1]), 1.0])
    )
    yaw = rng.uniform(-np.pi, np.pi) if heading is None else heading
    ground = z - 2.0
    T = np.eye(4)
    T[:3, :3] = _rotation_to(road_normals.normals[cell]) @ small @ _rot_z(yaw)
    T[:3, 3] = [centre_xy[0], centre_xy[1], ground + 1.8]
    return T, ground


def _cut_scan(map_points, map_labels, pose, rng, cut: _Cut) -> Query:
    """The scan a sensor at ``pose = (T_map_scan, ground)`` sees: kept, jittered and spurious
    vertices."""
    T, ground = pose
    rotation, t = T[:3, :3], T[:3, 3]
    centre_xy = t[:2]
    planar = np.linalg.norm(map_points[:, :2] - centre_xy, axis=1)
    radius = float(rng.uniform(*cut.radius_range))
    visible = np.flatnonzero(planar < radius)
    keep = visible[rng.random(visible.size) >= rng.uniform(*cut.drop_range)]
    if cut.max_kept is not None and keep.size > cut.max_kept:
        keep = np.sort(rng.choice(keep, cut.max_kept, replace=False))
    jitter = float(rng.uniform(*cut.jitter_range))
    kept = map_points[keep] + rng.normal(0.0, jitter / np.sqrt(3.0), (keep.size, 3))
    n_spurious = int(round(rng.uniform(*cut.spurious_range) * keep.size))
    angle = rng.uniform(0, 2 * np.pi, n_spurious)
    r = radius * np.sqrt(rng.random(n_spurious))
    spurious = np.column_stack(
        [
            centre_xy[0] + r * np.cos(angle),
            centre_xy[1] + r * np.sin(angle),
            ground + rng.uniform(0.5, 5.0, n_spurious),
        ]
    )
    points_map = np.concatenate([kept, spurious])
    labels = np.concatenate(
        [np.asarray(map_labels)[keep], rng.choice(np.asarray(cut.classes), n_spurious)]
    ).astype(np.int32)
    index = np.concatenate([keep, np.full(n_spurious, -1)]).astype(np.int64)
    order = rng.permutation(points_map.shape[0])
    points_scan = (points_map[order] - t) @ rotation
    return Query(points_scan, labels[order], T, index[order], radius, jitter)
