"""Bags written with ``rosbags``' own writers, for the bag readers' tests: a ROS 1 ``.bag``, a
ROS 2 folder of sqlite3 or MCAP storage, or the bare ``.mcap`` of such a folder.

:class:`BagWriter` writes single messages (clouds of labelled points with any field layout,
odometry, TF); :func:`write_drive` writes a simulated drive (``LabelledScans``) with odometry."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

#: How a test writes a bag: ROS 1, ROS 2 sqlite3, ROS 2 MCAP, and the MCAP file alone.
KINDS = ("ros1", "sqlite3", "mcap", "bare-mcap")
#: numpy codes of PointField datatypes.
TF_TYPE = "tf2_msgs/msg/TFMessage"
DATATYPES = {"i1": 1, "u1": 2, "i2": 3, "u2": 4, "i4": 5, "u4": 6, "f4": 7, "f8": 8}


def bag_path(root: Path, kind: str) -> Path:
    """Where :class:`BagWriter` writes a bag of ``kind`` under ``root``."""
    return root / {"ros1": "drive.bag", "bare-mcap": "drive.mcap"}.get(kind, kind)


class BagWriter:
    """A bag of ``kind`` at ``path`` (see :func:`bag_path`), open in a ``with`` block."""

    def __init__(self, path: Path, kind: str) -> None:
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore

        self.path, self.kind = Path(path), kind
        self.ros1 = kind == "ros1"
        self.typestore = get_typestore(Stores.ROS1_NOETIC if self.ros1 else Stores.ROS2_HUMBLE)
        if self.ros1:  # rosbags' Noetic store has no tf2_msgs
            tf = get_types_from_msg("geometry_msgs/TransformStamped[] transforms", TF_TYPE)
            self.typestore.register(tf)
        self.types = self.typestore.types
        self.connections: dict[str, object] = {}

    def __enter__(self) -> BagWriter:
        from rosbags.rosbag1 import Writer as Writer1
        from rosbags.rosbag2 import StoragePlugin
        from rosbags.rosbag2 import Writer as Writer2

        if self.ros1:
            self.writer = Writer1(self.path)
        else:
            folder = self.path.with_suffix("") if self.kind == "bare-mcap" else self.path
            plugin = StoragePlugin.SQLITE3 if self.kind == "sqlite3" else StoragePlugin.MCAP
            self.writer = Writer2(folder, version=8, storage_plugin=plugin)
        self.writer.open()
        return self

    def __exit__(self, *exc) -> None:
        self.writer.close()
        if self.kind == "bare-mcap":
            folder = self.path.with_suffix("")
            (folder / f"{folder.name}.mcap").rename(self.path)
            shutil.rmtree(folder)

    def header(self, stamp: int, frame: str):
        time = self.types["builtin_interfaces/msg/Time"](sec=stamp // 10**9, nanosec=stamp % 10**9)
        extra = {"seq": 0} if self.ros1 else {}
        return self.types["std_msgs/msg/Header"](stamp=time, frame_id=frame, **extra)

    def write(self, topic: str, message, log_time: int) -> None:
        msgtype = message.__msgtype__
        if topic not in self.connections:
            self.connections[topic] = self.writer.add_connection(
                topic, msgtype, typestore=self.typestore
            )
        serialize = self.typestore.serialize_ros1 if self.ros1 else self.typestore.serialize_cdr
        self.writer.write(self.connections[topic], log_time, serialize(message, msgtype))

    def cloud(
        self,
        topic: str,
        stamp: int,
        records: np.ndarray,
        frame: str = "velodyne",
        dense: bool = True,
        log_time: int | None = None,
        datatypes: dict[str, int] | None = None,
    ) -> None:
        """A PointCloud2 of a structured array (one field per name; ``datatypes`` overrides a
        field's PointField datatype)."""
        PointField = self.types["sensor_msgs/msg/PointField"]
        fields = [
            PointField(
                name=name,
                offset=records.dtype.fields[name][1],
                datatype=(datatypes or {}).get(name, DATATYPES[records.dtype[name].str[1:]]),
                count=1,
            )
            for name in records.dtype.names
        ]
        cloud = self.types["sensor_msgs/msg/PointCloud2"](
            header=self.header(stamp, frame),
            height=1,
            width=len(records),
            fields=fields,
            is_bigendian=False,
            point_step=records.dtype.itemsize,
            row_step=records.dtype.itemsize * len(records),
            data=np.frombuffer(records.tobytes(), np.uint8),
            is_dense=dense,
        )
        self.write(topic, cloud, stamp if log_time is None else log_time)

    def _pose(self, pose: np.ndarray, transform: bool = False):
        types = self.types
        x, y, z, w = Rotation.from_matrix(pose[:3, :3]).as_quat()
        rotation = types["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w)
        t = [float(v) for v in pose[:3, 3]]
        if transform:
            translation = types["geometry_msgs/msg/Vector3"](x=t[0], y=t[1], z=t[2])
            return types["geometry_msgs/msg/Transform"](translation=translation, rotation=rotation)
        position = types["geometry_msgs/msg/Point"](x=t[0], y=t[1], z=t[2])
        return types["geometry_msgs/msg/Pose"](position=position, orientation=rotation)

    def odometry(self, topic, stamp, pose, frame="odom", child="velodyne") -> None:
        types = self.types
        with_covariance = types["geometry_msgs/msg/PoseWithCovariance"](
            pose=self._pose(pose), covariance=np.zeros(36)
        )
        twist = types["geometry_msgs/msg/TwistWithCovariance"](
            twist=types["geometry_msgs/msg/Twist"](
                linear=types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                angular=types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
            ),
            covariance=np.zeros(36),
        )
        message = types["nav_msgs/msg/Odometry"](
            header=self.header(stamp, frame),
            child_frame_id=child,
            pose=with_covariance,
            twist=twist,
        )
        self.write(topic, message, stamp)

    def pose_stamped(self, topic, stamp, pose, frame="map") -> None:
        message = self.types["geometry_msgs/msg/PoseStamped"](
            header=self.header(stamp, frame), pose=self._pose(pose)
        )
        self.write(topic, message, stamp)

    def tf(self, topic, stamp, transforms) -> None:
        """A TFMessage of ``(parent, child, pose)`` transforms."""
        stamped = [
            self.types["geometry_msgs/msg/TransformStamped"](
                header=self.header(stamp, parent),
                child_frame_id=child,
                transform=self._pose(pose, transform=True),
            )
            for parent, child, pose in transforms
        ]
        self.write(topic, self.types[TF_TYPE](transforms=stamped), stamp)


def packed_records(points: np.ndarray, raw_labels: np.ndarray) -> np.ndarray:
    """x y z float32, intensity float32 and a uint32 ``label`` (id | instance << 16)."""
    records = np.zeros(
        len(points),
        [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"), ("label", "<u4")],
    )
    records["x"], records["y"], records["z"] = np.asarray(points, np.float32).T
    records["label"] = raw_labels
    return records


def write_drive(
    path: Path,
    kind: str,
    scans,
    stamps,
    odometry: str | None = "odom",
    odometry_poses: np.ndarray | None = None,
    odometry_stamps=None,
) -> Path:
    """``scans`` (``LabelledScans``) as clouds on ``/points`` (frame ``velodyne``) at ``stamps``,
    with odometry (``T_odom_velodyne``: ``odometry_poses`` at ``odometry_stamps``, default the
    scans' poses at their stamps) on ``/odom`` ("odom"), or on ``/tf`` as odom -> base_link with
    base_link -> velodyne on ``/tf_static`` ("tf"), or none (None)."""
    poses = scans.T_map_scan if odometry_poses is None else odometry_poses
    times = stamps if odometry_stamps is None else odometry_stamps
    lever = np.eye(4)
    lever[:3, 3] = [0.5, 0.0, 1.2]
    with BagWriter(path, kind) as bag:
        if odometry == "tf":
            bag.tf("/tf_static", int(stamps[0]), [("base_link", "velodyne", lever)])
        for stamp, points, raw in zip(stamps, scans.points, scans.raw_labels, strict=True):
            bag.cloud("/points", int(stamp), packed_records(points, raw))
        for stamp, pose in zip(times, poses, strict=True):
            if odometry == "odom":
                bag.odometry("/odom", int(stamp), pose)
            elif odometry == "tf":
                base = pose @ np.linalg.inv(lever)
                bag.tf("/tf", int(stamp), [("odom", "base_link", base)])
    return path
