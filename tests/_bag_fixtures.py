"""ROS bags written by the tests with ``rosbags``' own writers (ROS 1 ``.bag``, ROS 2 sqlite3
and MCAP folders, a bare ``.mcap``), from messages built with the writers' type stores
(ROS 1 Noetic's and ROS 2 Humble's message definitions)."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from scipy.spatial.transform import Rotation

#: The bag kinds written: ROS 1, ROS 2 sqlite3, ROS 2 MCAP (a folder), a bare .mcap file.
KINDS = ("ros1", "sqlite3", "mcap", "bare-mcap")


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


def write_bag(path: Path, kind: str, messages: list[tuple[str, str, int, object]]) -> Path:
    """Write ``(topic, msgtype, receive time ns, message)`` tuples (in time order) as a bag of
    ``kind`` at ``path`` (a ``.bag`` file for ROS 1, a folder for ROS 2, ``path.mcap`` for a
    bare MCAP). Returns what to open."""
    store = typestore(kind)
    messages = sorted(messages, key=lambda m: m[2])
    if kind == "ros1":
        path = path.with_suffix(".bag")
        writer = Writer1(path)
    else:
        plugin = StoragePlugin.SQLITE3 if kind == "sqlite3" else StoragePlugin.MCAP
        writer = Writer2(path, version=9, storage_plugin=plugin)
    with writer:
        connections = {}
        for topic, msgtype, logtime, message in messages:
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=store)
            if kind == "ros1":
                data = store.serialize_ros1(message, msgtype)
            else:
                data = store.serialize_cdr(message, msgtype)
            writer.write(connections[topic], logtime, data)
    if kind == "bare-mcap":
        bare = path.with_suffix(".mcap")
        shutil.move(next(path.glob("*.mcap")), bare)
        shutil.rmtree(path)
        return bare
    return path
