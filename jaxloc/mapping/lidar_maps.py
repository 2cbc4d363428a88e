"""Instance and road-surface-normal maps built from a labelled LiDAR sequence (TripletLoc's recipe).

The scans come from a sequence folder (:class:`~jaxloc.io.LidarSequence`) or any recording of
:func:`jaxloc.io.open_lidar_recording` (a bag among them), placed by their poses. Every
``every``-th scan is read; its trunk, pole and traffic-sign points are clustered into
instance centroids (:func:`cluster_instances`: 0.1 m voxels, 0.5 m euclidean clusters of >= 20
voxel points), moved to the map frame with the scan's pose, and the centroids of all scans are
fused within ``fuse_radius`` (0.5 m, transitively; mean position, the label of the member with
most points).

Road surface normals (RSN): the road points of each used scan within ``max_range`` (80 m) of the
sensor are moved to the map frame, voxel down-sampled (``road_voxel``) and binned into a
``cell_size`` (10 m) xy grid of the map frame; each cell with at least ``min_cell_points`` gets a
robust plane fit (:func:`fit_plane`: RANSAC, then total least squares re-fitted on the points
within 3 MADs of the plane; normal pointing up). The per-scan cell estimates within
``normal_fuse_radius`` (3.5 m) of each other are fused: mean xy, the normalised mean normal,
and the root mean square angle (degrees) between the estimates and that mean (0 for a cell seen
once). The result is what ``RSN/road_normal.txt``
holds (``x y nx ny nz std_deg``).
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from typing import NamedTuple

import numpy as np

from jaxloc.io.lidar_recording import LidarRecording
from jaxloc.io.lidar_sequence import LidarSequence, read_sequence_scan
from jaxloc.m2loc import ClusterConfig, Instances, RoadNormals, cluster_instances
from jaxloc.m2loc._clusters import euclidean_clusters, fuse_instances, voxel_downsample

#: SemanticKITTI's road class (raw id 40, learning id 9) in TripletLoc's numbering (SPVNAS's 8).
ROAD = 8


class MapBuildConfig(NamedTuple):
    """Parameters of :func:`build_lidar_maps` (metres and point counts).

    Attributes:
        every: use every ``every``-th scan (TripletLoc: 30).
        clusters: per-scan instance clustering (classes, voxel size, tolerance, minimum size).
        fuse_radius: instances of all scans closer than this are fused.
        road_classes: class ids of the road surface.
        max_range: road points farther than this from the sensor are ignored.
        road_voxel: voxel size of the road points before the plane fits.
        cell_size: xy grid cell of the plane fits (map frame).
        min_cell_points: a cell needs at least this many road voxels in one scan.
        normal_fuse_radius: per-scan cell estimates closer than this are fused.
    """

    every: int = 30
    clusters: ClusterConfig = ClusterConfig()
    fuse_radius: float = 0.5
    road_classes: tuple[int, ...] = (ROAD,)
    max_range: float = 80.0
    road_voxel: float = 0.2
    cell_size: float = 10.0
    min_cell_points: int = 30
    normal_fuse_radius: float = 3.5


class LidarMaps(NamedTuple):
    """What :func:`build_lidar_maps` returns: ``instances`` (map frame), ``road_normals`` (RSN
    cells), ``scans_used`` the indices of the scans read."""

    instances: Instances
    road_normals: RoadNormals
    scans_used: np.ndarray


def fit_plane(
    points: np.ndarray, threshold: float = 0.05, hypotheses: int = 64, rounds: int = 3
) -> tuple[np.ndarray, np.ndarray]:
    """Robust plane through points (N, 3), N >= 3: RANSAC (``hypotheses`` 3-point planes drawn
    with a fixed seed, so the fit is deterministic; the one with most points within
    ``threshold``), then total least squares on its inliers, re-fitted ``rounds`` times on the
    points within 3 MADs (at least ``threshold``) of the current plane.

    Returns:
        ``normal`` (3,) unit, pointing up (nz >= 0), and the inlier mask (N,).
    """
    rng = np.random.default_rng(0)
    triples = points[rng.integers(0, points.shape[0], (hypotheses, 3))]
    normals = np.cross(triples[:, 1] - triples[:, 0], triples[:, 2] - triples[:, 0])
    lengths = np.linalg.norm(normals, axis=1)
    normals = normals / np.where(lengths > 0, lengths, 1.0)[:, None]
    distance = np.abs(
        np.einsum("hd,nd->hn", normals, points) - np.sum(normals * triples[:, 0], 1)[:, None]
    )
    support = np.where(lengths > 1e-9, np.sum(distance <= threshold, axis=1), -1)
    inliers = distance[np.argmax(support)] <= threshold
    if inliers.sum() < 3:
        inliers = np.ones(points.shape[0], bool)
    for _ in range(rounds):
        centre = points[inliers].mean(axis=0)
        normal = np.linalg.svd(points[inliers] - centre, full_matrices=False)[2][-1]
        residual = np.abs((points - centre) @ normal)
        mad = np.median(residual[inliers])
        keep = residual <= max(3.0 * 1.4826 * mad, threshold)
        if keep.sum() < 3 or np.array_equal(keep, inliers):
            break
        inliers = keep
    return (normal if normal[2] >= 0 else -normal), inliers


def scan_road_cells(
    road_map: np.ndarray, sensor: np.ndarray, config: MapBuildConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Plane fits of one scan's road points (M, 3), map frame, per ``cell_size`` xy cell.

    Returns:
        ``xy`` (C, 2) mean xy of each fitted cell's inliers and ``normals`` (C, 3).
    """
    near = np.linalg.norm(road_map[:, :2] - sensor[:2], axis=1) <= config.max_range
    voxels = voxel_downsample(road_map[near], config.road_voxel)
    if voxels.shape[0] < max(config.min_cell_points, 3):
        return np.zeros((0, 2)), np.zeros((0, 3))
    keys = np.floor(voxels[:, :2] / config.cell_size).astype(np.int64)
    _, cell, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    cell = cell.reshape(-1)
    centres, normals = [], []
    for index in np.flatnonzero(counts >= max(config.min_cell_points, 3)):
        members = voxels[cell == index]
        normal, inliers = fit_plane(members)
        centres.append(members[inliers, :2].mean(axis=0))
        normals.append(normal)
    return np.reshape(centres, (-1, 2)), np.reshape(normals, (-1, 3))


def fuse_road_cells(xy: np.ndarray, normals: np.ndarray, radius: float) -> RoadNormals:
    """Fuse per-scan cell estimates (C, 2) / (C, 3) within ``radius`` (transitively): mean xy,
    normalised mean normal, RMS angle to it in degrees."""
    fused_xy, fused_normals, std_deg = [], [], []
    for group in euclidean_clusters(np.column_stack([xy, np.zeros(len(xy))]), radius, 1):
        mean = normals[group].mean(axis=0)
        mean /= np.linalg.norm(mean)
        angles = np.degrees(np.arccos(np.clip(normals[group] @ mean, -1.0, 1.0)))
        fused_xy.append(xy[group].mean(axis=0))
        fused_normals.append(mean)
        std_deg.append(float(np.sqrt(np.mean(angles**2))))
    return RoadNormals(
        np.reshape(fused_xy, (-1, 2)), np.reshape(fused_normals, (-1, 3)), np.asarray(std_deg)
    )


def build_lidar_maps(
    sequence: LidarSequence | LidarRecording,
    config: MapBuildConfig | None = None,
    progress: Callable[[int], None] | None = None,
) -> LidarMaps:
    """Instance map and RSN map of a labelled sequence (see the module docstring).

    Args:
        sequence: the scans and their ``T_map_scan`` poses: a sequence folder
            (:func:`~jaxloc.io.lidar_sequence.open_lidar_sequence`, any layout) or a recording
            (:func:`~jaxloc.io.open_lidar_recording`: a bag, folders, scan files), placed by its
            poses (a bag's ``gt=`` or ``gt_topic=``), else by its own odometry (a bag's: the map
            is then in the odometry's frame); scans without a pose are left out.
        config: build parameters.
        progress: called with 1 after each scan read (e.g. a tqdm bar's ``update``).

    Raises:
        ValueError: a sequence without poses, a bad scan (the loader names the file), or no
            instance in any used scan.
    """
    config = MapBuildConfig() if config is None else config
    if config.every < 1:
        raise ValueError(f"every must be >= 1, got {config.every}")
    read, poses, has_pose, name = _posed_scans(sequence)
    used = np.arange(0, len(poses), config.every)
    used = used[has_pose[used]]
    centroids, labels, sizes, cell_xy, cell_normals = [], [], [], [], []
    for index in used:
        scan = read(int(index))
        pose = poses[index]
        found = cluster_instances(scan.points, scan.labels, config.clusters)
        centroids.append(found.points @ pose[:3, :3].T + pose[:3, 3])
        labels.append(found.labels)
        sizes.append(found.sizes)
        road = np.isin(scan.labels, config.road_classes)
        road_map = scan.points[road].astype(np.float64) @ pose[:3, :3].T + pose[:3, 3]
        xy, normals = scan_road_cells(road_map, pose[:3, 3], config)
        cell_xy.append(xy)
        cell_normals.append(normals)
        if progress is not None:
            progress(1)
    points = np.concatenate(centroids)
    if points.shape[0] == 0:
        raise ValueError(
            f"{name}: no instance of the classes {config.clusters.classes} in the "
            f"{used.size} scan(s) used (every {config.every})"
        )
    instances = fuse_instances(
        points, np.concatenate(labels), np.concatenate(sizes), config.fuse_radius
    )
    road_normals = fuse_road_cells(
        np.concatenate(cell_xy), np.concatenate(cell_normals), config.normal_fuse_radius
    )
    return LidarMaps(instances, road_normals, used)


def _posed_scans(source: LidarSequence | LidarRecording):
    """``(read, poses, has_pose, name)``: ``read(i)`` gives scan i's labelled points, ``poses``
    (N, 4, 4) its ``T_map_scan`` where ``has_pose`` (N,) bool, ``name`` the source for errors."""
    if isinstance(source, LidarSequence):
        if source.T_map_scan is None:
            raise ValueError(f"{source.root}: the sequence has no poses")
        poses = source.T_map_scan
        return partial(read_sequence_scan, source), poses, np.ones(len(poses), bool), source.root
    name = source.sequences[0].root if source.sequences else source.paths[0]
    name = source.bag.path if source.bag is not None else name
    if source.poses is not None:
        return source.scan, source.poses, np.asarray(source.has_pose, bool), name
    if source.odometry is None:
        raise ValueError(
            f"{name}: no poses to place the scans by (its pose file, gt=, gt_topic=, odometry)"
        )
    return source.scan, source.odometry, np.ones(len(source), bool), name
