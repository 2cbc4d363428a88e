"""Synthetic labelled LiDAR scans of a known instance map, written in the SemanticKITTI layout.

:func:`make_lidar_sequence` drives a sensor along a straight road of an :class:`OutdoorWorld` and
samples, per scan, the surface points a LiDAR would return from the map's objects within
``max_range``: trunks and poles as vertical cylinders (radius 0.15 / 0.08 m) standing on the
terrain whose centroid is the map vertex, only the half facing the sensor; traffic signs as
0.7 m square plates at the vertex; the road surface (the world's terrain, 2 cm noise) in a disc
around the sensor; and building clutter, which the map builder must ignore. Labels are raw
SemanticKITTI ids (71 trunk, 80 pole, 81 traffic sign, 40 road, 50 building) with the instance
in the high 16 bits. The point density is uniform (no range fall-off or occlusion): the scans test
the builder's geometry and bookkeeping, not a sensor model.

:func:`write_semantickitti_sequence` writes ``velodyne/``, ``labels/``, ``poses.txt`` (cam0 poses
``P = Tr @ T_map_scan @ inv(Tr)``) and ``calib.txt`` (``P0``-``P3`` and ``Tr``).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import NamedTuple

import numpy as np

from jaxloc.m2loc._classes import POLE, TRAFFIC_SIGN, TRUNK
from jaxloc.synthetic.outdoor import OutdoorWorld, _rot_z, _rotation_to, _terrain_height

#: Raw SemanticKITTI ids of the synthetic scans.
RAW_TRUNK, RAW_POLE, RAW_SIGN, RAW_ROAD, RAW_BUILDING = 71, 80, 81, 40, 50
_RAW = {TRUNK: RAW_TRUNK, POLE: RAW_POLE, TRAFFIC_SIGN: RAW_SIGN}
_RADIUS = {TRUNK: 0.15, POLE: 0.08}

#: KITTI's velodyne-to-cam0 rotation (camera x right, y down, z forward; velodyne x forward,
#: y left, z up) with a typical lever arm.
KITTI_TR = np.array(
    [[0.0, -1.0, 0.0, -0.004], [0.0, 0.0, -1.0, -0.076], [1.0, 0.0, 0.0, -0.27], [0, 0, 0, 1.0]]
)


class LabelledScans(NamedTuple):
    """Scans of a sequence: ``points`` per scan (Ni, 3) float32 (sensor frame, metres),
    ``raw_labels`` per scan (Ni,) uint32 (semantic | instance << 16), ``T_map_scan`` (N, 4, 4)
    float64, ``visible`` (V,) int64 indices of the map vertices that some scan samples."""

    points: list[np.ndarray]
    raw_labels: list[np.ndarray]
    T_map_scan: np.ndarray
    visible: np.ndarray


def _object_points(centre, label, sensor, rng, step=0.06):
    """Map-frame surface points of one object (see the module docstring)."""
    ground = float(_terrain_height(centre[:2]))
    if label == TRAFFIC_SIGN:
        u = np.arange(-0.35, 0.35 + 1e-9, step)
        a, b = np.meshgrid(u, u)
        facing = rng.uniform(0, np.pi)
        along = np.array([np.cos(facing), np.sin(facing), 0.0])
        return centre + a.reshape(-1, 1) * along + b.reshape(-1, 1) * np.array([0, 0, 1.0])
    radius = _RADIUS[label]
    top = 2.0 * centre[2] - ground  # the cylinder's centroid is the map vertex
    heights = np.arange(ground, top, step)
    angles = np.arange(0.0, 2 * np.pi, step / radius)
    toward = sensor[:2] - centre[:2]
    outward = np.stack([np.cos(angles), np.sin(angles)], axis=1)
    angles = angles[outward @ toward > 0]
    ring = centre[:2] + radius * np.stack([np.cos(angles), np.sin(angles)], axis=1)
    xy = np.repeat(ring, heights.size, axis=0)
    return np.column_stack([xy, np.tile(heights, angles.size)])


def make_lidar_sequence(
    world: OutdoorWorld,
    start_xy: tuple[float, float],
    end_xy: tuple[float, float],
    num_scans: int,
    seed: int = 0,
    max_range: float = 40.0,
    sensor_height: float = 1.8,
    road_points: int = 6000,
    clutter_points: int = 1000,
) -> LabelledScans:
    """Scans at ``num_scans`` evenly spaced poses from ``start_xy`` to ``end_xy`` (map frame).

    The sensor is ``sensor_height`` above the terrain, its up axis the terrain normal, heading
    along the segment plus N(0, 3 deg) yaw noise. Points get N(0, 1 cm) noise.
    """
    rng = np.random.default_rng(seed)
    start, end = np.asarray(start_xy, float), np.asarray(end_xy, float)
    heading = np.arctan2(*(end - start)[::-1])
    points_out, labels_out, poses = [], [], []
    seen = np.zeros(len(world.points), bool)
    for t in np.linspace(0.0, 1.0, num_scans):
        xy = start + t * (end - start)
        eps = 0.5
        dzdx = (_terrain_height(xy + [eps, 0]) - _terrain_height(xy - [eps, 0])) / (2 * eps)
        dzdy = (_terrain_height(xy + [0, eps]) - _terrain_height(xy - [0, eps])) / (2 * eps)
        up = np.array([-dzdx, -dzdy, 1.0]) / np.linalg.norm([dzdx, dzdy, 1.0])
        pose = np.eye(4)
        pose[:3, :3] = _rotation_to(up) @ _rot_z(heading + rng.normal(0, np.deg2rad(3)))
        pose[:3, 3] = [*xy, _terrain_height(xy) + sensor_height]
        near = np.flatnonzero(np.linalg.norm(world.points[:, :2] - xy, axis=1) < max_range)
        seen[near] = True
        chunks, labels = [], []
        for index in near:
            label = int(world.labels[index])
            surface = _object_points(world.points[index], label, pose[:3, 3], rng)
            chunks.append(surface)
            labels.append(np.full(len(surface), _RAW[label] | ((index + 1) << 16), np.uint32))
        radius = max_range * np.sqrt(rng.random(road_points))
        angle = rng.uniform(0, 2 * np.pi, road_points)
        road_xy = xy + np.column_stack([radius * np.cos(angle), radius * np.sin(angle)])
        chunks.append(np.column_stack([road_xy, _terrain_height(road_xy)]))
        labels.append(np.full(road_points, RAW_ROAD, np.uint32))
        clutter = xy + rng.uniform(-max_range, max_range, (clutter_points, 2))
        chunks.append(np.column_stack([clutter, rng.uniform(0, 10, clutter_points)]))
        labels.append(np.full(clutter_points, RAW_BUILDING, np.uint32))
        world_points = np.concatenate(chunks)
        world_points += rng.normal(0, 0.01, world_points.shape)
        points_out.append(((world_points - pose[:3, 3]) @ pose[:3, :3]).astype(np.float32))
        labels_out.append(np.concatenate(labels))
        poses.append(pose)
    return LabelledScans(points_out, labels_out, np.asarray(poses), np.flatnonzero(seen))


def write_semantickitti_sequence(
    out_dir: str | os.PathLike, scans: LabelledScans, Tr: np.ndarray = KITTI_TR
) -> None:
    """Write ``scans`` as a SemanticKITTI sequence folder (the layout of
    :mod:`jaxloc.io.lidar_sequence`), with cam0 poses ``Tr @ T_map_scan @ inv(Tr)``."""
    out = Path(out_dir)
    (out / "velodyne").mkdir(parents=True, exist_ok=True)
    (out / "labels").mkdir(exist_ok=True)
    for index, (points, labels) in enumerate(zip(scans.points, scans.raw_labels, strict=True)):
        xyzi = np.column_stack([points, np.zeros(len(points), np.float32)]).astype("<f4")
        xyzi.tofile(out / "velodyne" / f"{index:06d}.bin")
        labels.astype("<u4").tofile(out / "labels" / f"{index:06d}.label")
    camera_poses = Tr @ scans.T_map_scan @ np.linalg.inv(Tr)
    rows = [" ".join(f"{v:.9e}" for v in pose[:3].ravel()) for pose in camera_poses]
    (out / "poses.txt").write_text("\n".join(rows) + "\n")
    intrinsics = "7.070912e+02 0 6.018873e+02 0 0 7.070912e+02 1.831104e+02 0 0 0 1 0"
    calib = [f"P{i}: {intrinsics}" for i in range(4)]
    calib.append("Tr: " + " ".join(f"{v:.9e}" for v in Tr[:3].ravel()))
    (out / "calib.txt").write_text("\n".join(calib) + "\n")
