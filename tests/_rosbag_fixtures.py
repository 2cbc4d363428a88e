"""ROS bags written by the tests with ``rosbags``' own writers: a ROS 1 ``.bag``, a ROS 2 folder of
sqlite3 or MCAP storage, or the bare ``.mcap`` of such a folder, from messages built with the
writers' type stores (ROS 1 Noetic's, with ``tf2_msgs/TFMessage`` added, and ROS 2 Humble's).

:class:`Messages` builds messages (images, CameraInfo, poses, odometry, TF); :class:`BagWriter`
writes them one at a time (and labelled clouds of any field layout); :func:`write_bag` writes a
list of them; :func:`write_drive` writes a simulated drive (``LabelledScans``) with odometry."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin, Writer as Writer2
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from scipy.spatial.transform import Rotation

#: The bag kinds written: ROS 1, ROS 2 sqlite3, ROS 2 MCAP (a folder), a bare .mcap file.
KINDS = ("ros1", "sqlite3", "mcap", "bare-mcap")
#: PointField datatypes of numpy codes.
DATATYPES = {"i1": 1, "u1": 2, "i2": 3, "u2": 4, "i4": 5, "u4": 6, "f4": 7, "f8": 8}


def typestore(kind: str):
    """The type store of a bag kind (ROS 1 Noetic's with tf2_msgs/TFMessage added)."""
    if kind != "ros1":
        return get_typestore(Stores.ROS2_HUMBLE)
    store = get_typestore(Stores.ROS1_NOETIC)
    store.register(
        get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage")
    )
    return store


class Messages:
    """Builds ROS messages of one type store (field names differ: ROS 1's ``K``, ROS 2's ``k``)."""

    def __init__(self, kind: str):
        self.kind, self.store = kind, typestore(kind)
        self.types = self.store.types

    def make(self, name: str, **fields):
        cls = self.types[name]
        names = set(cls.__dataclass_fields__)
        return cls(**{k if k in names else k.upper(): v for k, v in fields.items()})

    def header(self, stamp_ns: int, frame_id: str):
        time = self.types["builtin_interfaces/msg/Time"](
            sec=int(stamp_ns // 10**9), nanosec=int(stamp_ns % 10**9)
        )
        extra = {"seq": 0} if self.kind == "ros1" else {}
        return self.make("std_msgs/msg/Header", stamp=time, frame_id=frame_id, **extra)

    def image(self, stamp_ns, frame_id, pixels: np.ndarray, encoding: str, bigendian=False):
        pixels = np.ascontiguousarray(pixels)
        if bigendian:
            pixels = pixels.astype(pixels.dtype.newbyteorder(">"))
        height, width = pixels.shape[:2]
        data = np.frombuffer(pixels.tobytes(), np.uint8)
        return self.make(
            "sensor_msgs/msg/Image", header=self.header(stamp_ns, frame_id), height=height,
            width=width, encoding=encoding, is_bigendian=int(bigendian),
            step=data.size // height, data=data,
        )  # fmt: skip

    def compressed(self, stamp_ns, frame_id, data: bytes, format: str = "jpeg"):
        return self.make(
            "sensor_msgs/msg/CompressedImage", header=self.header(stamp_ns, frame_id),
            format=format, data=np.frombuffer(data, np.uint8),
        )  # fmt: skip

    def camera_info(self, stamp_ns, frame_id, K: np.ndarray, size):
        roi = self.make(
            "sensor_msgs/msg/RegionOfInterest", x_offset=0, y_offset=0, height=0, width=0,
            do_rectify=False,
        )  # fmt: skip
        P = np.zeros((3, 4))
        P[:3, :3] = K[:3, :3]
        return self.make(
            "sensor_msgs/msg/CameraInfo", header=self.header(stamp_ns, frame_id),
            height=size[1], width=size[0], distortion_model="plumb_bob", d=np.zeros(5),
            k=np.asarray(K[:3, :3], np.float64).ravel(), r=np.eye(3).ravel(), p=P.ravel(),
            binning_x=0, binning_y=0, roi=roi,
        )  # fmt: skip

    def pose(self, T: np.ndarray):
        q = Rotation.from_matrix(T[:3, :3]).as_quat()
        point = self.make("geometry_msgs/msg/Point", x=T[0, 3], y=T[1, 3], z=T[2, 3])
        quaternion = self.make("geometry_msgs/msg/Quaternion", x=q[0], y=q[1], z=q[2], w=q[3])
        return self.make("geometry_msgs/msg/Pose", position=point, orientation=quaternion)

    def odometry(self, stamp_ns, frame_id, child, T):
        vector = self.make("geometry_msgs/msg/Vector3", x=0.0, y=0.0, z=0.0)
        twist = self.make("geometry_msgs/msg/Twist", linear=vector, angular=vector)
        return self.make(
            "nav_msgs/msg/Odometry", header=self.header(stamp_ns, frame_id), child_frame_id=child,
            pose=self.make("geometry_msgs/msg/PoseWithCovariance", pose=self.pose(T),
                           covariance=np.zeros(36)),
            twist=self.make("geometry_msgs/msg/TwistWithCovariance", twist=twist,
                            covariance=np.zeros(36)),
        )  # fmt: skip

    def pose_stamped(self, stamp_ns, frame_id, T):
        return self.make(
            "geometry_msgs/msg/PoseStamped", header=self.header(stamp_ns, frame_id),
            pose=self.pose(T),
        )  # fmt: skip

    def tf(self, transforms):
        """A TFMessage of (stamp_ns, parent, child, T_parent_child) tuples."""
        stamped = []
        for stamp_ns, parent, child, T in transforms:
            pose = self.pose(T)
            p = pose.position
            translation = self.make("geometry_msgs/msg/Vector3", x=p.x, y=p.y, z=p.z)
            transform = self.make(
                "geometry_msgs/msg/Transform", translation=translation, rotation=pose.orientation
            )
            stamped.append(self.make(
                "geometry_msgs/msg/TransformStamped", header=self.header(stamp_ns, parent),
                child_frame_id=child, transform=transform,
            ))  # fmt: skip
        return self.make("tf2_msgs/msg/TFMessage", transforms=stamped)


def bag_path(root: Path, kind: str) -> Path:
    """Where :class:`BagWriter` writes a bag of ``kind`` under ``root``."""
    return root / {"ros1": "drive.bag", "bare-mcap": "drive.mcap"}.get(kind, kind)


class BagWriter:
    """A bag of ``kind`` at ``path`` (a ``.bag`` file, a ROS 2 folder, or a ``.mcap`` file for
    "bare-mcap"), open in a ``with`` block; :attr:`messages` builds its messages."""

    def __init__(self, path: Path, kind: str) -> None:
        self.path, self.kind, self.ros1 = Path(path), kind, kind == "ros1"
        self.messages = Messages(kind)
        self.typestore, self.types = self.messages.store, self.messages.types
        self.connections: dict[str, object] = {}

    def __enter__(self) -> BagWriter:
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
            shutil.move(next(folder.glob("*.mcap")), self.path)
            shutil.rmtree(folder)

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
            header=self.messages.header(stamp, frame),
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

    def odometry(self, topic, stamp, pose, frame="odom", child="velodyne") -> None:
        self.write(topic, self.messages.odometry(stamp, frame, child, pose), stamp)

    def pose_stamped(self, topic, stamp, pose, frame="map") -> None:
        self.write(topic, self.messages.pose_stamped(stamp, frame, pose), stamp)

    def tf(self, topic, stamp, transforms) -> None:
        """A TFMessage of ``(parent, child, pose)`` transforms."""
        self.write(topic, self.messages.tf([(stamp, *t) for t in transforms]), stamp)


def write_bag(path: Path, kind: str, messages: list[tuple[str, str, int, object]]) -> Path:
    """Write ``(topic, msgtype, receive time ns, message)`` tuples (in time order) as a bag of
    ``kind`` at ``path`` (a ``.bag`` file for ROS 1, a folder for ROS 2, ``path.mcap`` for a
    bare MCAP). Returns what to open."""
    suffix = {"ros1": ".bag", "bare-mcap": ".mcap"}.get(kind)
    path = path.with_suffix(suffix) if suffix else path
    with BagWriter(path, kind) as bag:
        for topic, _, log_time, message in sorted(messages, key=lambda m: m[2]):
            bag.write(topic, message, log_time)
    return path


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
