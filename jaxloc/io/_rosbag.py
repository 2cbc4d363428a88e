"""What every bag reader shares: opening a bag with ``rosbags``, picking topics, header stamps,
and poses out of odometry, pose and TF topics, interpolated to given stamps.

Bags are read with the pure-Python ``rosbags`` (``rosbags.highlevel.AnyReader``): a ROS 1
``.bag``, a ROS 2 bag folder (``metadata.yaml`` with sqlite3 or MCAP storage), or a bare ``.mcap``
or ``.db3`` file. Any error ``rosbags`` raises on a damaged or truncated bag becomes one
``ValueError`` naming the bag. Message types are named as ``rosbags`` names them for both ROS
versions (``sensor_msgs/msg/PointCloud2``).

Poses are 4x4 float64 ``T_parent_child`` (``p_parent = T @ p_child``), from a message's position
(or translation) and unit quaternion (x, y, z, w). A pose series is interpolated at a stamp
between its two neighbouring samples (translation linearly, rotation by slerp); a stamp before
the first sample, after the last, or between samples more than :data:`MAX_GAP_NS` apart has none.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from jaxloc.io.poses import QUATERNION_TOLERANCE

#: File suffixes of bags given as one file: ROS 1, and ROS 2 storage files without their folder.
BAG_SUFFIXES = (".bag", ".mcap", ".db3")
#: Message types whose messages are poses (``T_frame_child``), for odometry and ground truth.
POSE_TYPES = (
    "nav_msgs/msg/Odometry",
    "geometry_msgs/msg/PoseStamped",
    "geometry_msgs/msg/PoseWithCovarianceStamped",
    "geometry_msgs/msg/TransformStamped",
)
TF_TYPE = "tf2_msgs/msg/TFMessage"
#: The TF topics: transforms that change, and those that do not.
TF_TOPIC, TF_STATIC_TOPIC = "/tf", "/tf_static"
#: Nanoseconds: a stamp between two pose samples farther apart than this has no pose (a gap in
#: the recording, not motion to interpolate over).
MAX_GAP_NS = 1_000_000_000


def is_bag(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a bag: a ``.bag``, ``.mcap`` or ``.db3`` file, or a folder with a
    ``metadata.yaml`` (ROS 2)."""
    path = Path(path)
    if path.is_dir():
        return (path / "metadata.yaml").is_file()
    return path.suffix in BAG_SUFFIXES


def _reason(error: BaseException) -> str:
    text = str(error).strip().splitlines()
    return f"{type(error).__name__}: {text[0][:200]}" if text else type(error).__name__


def open_bag(path: Path) -> Any:
    """An open ``rosbags.highlevel.AnyReader`` of the bag (close it with ``.close()``).

    Raises:
        FileNotFoundError: no such file or folder.
        ValueError: naming the bag: not a bag ``rosbags`` reads (damaged, truncated, unknown
            storage).
    """
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    if not path.exists():
        raise FileNotFoundError(f"{path}: no such bag")
    try:
        # the default types serve ROS 2 bags that store no message definitions
        reader = AnyReader([path], default_typestore=get_typestore(Stores.LATEST))
        reader.open()
    except Exception as error:  # rosbags' errors differ by storage (its own, apsw's, struct's)
        raise ValueError(f"{path}: not a readable bag ({_reason(error)})") from None
    return reader


def messages(reader: Any, path: Path, topics: Sequence[str], start=None, stop=None) -> Iterator:
    """``(topic, msgtype, log_time_ns, raw)`` of the messages of ``topics``, in log-time order,
    one at a time (one pass over the bag, whatever the number of topics); a damaged part of the
    bag raises ``ValueError`` naming the bag and the topics."""
    connections = [c for c in reader.connections if c.topic in topics]
    if not connections:
        return
    iterator = reader.messages(connections, start, stop)
    try:
        while True:
            try:
                connection, log_time, raw = next(iterator)
            except StopIteration:
                return
            except Exception as error:
                raise ValueError(
                    f"{path}: damaged bag, reading {', '.join(topics)} ({_reason(error)})"
                ) from None
            yield connection.topic, connection.msgtype, log_time, raw
    finally:
        iterator.close()  # a reader left half-way keeps no cursor open


def deserialize(reader: Any, raw: bytes, msgtype: str, where: str) -> Any:
    """The message of ``raw``; a message that does not decode raises ``ValueError`` naming
    ``where``."""
    try:
        return reader.deserialize(raw, msgtype)
    except Exception as error:
        raise ValueError(
            f"{where}: a {msgtype} message does not decode ({_reason(error)})"
        ) from None


def topic_types(reader: Any) -> dict[str, str | None]:
    """Topic name -> message type (None where connections disagree)."""
    return {name: info.msgtype for name, info in reader.topics.items()}


def pick_topic(
    reader: Any,
    path: Path,
    msgtypes: Sequence[str],
    topic: str | None,
    option: str,
    what: str,
) -> str | None:
    """The topic of one of ``msgtypes``: ``topic`` if given (it must be one), else the only one
    of the bag, else None when the bag has none.

    Raises:
        ValueError: naming the bag and ``option``: a named topic that is absent or of another
            type; several candidates and none named (listing them).
    """
    types = topic_types(reader)
    candidates = sorted(name for name, msgtype in types.items() if msgtype in msgtypes)
    kinds = " or ".join(t.replace("/msg/", "/") for t in msgtypes)
    if topic is not None:
        if topic not in types:
            raise ValueError(
                f"{path}: no topic {topic!r} ({option}); {what} topics ({kinds}): "
                f"{candidates or 'none'}"
            )
        if types[topic] not in msgtypes:
            raise ValueError(f"{path}: {option} {topic!r} is {types[topic]}, not {kinds}")
        return topic
    if len(candidates) > 1:
        raise ValueError(
            f"{path}: {len(candidates)} {what} topics {candidates}: name one ({option})"
        )
    return candidates[0] if candidates else None


def stamp_ns(header: Any) -> int:
    """A ``std_msgs/Header``'s stamp in integer nanoseconds."""
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _matrix(position: Any, orientation: Any, where: str) -> np.ndarray:
    from scipy.spatial.transform import Rotation  # here: scipy.spatial costs ~0.3 s to import

    xyz = np.array([position.x, position.y, position.z], np.float64)
    quaternion = np.array([orientation.x, orientation.y, orientation.z, orientation.w], np.float64)
    norm = float(np.linalg.norm(quaternion))
    if not (np.all(np.isfinite(xyz)) and abs(norm - 1.0) <= QUATERNION_TOLERANCE):
        raise ValueError(
            f"{where}: a pose with a non-finite position or a quaternion of norm {norm:.6g}"
        )
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_quat(quaternion / norm).as_matrix()
    pose[:3, 3] = xyz
    return pose


def pose_of(message: Any, msgtype: str, where: str) -> tuple[str, str | None, int, np.ndarray]:
    """``(frame, child frame or None, stamp ns, T_frame_child)`` of a message of
    :data:`POSE_TYPES` (a PoseStamped has no child frame)."""
    if msgtype == "geometry_msgs/msg/TransformStamped":
        t = message.transform
        pose = _matrix(t.translation, t.rotation, where)
        return message.header.frame_id, message.child_frame_id, stamp_ns(message.header), pose
    body = message.pose.pose if msgtype != "geometry_msgs/msg/PoseStamped" else message.pose
    child = message.child_frame_id if msgtype == "nav_msgs/msg/Odometry" else None
    pose = _matrix(body.position, body.orientation, where)
    return message.header.frame_id, child, stamp_ns(message.header), pose


class PoseSeries(NamedTuple):
    """Poses of one frame in another over time: ``stamps`` (M,) int64 ns, increasing;
    ``poses`` (M, 4, 4) float64 ``T_frame_child``."""

    frame: str
    child: str | None
    stamps: np.ndarray
    poses: np.ndarray


def _series(frame, child, stamps, poses, where: str) -> PoseSeries:
    """A PoseSeries sorted by stamp; a stamp given twice with two poses is an error (one with the
    same pose is kept once)."""
    stamps = np.asarray(stamps, np.int64)
    poses = np.asarray(poses, np.float64).reshape(-1, 4, 4)
    order = np.argsort(stamps, kind="stable")
    stamps, poses = stamps[order], poses[order]
    same = np.flatnonzero(np.diff(stamps) == 0)
    if same.size:
        differ = same[~np.all(np.isclose(poses[same], poses[same + 1], atol=1e-9), axis=(1, 2))]
        if differ.size:
            raise ValueError(f"{where}: two poses at one stamp ({stamps[differ[0]]} ns)")
        keep = np.ones(len(stamps), bool)
        keep[same + 1] = False
        stamps, poses = stamps[keep], poses[keep]
    return PoseSeries(frame, child, stamps, poses)


class PoseCollector:
    """The poses of one topic of :data:`POSE_TYPES`, message by message (one frame and child
    frame throughout); :meth:`series` sorts them."""

    def __init__(self, path: Path, topic: str) -> None:
        self.where = f"{path}: {topic}"
        self.frames: tuple | None = None
        self.stamps: list[int] = []
        self.poses: list[np.ndarray] = []

    def add(self, message: Any, msgtype: str) -> None:
        frame, child, stamp, pose = pose_of(message, msgtype, self.where)
        if self.frames is None:
            self.frames = (frame, child)
        elif self.frames != (frame, child):
            raise ValueError(
                f"{self.where}: the frames change from {self.frames} to {(frame, child)}"
            )
        self.stamps.append(stamp)
        self.poses.append(pose)

    def series(self) -> PoseSeries:
        """The poses as a :class:`PoseSeries`.

        Raises:
            ValueError: naming the bag and topic: no message, two poses at one stamp.
        """
        if self.frames is None:
            raise ValueError(f"{self.where}: no message")
        return _series(*self.frames, self.stamps, self.poses, self.where)


class TfCollector:
    """The TF trees of ``/tf`` and ``/tf_static``, message by message: per child frame its parent
    and transforms (each child has one parent)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.edges: dict[str, dict[str, list]] = {TF_TOPIC: {}, TF_STATIC_TOPIC: {}}

    def add(self, message: Any, topic: str) -> None:
        """The transforms of a TFMessage of ``topic`` (``/tf_static``: static, any other:
        changing)."""
        where = f"{self.path}: {topic}"
        edges = self.edges[TF_STATIC_TOPIC if topic == TF_STATIC_TOPIC else TF_TOPIC]
        for transform in message.transforms:
            parent, child, stamp, pose = pose_of(
                transform, "geometry_msgs/msg/TransformStamped", where
            )
            parent, child = parent.lstrip("/"), child.lstrip("/")
            known = edges.setdefault(child, [parent, [], []])
            if known[0] != parent:
                raise ValueError(
                    f"{where}: frame {child!r} has two parents, {known[0]!r} and {parent!r}"
                )
            known[1].append(stamp)
            known[2].append(pose)

    def trees(self) -> tuple[dict[str, PoseSeries], dict[str, PoseSeries]]:
        """``(dynamic, static)``: child frame -> :class:`PoseSeries` of ``T_parent_child`` (a
        static one holds the last transform sent).

        Raises:
            ValueError: naming the bag and the edge: two transforms at one stamp.
        """
        dynamic = {
            child: _series(
                parent, child, stamps, poses, f"{self.path}: {TF_TOPIC} {parent} -> {child}"
            )
            for child, (parent, stamps, poses) in self.edges[TF_TOPIC].items()
        }
        static = {
            child: PoseSeries(parent, child, np.zeros(1, np.int64), poses[-1][None])
            for child, (parent, _, poses) in self.edges[TF_STATIC_TOPIC].items()
        }
        return dynamic, static


def static_transform(static: dict[str, PoseSeries], frame: str, child: str) -> np.ndarray | None:
    """``T_frame_child`` through the static TF tree (via their common root), or None when the
    tree does not join them."""

    def to_root(name: str) -> tuple[str, np.ndarray]:
        pose, seen = np.eye(4), {name}
        while name in static:
            pose = static[name].poses[0] @ pose
            name = static[name].frame
            if name in seen:
                break
            seen.add(name)
        return name, pose

    frame, child = frame.lstrip("/"), child.lstrip("/")
    root_a, T_root_frame = to_root(frame)
    root_b, T_root_child = to_root(child)
    return np.linalg.inv(T_root_frame) @ T_root_child if root_a == root_b else None


def interpolate(series: PoseSeries, stamps_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The series' poses at ``stamps_ns`` (N,) int64 (see the module docstring).

    Returns:
        ``poses`` (N, 4, 4) float64 (identity where there is none) and ``covered`` (N,) bool.
    """
    from scipy.spatial.transform import Rotation, Slerp

    stamps = np.asarray(stamps_ns, np.int64)
    known = series.stamps
    poses = np.tile(np.eye(4), (len(stamps), 1, 1))
    right = np.searchsorted(known, stamps, side="left")
    exact = (right < len(known)) & (known[np.minimum(right, len(known) - 1)] == stamps)
    poses[exact] = series.poses[right[exact]]
    inside = ~exact & (right > 0) & (right < len(known))
    inside[inside] = known[right[inside]] - known[right[inside] - 1] <= MAX_GAP_NS
    if inside.any():
        seconds = (known - known[0]) * 1e-9
        slerp = Slerp(seconds, Rotation.from_matrix(series.poses[:, :3, :3]))
        at = (stamps[inside] - known[0]) * 1e-9
        poses[inside, :3, :3] = slerp(at).as_matrix()
        for axis in range(3):
            poses[inside, axis, 3] = np.interp(at, seconds, series.poses[:, axis, 3])
    return poses, exact | inside


def tf_chain(
    dynamic: dict[str, PoseSeries], static: dict[str, PoseSeries], frame: str
) -> list[PoseSeries]:
    """The TF edges from ``frame`` up to the root of its tree, nearest first (empty when
    ``frame`` has no parent)."""
    chain, name, seen = [], frame.lstrip("/"), set()
    while name not in seen and (name in dynamic or name in static):
        seen.add(name)
        edge = dynamic.get(name) or static[name]
        chain.append(edge)
        name = edge.frame
    return chain


def chain_poses(
    chain: list[PoseSeries], dynamic: dict[str, PoseSeries], stamps_ns: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``T_root_frame`` (N, 4, 4) at ``stamps_ns`` along a :func:`tf_chain`, and (N,) bool where
    every changing edge covers the stamp."""
    poses = np.tile(np.eye(4), (len(stamps_ns), 1, 1))
    covered = np.ones(len(stamps_ns), bool)
    for edge in chain:
        if edge.child in dynamic and dynamic[edge.child] is edge:
            edge_poses, edge_covered = interpolate(edge, stamps_ns)
            covered &= edge_covered
        else:
            edge_poses = edge.poses[0]
        poses = edge_poses @ poses
    return poses, covered
