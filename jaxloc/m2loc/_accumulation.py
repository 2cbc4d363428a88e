"""Localize a drive, not a scan: the instances of the last K scans fused into one local submap.

A real scan holds few instances (13-20 trunks, poles and signs on KITTI 00), too few for a one-shot
place recognition to be sure. A robot has odometry: :func:`fuse_scans` expresses the instance
centroids of a window of scans in the newest scan's frame through their relative poses and merges
the copies of one object seen by several scans, and :func:`localize_window` localizes that submap
with :func:`~jaxloc.m2loc.localize_scan` (the pose is the newest scan's ``T_map_scan``), asking
it for a clique beyond the minimal set (:data:`WINDOW_MIN_CLIQUE`). On a sparse stretch of road
the last K scans may hold too few objects between them; :func:`grow_window` then adds older scans,
one at a time and up to the ones given, until the fused submap holds
:data:`WINDOW_MIN_INSTANCES` instances.

Merging: scans are taken newest first; an instance joins the nearest fused instance of its class
within ``merge_radius`` that no other instance of the same scan has joined (one object per scan:
two instances of one scan are two objects), else it starts a new one. A fused centroid is the mean
of its members, so an object seen by three scans counts once, with its noise averaged, never three
times. Host-side numpy, like :func:`~jaxloc.m2loc.localize_scan`'s own checks; the fused submap
then runs at the query capacity band of its size (no new program per window length).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from jaxloc.m2loc._localization import LocalizationResult, localize_scan
from jaxloc.m2loc._map import TripletMap

#: Instances of one class closer than this (metres, after odometry) are one object by default.
MERGE_RADIUS = 1.0
#: The smallest clique the pose of a fused window (two scans or more) may rest on. Three
#: associations are the minimal set: they fix a pose whatever the place, and only the verification
#: of the other vertices speaks for it, which a dense map passes by chance more often for a
#: window's 25-40 instances than for a scan's 13-20. On development drives (seeds 2000-4000,
#: ``experiments/m2loc_window_clique.py``) 4 kept 1003 of 1011 right window poses and refused the
#: one wrong one; for single scans it would have cost 38 of 154 right poses, so scans keep
#: ``TripletConfig.min_inliers``.
WINDOW_MIN_CLIQUE = 4
#: The fewest fused instances a window of K scans grows to (older scans added, up to the bound
#: the caller gives) before it is localized. Chosen on development drives (seeds 2000-4000, 360
#: drives, ``experiments/m2loc_window_growth.py``), windows of K to 2K scans: 18 raised the right
#: poses of K = 2 / 3 / 5 from 308 / 343 / 352 to 332 / 350 / 353 at 2.32 / 3.23 / 5.10 scans on
#: average, with no wrong pose nor false accept; 12 gained less (330 / 349 / 352), 24 more for
#: K = 2 (335) but let a foreign window of 10 scans through.
WINDOW_MIN_INSTANCES = 18


class FusedScans(NamedTuple):
    """A window of scans fused in the newest scan's frame.

    Attributes:
        points: (M, 3) float64 fused instance centroids, newest scan frame, metres.
        labels: (M,) int64 class ids.
        counts: (M,) int64 scans that saw each fused instance.
        members: (M, K) int64 index of the member instance in each scan (newest first), -1 where
            that scan did not see it.
    """

    points: np.ndarray
    labels: np.ndarray
    counts: np.ndarray
    members: np.ndarray


def _check_window(points, labels, poses) -> tuple[list, list, np.ndarray]:
    if not (len(points) == len(labels) == len(poses)) or len(points) == 0:
        raise ValueError(
            f"need one labels array and one pose per scan, got {len(points)} scans, "
            f"{len(labels)} label arrays and {len(poses)} poses"
        )
    clouds, classes = [], []
    for i, (p, c) in enumerate(zip(points, labels, strict=True)):
        p, c = np.asarray(p, np.float64), np.asarray(c)
        if p.ndim != 2 or p.shape[1] != 3 or c.shape != (p.shape[0],):
            raise ValueError(
                f"scan {i}: points must be (N, 3) and labels (N,), got {p.shape}, {c.shape}"
            )
        if not np.all(np.isfinite(p)):
            raise ValueError(f"scan {i}: points must be finite")
        if not np.issubdtype(c.dtype, np.integer):
            raise ValueError(f"scan {i}: labels must be integers, got {c.dtype}")
        clouds.append(p)
        classes.append(c.astype(np.int64))
    poses = np.asarray(poses, np.float64)
    if poses.shape != (len(clouds), 4, 4) or not np.all(np.isfinite(poses)):
        raise ValueError(f"poses must be ({len(clouds)}, 4, 4) finite, got {poses.shape}")
    rotations = poses[:, :3, :3]
    should_be_eye = np.einsum("kij,kil->kjl", rotations, rotations)
    if np.max(np.abs(should_be_eye - np.eye(3))) > 1e-4 or np.any(poses[:, 3] != [0, 0, 0, 1]):
        raise ValueError(
            "poses must be rigid 4x4 transforms (orthonormal rotation, last row 0 0 0 1)"
        )
    return clouds, classes, poses


def fuse_scans(
    points: list[np.ndarray],
    labels: list[np.ndarray],
    T_newest_scan: np.ndarray,
    merge_radius: float = MERGE_RADIUS,
) -> FusedScans:
    """Fuse the instance centroids of K scans into the newest scan's frame.

    Args:
        points: K arrays (N_k, 3) of instance centroids, each in its own scan frame (metres),
            newest scan first.
        labels: K arrays (N_k,) int class ids.
        T_newest_scan: (K, 4, 4) pose of each scan in the newest scan's frame (``[0]`` is the
            identity up to odometry noise): ``p_newest = T_newest_scan[k] @ p_scan_k``.
        merge_radius: instances of one class closer than this (metres) are one object.

    Returns:
        :class:`FusedScans`, the fused instances in the order they were first seen.

    Raises:
        ValueError: mismatched lengths, non-finite values, non-rigid poses, a negative radius.
    """
    clouds, classes, poses = _check_window(points, labels, T_newest_scan)
    if not merge_radius >= 0:
        raise ValueError(f"merge_radius must be >= 0, got {merge_radius}")
    num_scans = len(clouds)
    sums = np.zeros((0, 3))
    fused_labels = np.zeros(0, np.int64)
    members = np.zeros((0, num_scans), np.int64)
    for k, (cloud, cls, pose) in enumerate(zip(clouds, classes, poses, strict=True)):
        moved = cloud @ pose[:3, :3].T + pose[:3, 3]
        centres = sums / np.maximum(np.sum(members >= 0, axis=1), 1)[:, None]
        gap = np.linalg.norm(moved[:, None] - centres[None], axis=-1)  # (N_k, M)
        gap = np.where(cls[:, None] == fused_labels[None], gap, np.inf)
        # One-to-one: closest pairs first; each fused object takes one instance of this scan.
        joined = np.full(len(moved), -1)
        taken = np.zeros(len(centres), bool)
        for flat in np.argsort(gap, axis=None, kind="stable"):
            i, j = divmod(int(flat), len(centres))
            if gap[i, j] > merge_radius:
                break
            if joined[i] < 0 and not taken[j]:
                joined[i], taken[j] = j, True
        fresh = np.flatnonzero(joined < 0)
        joined[fresh] = len(centres) + np.arange(fresh.size)
        sums = np.concatenate([sums, np.zeros((fresh.size, 3))])
        fused_labels = np.concatenate([fused_labels, cls[fresh]])
        members = np.concatenate([members, np.full((fresh.size, num_scans), -1)])
        np.add.at(sums, joined, moved)
        members[joined, k] = np.arange(len(moved))
    counts = np.sum(members >= 0, axis=1)
    return FusedScans(sums / np.maximum(counts, 1)[:, None], fused_labels, counts, members)


def grow_window(
    points: list[np.ndarray],
    labels: list[np.ndarray],
    T_newest_scan: np.ndarray,
    least_scans: int,
    min_instances: int = WINDOW_MIN_INSTANCES,
    merge_radius: float = MERGE_RADIUS,
) -> FusedScans:
    """The fused submap of the newest ``least_scans`` scans, grown with the older scans given, one
    at a time, while it holds fewer than ``min_instances`` instances.

    Arguments as :func:`fuse_scans` (the scans given, newest first, bound the window: at most all
    of them are fused); ``least_scans`` >= 1 (all the scans given where fewer are: the start of a
    drive); ``min_instances`` >= 0 (0: exactly ``least_scans`` scans).

    Returns:
        :class:`FusedScans` of the first K' scans given, ``K' = members.shape[1]``: the fewest of
        at least ``least_scans`` whose fusion holds ``min_instances`` instances, else all.
    """
    everything = fuse_scans(points, labels, T_newest_scan, merge_radius)  # checks the scans first
    if least_scans < 1 or min_instances < 0:
        raise ValueError(
            f"need least_scans >= 1 and min_instances >= 0, got {least_scans}, {min_instances}"
        )
    # Scans are fused newest first and each merges only into what the newer ones built, so the
    # fusion of the first k scans holds the fused instances first seen by one of them.
    first_seen = np.argmax(everything.members >= 0, axis=1)
    held = np.cumsum(np.bincount(first_seen, minlength=len(points)))  # held[k - 1]: k scans
    least = min(least_scans, len(points))
    enough = np.flatnonzero(held[least - 1 :] >= min_instances)
    scans = least + int(enough[0]) if enough.size else len(points)
    if scans == len(points):
        return everything
    return fuse_scans(
        points[:scans], labels[:scans], np.asarray(T_newest_scan)[:scans], merge_radius
    )


def require_clique(result: LocalizationResult, min_clique: int) -> LocalizationResult:
    """``result``, or where its valid pose rests on fewer than ``min_clique`` clique vertices the
    same result refused (``valid`` False, identity ``pose``)."""
    if not result.valid or result.clique_size >= min_clique:
        return result
    return result._replace(valid=False, pose=np.eye(4))


def localize_window(
    triplet_map: TripletMap,
    points: list[np.ndarray],
    labels: list[np.ndarray],
    T_newest_scan: np.ndarray,
    merge_radius: float = MERGE_RADIUS,
    min_clique: int = WINDOW_MIN_CLIQUE,
    least_scans: int | None = None,
    min_instances: int = WINDOW_MIN_INSTANCES,
) -> tuple[LocalizationResult, FusedScans]:
    """Localize the newest scan of a window through the fused submap of the window.

    Arguments as :func:`fuse_scans`, with the described map (:func:`~jaxloc.m2loc.build_map`);
    ``min_clique``: the smallest clique a window of two scans or more may rest on
    (:data:`WINDOW_MIN_CLIQUE`; a window of one scan is a scan and keeps the map's
    ``min_inliers``). ``least_scans``: None fuses every scan given; K fuses the newest K and grows
    the window with the older ones given as :func:`grow_window` does (``min_instances``). Returns
    the :class:`~jaxloc.m2loc.LocalizationResult` of the fused submap (its ``pose`` is
    ``T_map_newest``; its inlier indices index the fused instances) and the fusion itself (its
    ``members.shape[1]`` scans were fused).
    """
    least = len(points) if least_scans is None else least_scans
    fused = grow_window(points, labels, T_newest_scan, least, min_instances, merge_radius)
    result = localize_scan(triplet_map, None, fused.points, fused.labels)
    return require_clique(result, min_clique) if fused.members.shape[1] > 1 else result, fused
