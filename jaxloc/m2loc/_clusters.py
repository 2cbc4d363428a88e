"""Instance centroids from labelled points (host side, vectorised numpy/scipy).

TripletLoc's recipe: per class, a 0.1 m voxel grid (centroid of each occupied voxel), euclidean
clustering (0.5 m tolerance, >= 20 voxel points), centroids of the clusters; then centroids of all
classes within 0.5 m are fused (mean position, label of the member with most points).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import NamedTuple

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from jaxloc.m2loc._classes import GRAPH_CLASSES


class ClusterConfig(NamedTuple):
    """Clustering parameters (metres, point counts).

    Attributes:
        classes: class ids to cluster.
        voxel_size: voxel grid leaf size.
        tolerance: per-class euclidean cluster tolerance (a float for all classes or a mapping).
        min_points: per-class minimum voxel points per cluster (int or mapping).
        fuse_radius: instances of any class closer than this are fused.
    """

    classes: tuple[int, ...] = GRAPH_CLASSES
    voxel_size: float = 0.1
    tolerance: float | Mapping[int, float] = 0.5
    min_points: int | Mapping[int, int] = 20
    fuse_radius: float = 0.5


class Instances(NamedTuple):
    """Instance centroids: ``points`` (N, 3) float64, ``labels`` (N,) int32, ``sizes`` (N,) int64
    voxel-point counts (the largest member's count after fusion)."""

    points: np.ndarray
    labels: np.ndarray
    sizes: np.ndarray


def _per_class(value, class_id: int):
    return value[class_id] if isinstance(value, Mapping) else value


def voxel_downsample(points: np.ndarray, voxel_size: float) -> np.ndarray:
    """Centroids (V, 3) of the points (N, 3) in each occupied voxel of a grid of ``voxel_size``."""
    if points.shape[0] == 0:
        return np.zeros((0, 3), np.float64)
    keys = np.floor(points / voxel_size).astype(np.int64)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    sums = np.zeros((counts.size, 3), np.float64)
    np.add.at(sums, inverse, points)
    return sums / counts[:, None]


def euclidean_clusters(
    points: np.ndarray, tolerance: float, min_points: int = 1
) -> list[np.ndarray]:
    """Connected components of the ``tolerance``-neighbourhood graph of points (N, 3).

    Returns the index arrays of components with at least ``min_points`` members, largest first
    (PCL EuclideanClusterExtraction semantics, without a maximum size).
    """
    n = points.shape[0]
    if n == 0:
        return []
    pairs = cKDTree(points).query_pairs(tolerance, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs), np.int8), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    count, component = connected_components(graph, directed=False)
    sizes = np.bincount(component, minlength=count)
    order = np.argsort(component, kind="stable")
    groups = np.split(order, np.cumsum(sizes)[:-1])
    keep = [group for group in groups if group.size >= min_points]
    return sorted(keep, key=lambda group: -group.size)


def fuse_instances(
    points: np.ndarray, labels: np.ndarray, sizes: np.ndarray, radius: float
) -> Instances:
    """Fuse instances within ``radius`` (transitively): mean position, largest member's label."""
    groups = euclidean_clusters(points, radius, 1)
    fused_points = np.array([points[g].mean(axis=0) for g in groups]).reshape(-1, 3)
    largest = [g[np.argmax(sizes[g])] for g in groups]
    return Instances(
        fused_points, labels[largest].astype(np.int32), sizes[largest].astype(np.int64)
    )


def cluster_instances(
    points: np.ndarray, labels: np.ndarray, config: ClusterConfig | None = None
) -> Instances:
    """Instance centroids of the labelled points (N, 3) / (N,) of a scan (sensor frame, metres).

    Raises:
        ValueError: on shapes that do not match or non-finite points.
    """
    config = ClusterConfig() if config is None else config
    points = np.asarray(points, np.float64)
    labels = np.asarray(labels)
    if points.ndim != 2 or points.shape[1] != 3 or labels.shape != (points.shape[0],):
        raise ValueError(
            f"points must be (N, 3) and labels (N,), got {points.shape}, {labels.shape}"
        )
    if not np.all(np.isfinite(points)):
        raise ValueError("points contain NaN or inf")
    centroids, classes, sizes = [], [], []
    for class_id in config.classes:
        voxels = voxel_downsample(points[labels == class_id], config.voxel_size)
        clusters = euclidean_clusters(
            voxels,
            _per_class(config.tolerance, class_id),
            _per_class(config.min_points, class_id),
        )
        centroids += [voxels[c].mean(axis=0) for c in clusters]
        classes += [class_id] * len(clusters)
        sizes += [c.size for c in clusters]
    return fuse_instances(
        np.asarray(centroids, np.float64).reshape(-1, 3),
        np.asarray(classes, np.int32),
        np.asarray(sizes, np.int64),
        config.fuse_radius,
    )
