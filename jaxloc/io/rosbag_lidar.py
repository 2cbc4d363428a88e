"""Labelled LiDAR scans from a bag: ``sensor_msgs/PointCloud2`` clouds with a label per point,
the odometry and ground truth the bag holds, read one cloud at a time.

A bag is a ROS 1 ``.bag``, a ROS 2 bag folder (sqlite3 or MCAP storage) or a bare ``.mcap``
(read with ``rosbags``, no ROS installation needed). :func:`open_rosbag_scans` reads its topics and
the clouds' headers once; :meth:`RosbagScans.scan` then reads cloud ``i`` alone, so a bag is
never in memory as a whole. :func:`jaxloc.io.open_lidar_recording` opens bags with it.

Clouds (``topic``: the only PointCloud2 topic, else named) must hold float32 or float64 fields
``x``, ``y``, ``z`` (metres, in the cloud's ``frame_id``) and an integer label field:

* ``label`` (or ``label_field``) uint32 or int32: the SemanticKITTI id in the low 16 bits and the
  instance in the high 16 (a ``.label`` word), unless ``instance_field`` names the instance;
* any other integer type (uint16 ``label``, a named class field): the SemanticKITTI id itself,
  the instance from ``instance_field`` (else 0).

Ids go through SemanticKITTI's learning map as in :mod:`jaxloc.io.semantickitti`; an id it does
not know, a point beyond :data:`~jaxloc.io.semantickitti.MAX_RANGE_M`, or a non-finite point of
a cloud marked dense is an error; a cloud not marked dense (``is_dense`` false) loses its
non-finite points (no return). The header stamps must increase from cloud to cloud.

Odometry (``odometry_topic``): the only ``nav_msgs/Odometry`` topic, else named (any of
:data:`~jaxloc.io._rosbag_poses.POSE_TYPES`, or ``/tf``); a bag without one uses ``/tf`` when it
moves the clouds' frame (the clouds' frame in ``odom`` where the tree has it above them, else in
the tree's root); ``"none"`` reads none. Its poses are interpolated to the clouds' stamps
(:func:`jaxloc.io._rosbag_poses.interpolate`), carried to the clouds' frame through the TF tree
where the odometry's child frame is another (a ``PoseStamped`` names no child frame: its poses
are taken as the LiDAR's), and must cover every scan. Ground truth (``gt_topic``, a pose topic
named) is read the same way, a scan outside it having no pose.
"""

from __future__ import annotations

import contextlib
import os
import weakref
from pathlib import Path
from typing import Any

import numpy as np

from jaxloc.io import _rosbag as bag
from jaxloc.io._rosbag_poses import NO_ODOMETRY, POSE_TYPES, BagPoses, pick_odometry, sensor_poses
from jaxloc.io.semantickitti import LabelledScan, check_point_range, checked_class_ids

#: The clouds' message type (as ``rosbags`` names it, for ROS 1 and ROS 2).
CLOUD_TYPE = "sensor_msgs/msg/PointCloud2"
#: PointField datatypes (1-8) as numpy type codes.
FIELD_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
_FLOATS, _PACKED = (7, 8), (5, 6)


def cloud_dtype(
    cloud: Any, where: str, label_field: str | None = None, instance_field: str | None = None
) -> tuple[np.dtype, bool]:
    """The record dtype of a PointCloud2's points (fields ``x``, ``y``, ``z``, ``label`` and
    ``instance`` at their offsets, ``point_step`` bytes), and whether its label packs the
    instance in the high 16 bits. Checks the cloud's layout, not its data.

    Raises:
        ValueError: naming ``where``: a field of unknown datatype, missing coordinate or label
            fields, fields of the wrong type, a layout its data does not fill.
    """
    fields = {field.name: field for field in cloud.fields}
    for field in cloud.fields:
        if field.datatype not in FIELD_TYPES:
            raise ValueError(
                f"{where}: field {field.name!r} has unknown datatype {field.datatype} "
                "(PointField knows 1-8)"
            )
    label = label_field or "label"
    listed = ", ".join(fields) or "none"
    wanted = {"x": "x", "y": "y", "z": "z", "label": label}
    if instance_field is not None:
        wanted["instance"] = instance_field
    for role, name in wanted.items():
        if name not in fields:
            hint = " (name it with label_field=)" if role == "label" and label_field is None else ""
            raise ValueError(f"{where}: no {role} field {name!r} (fields: {listed}){hint}")
        field = fields[name]
        floats = role in ("x", "y", "z")
        if (field.datatype in _FLOATS) != floats or field.count != 1:
            kind = "float32 or float64" if floats else "integer"
            raise ValueError(
                f"{where}: field {name!r} is {FIELD_TYPES[field.datatype]} x {field.count}, "
                f"expected one {kind}"
            )
    order = ">" if cloud.is_bigendian else "<"
    names = list(wanted)
    formats = [order + FIELD_TYPES[fields[wanted[n]].datatype] for n in names]
    offsets = [int(fields[wanted[n]].offset) for n in names]
    step, width, height = int(cloud.point_step), int(cloud.width), int(cloud.height)
    ends = [o + np.dtype(f).itemsize for o, f in zip(offsets, formats, strict=True)]
    if max(ends) > step or width * step > int(cloud.row_step):
        raise ValueError(
            f"{where}: fields end at byte {max(ends)} of a {step}-byte point, rows of {width} "
            f"points in {cloud.row_step} bytes"
        )
    if len(cloud.data) != int(cloud.row_step) * height:
        raise ValueError(
            f"{where}: {len(cloud.data)} bytes of data for {height} rows of {cloud.row_step}"
        )
    dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": step})
    packed = fields[label].datatype in _PACKED and instance_field is None
    return dtype, packed


def read_cloud(
    cloud: Any, where: str, label_field: str | None = None, instance_field: str | None = None
) -> LabelledScan:
    """A PointCloud2 message as a :class:`~jaxloc.io.LabelledScan` (class ids; the cloud's
    frame, metres; see the module docstring for the fields).

    Raises:
        ValueError: naming ``where``: as :func:`cloud_dtype`; non-finite points in a dense cloud,
            points beyond the range bound, ids not in the learning map, instances above 2**31.
    """
    dtype, packed = cloud_dtype(cloud, where, label_field, instance_field)
    data = np.asarray(cloud.data, np.uint8).reshape(int(cloud.height), int(cloud.row_step))
    data = np.ascontiguousarray(data[:, : int(cloud.width) * int(cloud.point_step)])
    records = np.frombuffer(data, dtype)
    points = np.column_stack([records["x"], records["y"], records["z"]]).astype(np.float64)
    if not cloud.is_dense:  # points without a return are NaN in clouds not marked dense
        kept = np.all(np.isfinite(points), axis=1)
        points, records = points[kept], records[kept]
    check_point_range(points, where)
    raw = records["label"].astype(np.int64)
    if packed:
        raw &= 0xFFFFFFFF  # an int32 word as the uint32 it holds
        ids, instances = raw & 0xFFFF, raw >> 16
    else:
        ids = raw
        has_instance = "instance" in dtype.names
        instances = records["instance"].astype(np.int64) if has_instance else np.zeros_like(raw)
    if instances.size and instances.max() > np.iinfo(np.int32).max:
        raise ValueError(f"{where}: instance id {instances.max()} is above 2**31 - 1")
    labels = checked_class_ids(ids, where)
    return LabelledScan(
        points.astype(np.float32).reshape(-1, 3), labels, instances.astype(np.int32)
    )


class RosbagScans:
    """The labelled clouds of one topic of a bag, read one at a time (what
    :func:`open_rosbag_scans` returns).

    Attributes:
        path: the bag.
        topic: the clouds' topic.
        frame_id: the clouds' frame.
        numbers: per scan its index among the topic's messages.
        stamps: (N,) int64 header stamps, nanoseconds, increasing.
        odometry: (N, 4, 4) float64 ``T_odom_scan`` at the stamps, or None.
        odometry_topic: the topic the odometry came from (``/tf`` for TF), or None.
        ground_truth: (N, 4, 4) float64 ``T_map_scan`` from ``gt_topic`` (identity where a scan
            has none), or None; has_ground_truth: (N,) bool.
        label_field, instance_field: the fields read (None: ``label``, and none).
    """

    def __init__(
        self,
        path: Path,
        topic: str,
        frame_id: str,
        numbers: tuple[int, ...],
        stamps: np.ndarray,
        places: list[tuple[int, int]],
        odometry: tuple[np.ndarray | None, str | None],
        ground_truth: tuple[np.ndarray | None, np.ndarray],
        fields: tuple[str | None, str | None],
    ) -> None:
        self.path, self.topic, self.frame_id = path, topic, frame_id
        self.numbers, self.stamps = numbers, stamps
        self.odometry, self.odometry_topic = odometry
        self.ground_truth, self.has_ground_truth = ground_truth
        self.label_field, self.instance_field = fields
        self._places = places  # per scan its place in the bag (bag.message_at)
        self._reader: list = []  # the open reader, once a scan was read
        weakref.finalize(self, _close, self._reader)

    def __len__(self) -> int:
        return len(self.numbers)

    def name(self, index: int) -> str:
        """Scan ``index`` as errors name it: ``BAG:TOPIC[number]``."""
        return f"{self.path}:{self.topic}[{self.numbers[index]}]"

    def scan(self, index: int) -> LabelledScan:
        """Read scan ``index`` (:func:`read_cloud`).

        Raises:
            ValueError: naming the bag, topic and scan: a damaged message or any error of
                :func:`read_cloud`.
        """
        if not self._reader:
            self._reader.append(bag.open_bag(self.path))
        where = self.name(index)
        cloud = bag.message_at(self._reader[0], self.path, self.topic, self._places[index], where)
        if bag.stamp_ns(cloud.header) != self.stamps[index]:
            raise ValueError(f"{where}: the message is not where it was (the bag changed?)")
        return read_cloud(cloud, where, self.label_field, self.instance_field)

    def close(self) -> None:
        """Close the bag (a later :meth:`scan` opens it again)."""
        _close(self._reader)


def _close(holder: list) -> None:
    while holder:
        holder.pop().close()


def _topics(reader, path: Path, topic, odometry_topic, gt_topic):
    """The clouds', odometry's and ground truth's topics (see :func:`open_rosbag_scans`)."""
    clouds = bag.topics_of(reader, (CLOUD_TYPE,))
    clouds = bag.pick_topic(reader, path, clouds, topic, "PointCloud2", "topic")
    if clouds is None:
        raise bag.no_topic(reader, path, "sensor_msgs/PointCloud2")
    odometry = pick_odometry(reader, path, odometry_topic)
    truth = bag.topics_of(reader, POSE_TYPES)
    truth = None if gt_topic is None else bag.pick_topic(reader, path, truth, gt_topic, "pose",
                                                         "gt_topic")  # fmt: skip
    return clouds, odometry, truth


class _Clouds:
    """What one pass over the bag gathers of the clouds: their frame, log times and stamps."""

    def __init__(self) -> None:
        self.frame: str | None = None
        self.log_times: list[int] = []
        self.stamps: list[int] = []

    def add(self, cloud, log_time: int, where: str, fields: tuple) -> None:
        cloud_dtype(cloud, where, *fields)
        stamp = bag.stamp_ns(cloud.header)
        if self.stamps and stamp <= self.stamps[-1]:
            raise ValueError(
                f"{where}: stamp {bag.seconds(stamp)} s is not after the previous cloud's "
                f"({bag.seconds(self.stamps[-1])} s); the stamps must increase"
            )
        if self.frame is not None and cloud.header.frame_id != self.frame:
            raise ValueError(f"{where}: frame {cloud.header.frame_id!r}, not {self.frame!r}")
        self.frame = cloud.header.frame_id
        self.log_times.append(log_time)
        self.stamps.append(stamp)


def _odometry(found: BagPoses, topic, named: bool, frame: str, stamps, clouds: str):
    if topic is None:
        return None, None
    at = sensor_poses(found, topic, frame, stamps, "clouds", required=named)
    if at is None:
        return None, None
    if not at.covered.all():
        miss = int(np.flatnonzero(~at.covered)[0])
        raise ValueError(
            f"{found.path}: odometry {topic} ({bag.seconds(at.first)} s to "
            f"{bag.seconds(at.last)} s) does not cover scan {miss} of {clouds} "
            f"({bag.seconds(int(stamps[miss]))} s); pass odometry_topic={NO_ODOMETRY!r} to read "
            "none"
        )
    return at.poses, topic


def _ground_truth(found: BagPoses, topic, frame: str, stamps, clouds: str):
    if topic is None:
        return None, np.zeros(len(stamps), bool)
    at = sensor_poses(found, topic, frame, stamps, "clouds")
    if not at.covered.any():
        raise ValueError(
            f"{found.path}: ground truth {topic} ({bag.seconds(at.first)} s to "
            f"{bag.seconds(at.last)} s) covers no scan of {clouds} "
            f"({bag.seconds(int(stamps[0]))} s to {bag.seconds(int(stamps[-1]))} s)"
        )
    return at.poses, at.covered


def open_rosbag_scans(
    path: str | os.PathLike,
    *,
    every: int = 1,
    topic: str | None = None,
    odometry_topic: str | None = None,
    gt_topic: str | None = None,
    label_field: str | None = None,
    instance_field: str | None = None,
) -> RosbagScans:
    """Open the labelled clouds of a bag (see the module docstring): reads its topics, every
    cloud's header and layout (one at a time), the odometry and the ground truth.

    Args:
        path: a ``.bag``, a ROS 2 bag folder, or a ``.mcap`` / ``.db3`` file.
        every: every ``every``-th cloud.
        topic: the PointCloud2 topic (default: the only one).
        odometry_topic: the odometry (default: the only ``nav_msgs/Odometry`` topic, else
            ``/tf``; ``"none"``: none).
        gt_topic: a pose topic of ground truth ``T_map_scan`` (default: none).
        label_field: the class field (default ``label``); instance_field: the instance field
            (default: the high 16 bits of a 32-bit label, else none).

    Returns:
        A :class:`RosbagScans`.

    Raises:
        FileNotFoundError: no such bag.
        ValueError: naming the bag (and topic): not a readable bag, no PointCloud2 topic, two
            without ``topic``, a cloud layout :func:`cloud_dtype` refuses, stamps that do not
            increase, clouds of two frames, odometry that does not cover the scans, bad poses.
    """
    if every < 1:
        raise ValueError(f"every must be >= 1, got {every}")
    path, fields = Path(path), (label_field, instance_field)
    with contextlib.closing(bag.open_bag(path)) as reader:
        clouds, odometry, truth = _topics(reader, path, topic, odometry_topic, gt_topic)
        poses, found = BagPoses(reader, path, {odometry, truth} - {None}), _Clouds()
        for name, msgtype, log_time, raw in bag.messages(reader, path, [clouds, *poses.topics]):
            where = f"{path}:{name}[{len(found.stamps)}]" if name == clouds else f"{path}: {name}"
            message = bag.deserialize(reader, raw, msgtype, where)
            if name == clouds:
                found.add(message, log_time, where, fields)
            else:
                poses.add(name, msgtype, message)
    if found.frame is None:
        raise ValueError(f"{path}: {clouds} holds no cloud")
    numbers = tuple(range(0, len(found.stamps), every))
    stamps = np.asarray(found.stamps, np.int64)[list(numbers)]
    named = odometry_topic is not None
    moving = _odometry(poses, odometry, named, found.frame, stamps, clouds)
    judged = _ground_truth(poses, truth, found.frame, stamps, clouds)
    places = bag.places(found.log_times)
    places = [places[n] for n in numbers]
    return RosbagScans(path, clouds, found.frame, numbers, stamps, places, moving, judged, fields)
