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
:data:`~jaxloc.io._rosbag.POSE_TYPES`, or ``/tf``); a bag without one uses ``/tf`` when it moves
the clouds' frame; ``"none"`` reads none. Its poses are interpolated to the clouds' stamps
(:func:`jaxloc.io._rosbag.interpolate`), moved to the clouds' frame through ``/tf_static``
where the odometry's child frame is another (a ``PoseStamped`` names no child frame: its poses
are taken as the LiDAR's), and must cover every scan. Ground truth (``gt_topic``, a pose topic
named) is read the same way, a scan outside it having no pose.
"""

from __future__ import annotations

import os
import weakref
from pathlib import Path
from typing import Any

import numpy as np

from jaxloc.io import _rosbag as bag
from jaxloc.io.poses import format_ns_as_seconds
from jaxloc.io.semantickitti import LabelledScan, check_point_range, checked_class_ids

#: The clouds' message type (as ``rosbags`` names it, for ROS 1 and ROS 2).
CLOUD_TYPE = "sensor_msgs/msg/PointCloud2"
#: The message type of odometry picked without ``odometry_topic``.
ODOMETRY_TYPE = "nav_msgs/msg/Odometry"
#: ``odometry_topic`` value that reads no odometry.
NO_ODOMETRY = "none"
#: PointField datatypes (1-8) as numpy type codes.
FIELD_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
_FLOATS, _PACKED = (7, 8), (5, 6)


def _seconds(ns: int) -> str:
    return format_ns_as_seconds(ns).rstrip("0").rstrip(".") + " s"


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
        self._places = places  # per scan (log time, its rank among messages of that log time)
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
        reader, where = self._reader[0], self.name(index)
        log_time, rank = self._places[index]
        found = bag.messages(reader, self.path, [self.topic], log_time, log_time + 1)
        cloud = None
        try:
            for seen, (_, msgtype, _, raw) in enumerate(found):
                if seen == rank:
                    cloud = bag.deserialize(reader, raw, msgtype, where)
                    break
        finally:
            found.close()
        if cloud is None or bag.stamp_ns(cloud.header) != self.stamps[index]:
            raise ValueError(f"{where}: the message is not where it was (the bag changed?)")
        return read_cloud(cloud, where, self.label_field, self.instance_field)

    def close(self) -> None:
        """Close the bag (a later :meth:`scan` opens it again)."""
        _close(self._reader)


def _close(holder: list) -> None:
    while holder:
        holder.pop().close()


def _frame_transform(static, child: str | None, frame: str, where: str) -> np.ndarray:
    """``T_child_frame`` through ``/tf_static`` (identity when the poses are of ``frame``)."""
    if child is None or child.lstrip("/") == frame.lstrip("/"):
        return np.eye(4)
    found = bag.static_transform(static, child, frame)
    if found is None:
        raise ValueError(
            f"{where}: poses of frame {child!r}, clouds in {frame!r}, and no /tf_static "
            "transform joins them"
        )
    return found


def _topics(
    reader, path: Path, topic, odometry_topic, gt_topic
) -> tuple[str, str | None, str | None]:
    """The clouds', odometry's and ground truth's topics (see :func:`open_rosbag_scans`)."""
    types = bag.topic_types(reader)
    clouds = bag.pick_topic(reader, path, (CLOUD_TYPE,), topic, "topic=", "PointCloud2")
    if clouds is None:
        listed = sorted(f"{name} ({msgtype})" for name, msgtype in types.items())
        raise ValueError(f"{path}: no sensor_msgs/PointCloud2 topic (topics: {listed})")
    odometry = None
    if odometry_topic is None:
        odometry = bag.pick_topic(
            reader, path, (ODOMETRY_TYPE,), None, "odometry_topic=", "odometry"
        )
        if odometry is None and types.get(bag.TF_TOPIC) == bag.TF_TYPE:
            odometry = bag.TF_TOPIC
    elif odometry_topic != NO_ODOMETRY and types.get(odometry_topic) != bag.TF_TYPE:
        kinds = bag.POSE_TYPES + (bag.TF_TYPE,)
        odometry = bag.pick_topic(reader, path, kinds, odometry_topic, "odometry_topic=", "pose")
    elif odometry_topic != NO_ODOMETRY:
        odometry = odometry_topic
    truth = None
    if gt_topic is not None:
        truth = bag.pick_topic(reader, path, bag.POSE_TYPES, gt_topic, "gt_topic=", "pose")
    return clouds, odometry, truth


class _Collected:
    """What one pass over the bag gathers: the clouds' frame, log times and stamps, the poses of
    the odometry and ground-truth topics, the TF trees."""

    def __init__(self, path: Path, pose_topics: set[str]) -> None:
        self.frame: str | None = None
        self.log_times: list[int] = []
        self.stamps: list[int] = []
        self.poses = {topic: bag.PoseCollector(path, topic) for topic in pose_topics}
        self.tf = bag.TfCollector(path)

    def cloud(self, cloud, log_time: int, where: str, fields: tuple) -> None:
        cloud_dtype(cloud, where, *fields)
        stamp = bag.stamp_ns(cloud.header)
        if self.stamps and stamp <= self.stamps[-1]:
            raise ValueError(
                f"{where}: stamp {_seconds(stamp)} is not after the previous cloud's "
                f"({_seconds(self.stamps[-1])}); the stamps must increase"
            )
        if self.frame is not None and cloud.header.frame_id != self.frame:
            raise ValueError(f"{where}: frame {cloud.header.frame_id!r}, not {self.frame!r}")
        self.frame = cloud.header.frame_id
        self.log_times.append(log_time)
        self.stamps.append(stamp)


def _poses_at(found: _Collected, topic: str, stamps: np.ndarray, where: str):
    """Poses of ``topic`` (a pose topic or TF) of the clouds' frame at ``stamps``:
    ``(poses, covered, (first, last) stamp)``, or None for TF that does not move the frame."""
    dynamic, static = found.tf.trees()
    if topic not in found.poses:
        chain = bag.tf_chain(dynamic, static, found.frame)
        moving = [edge for edge in chain if dynamic.get(edge.child) is edge]
        if not moving:
            return None
        poses, covered = bag.chain_poses(chain, dynamic, stamps)
        first = max(int(edge.stamps[0]) for edge in moving)
        return poses, covered, (first, min(int(edge.stamps[-1]) for edge in moving))
    series = found.poses[topic].series()
    extrinsic = _frame_transform(static, series.child, found.frame, where)
    poses, covered = bag.interpolate(series, stamps)
    return poses @ extrinsic, covered, (int(series.stamps[0]), int(series.stamps[-1]))


def _odometry(found: _Collected, path: Path, topic, named: bool, stamps, clouds: str):
    if topic is None:
        return None, None
    at = _poses_at(found, topic, stamps, f"{path}: {topic}")
    if at is None and named:
        raise ValueError(f"{path}: {topic} does not move the clouds' frame {found.frame!r}")
    if at is None:
        return None, None
    poses, covered, (first, last) = at
    if not covered.all():
        miss = int(np.flatnonzero(~covered)[0])
        raise ValueError(
            f"{path}: odometry {topic} ({_seconds(first)} to {_seconds(last)}) does not cover "
            f"scan {miss} of {clouds} ({_seconds(int(stamps[miss]))}); pass "
            f"odometry_topic={NO_ODOMETRY!r} to read none"
        )
    return poses, topic


def _ground_truth(found: _Collected, path: Path, topic, stamps, clouds: str):
    if topic is None:
        return None, np.zeros(len(stamps), bool)
    poses, covered, (first, last) = _poses_at(found, topic, stamps, f"{path}: {topic}")
    if not covered.any():
        raise ValueError(
            f"{path}: ground truth {topic} ({_seconds(first)} to {_seconds(last)}) covers no "
            f"scan of {clouds} ({_seconds(int(stamps[0]))} to {_seconds(int(stamps[-1]))})"
        )
    return poses, covered


def _ranks(log_times: list[int]) -> list[tuple[int, int]]:
    places, previous, rank = [], None, 0
    for log_time in log_times:
        rank = rank + 1 if log_time == previous else 0
        places.append((log_time, rank))
        previous = log_time
    return places


def open_rosbag_scans(
    path: str | os.PathLike,
    *,
    topic: str | None = None,
    odometry_topic: str | None = None,
    gt_topic: str | None = None,
    label_field: str | None = None,
    instance_field: str | None = None,
    every: int = 1,
) -> RosbagScans:
    """Open the labelled clouds of a bag (see the module docstring): reads its topics, every
    cloud's header and layout (one at a time), the odometry and the ground truth.

    Args:
        path: a ``.bag``, a ROS 2 bag folder, or a ``.mcap`` / ``.db3`` file.
        topic: the PointCloud2 topic (default: the only one).
        odometry_topic: the odometry (default: the only ``nav_msgs/Odometry`` topic, else
            ``/tf``; ``"none"``: none).
        gt_topic: a pose topic of ground truth ``T_map_scan`` (default: none).
        label_field: the class field (default ``label``); instance_field: the instance field
            (default: the high 16 bits of a 32-bit label, else none).
        every: every ``every``-th cloud.

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
    reader = bag.open_bag(path)
    try:
        clouds, odometry, truth = _topics(reader, path, topic, odometry_topic, gt_topic)
        types = bag.topic_types(reader)
        tf_topics = {t for t in (odometry, bag.TF_STATIC_TOPIC) if types.get(t) == bag.TF_TYPE}
        pose_topics = {t for t in (odometry, truth) if t is not None} - tf_topics
        found = _Collected(path, pose_topics)
        wanted = [clouds, *sorted(pose_topics | tf_topics)]
        for name, msgtype, log_time, raw in bag.messages(reader, path, wanted):
            where = f"{path}:{name}[{len(found.stamps)}]" if name == clouds else f"{path}: {name}"
            message = bag.deserialize(reader, raw, msgtype, where)
            if name == clouds:
                found.cloud(message, log_time, where, fields)
            elif name in tf_topics:
                found.tf.add(message, name)
            if name in found.poses:
                found.poses[name].add(message, msgtype)
    finally:
        reader.close()
    if found.frame is None:
        raise ValueError(f"{path}: {clouds} holds no cloud")
    numbers = tuple(range(0, len(found.stamps), every))
    stamps = np.asarray(found.stamps, np.int64)[list(numbers)]
    ranks = _ranks(found.log_times)
    named = odometry_topic is not None
    moving = _odometry(found, path, odometry, named, stamps, clouds)
    judged = _ground_truth(found, path, truth, stamps, clouds)
    places = [ranks[n] for n in numbers]
    return RosbagScans(path, clouds, found.frame, numbers, stamps, places, moving, judged, fields)
