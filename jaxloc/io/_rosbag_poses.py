"""Poses in a bag at given stamps, for every bag reader: pose topics (``nav_msgs/Odometry``,
``geometry_msgs/PoseStamped``, ``PoseWithCovarianceStamped``, ``TransformStamped``), the TF tree
(``tf2_msgs/TFMessage`` on ``/tf`` and ``/tf_static``), which of them is the odometry, and SE(3)
interpolation to the stamps of a sensor's messages.

A pose is a 4x4 float64 ``T_parent_child`` (metres; ``p_parent = T @ p_child``) from a message's
position (or translation) and unit quaternion (x, y, z, w); stamps are int64 nanoseconds. Frame
ids lose a leading ``/`` (ROS 1's ``/base_link`` is tf2's ``base_link``). A pose series is
interpolated at a stamp between its two neighbouring samples (translation linearly, rotation by
slerp); a stamp before the first sample or after the last (by more than a tolerance, within which
it takes the nearest end's pose), or between samples more than :data:`MAX_GAP_NS` apart (a gap in
the recording, not motion to interpolate over), has none.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from jaxloc.io._rosbag import deserialize, messages, pick_topic, seconds, topic_types, topics_of
from jaxloc.io.poses import QUATERNION_TOLERANCE

TF_TYPE = "tf2_msgs/msg/TFMessage"
#: The TF topics: transforms that change, and those that do not.
TF_TOPIC, TF_STATIC_TOPIC = "/tf", "/tf_static"
ODOMETRY_TYPE, POSE_STAMPED_TYPE = "nav_msgs/msg/Odometry", "geometry_msgs/msg/PoseStamped"
TRANSFORM_TYPE = "geometry_msgs/msg/TransformStamped"
#: Message types whose messages are poses (``T_frame_child``), for odometry and ground truth.
POSE_TYPES = (
    ODOMETRY_TYPE,
    POSE_STAMPED_TYPE,
    "geometry_msgs/msg/PoseWithCovarianceStamped",
    TRANSFORM_TYPE,
)
#: ``odometry_topic`` value that reads no odometry.
NO_ODOMETRY = "none"
#: Nanoseconds: a stamp between two pose samples farther apart than this has no pose.
MAX_GAP_NS = 1_000_000_000


def _frame(frame_id: Any) -> str:
    return str(frame_id).lstrip("/")


def pose_matrix(position: Any, orientation: Any, where: str) -> np.ndarray:
    """(4, 4) of a ROS position (x, y, z) and quaternion (x, y, z, w); ValueError naming
    ``where`` for a non-finite value or a quaternion far from unit norm."""
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
    header = message.header
    stamp = int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)
    if msgtype == TRANSFORM_TYPE:
        t = message.transform
        pose = pose_matrix(t.translation, t.rotation, where)
        return _frame(header.frame_id), _frame(message.child_frame_id), stamp, pose
    body = message.pose if msgtype == POSE_STAMPED_TYPE else message.pose.pose
    child = _frame(message.child_frame_id) if msgtype == ODOMETRY_TYPE else None
    pose = pose_matrix(body.position, body.orientation, where)
    return _frame(header.frame_id), child, stamp, pose


class PoseSeries(NamedTuple):
    """Poses of one frame in another over time.

    Attributes:
        frame: the fixed frame; child: the moving one (None: a PoseStamped's, the sensor's own).
        stamps: (M,) int64 ns, increasing; None for a static transform (M = 1).
        poses: (M, 4, 4) float64 ``T_frame_child``.
        where: what the poses came from (the bag and topic, or a file), for errors.
    """

    frame: str
    child: str | None
    stamps: np.ndarray | None
    poses: np.ndarray
    where: str


def pose_series(frame, child, stamps, poses, where: str) -> PoseSeries:
    """A :class:`PoseSeries` sorted by stamp; a stamp given twice with two different poses is a
    ValueError naming ``where`` (one with the same pose is kept once), as is no pose at all."""
    stamps = np.asarray(stamps, np.int64).reshape(-1)
    poses = np.asarray(poses, np.float64).reshape(-1, 4, 4)
    if not len(stamps):
        raise ValueError(f"{where}: no poses")
    order = np.argsort(stamps, kind="stable")
    stamps, poses = stamps[order], poses[order]
    same = np.flatnonzero(np.diff(stamps) == 0)
    differ = same[np.abs(poses[same] - poses[same + 1]).max(axis=(1, 2), initial=0) > 1e-9]
    if differ.size:
        raise ValueError(f"{where}: two different poses at {seconds(stamps[differ[0]])} s")
    keep = np.ones(len(stamps), bool)
    keep[same + 1] = False
    return PoseSeries(frame, child, stamps[keep], poses[keep], where)


def span(series: PoseSeries) -> tuple[int, int]:
    """The first and last stamp (ns) of a changing series."""
    return int(series.stamps[0]), int(series.stamps[-1])


def interpolate(
    series: PoseSeries, stamps_ns, *, tolerance_ns: int = 0, max_gap_ns: int | None = MAX_GAP_NS
) -> tuple[np.ndarray, np.ndarray]:
    """The series' poses at ``stamps_ns`` (N,) int64 (see the module docstring; ``max_gap_ns``
    None: no gap is too long).

    Returns:
        ``poses`` (N, 4, 4) float64 (identity where there is none) and ``covered`` (N,) bool.
    """
    from scipy.spatial.transform import Rotation, Slerp

    at = np.asarray(stamps_ns, np.int64).reshape(-1)
    if series.stamps is None:
        return np.repeat(series.poses[:1], len(at), axis=0), np.ones(len(at), bool)
    known = series.stamps
    at = np.where((at < known[0]) & (at >= known[0] - tolerance_ns), known[0], at)
    at = np.where((at > known[-1]) & (at <= known[-1] + tolerance_ns), known[-1], at)
    poses = np.tile(np.eye(4), (len(at), 1, 1))
    right = np.searchsorted(known, at, side="left")
    exact = (right < len(known)) & (known[np.minimum(right, len(known) - 1)] == at)
    poses[exact] = series.poses[right[exact]]
    inside = ~exact & (right > 0) & (right < len(known))
    if max_gap_ns is not None:
        inside[inside] = known[right[inside]] - known[right[inside] - 1] <= max_gap_ns
    if inside.any():
        offsets = (known - known[0]) * 1e-9
        slerp = Slerp(offsets, Rotation.from_matrix(series.poses[:, :3, :3]))
        where = (at[inside] - known[0]) * 1e-9
        poses[inside, :3, :3] = slerp(where).as_matrix()
        for axis in range(3):
            poses[inside, axis, 3] = np.interp(where, offsets, series.poses[:, axis, 3])
    return poses, exact | inside


class TfTree:
    """The TF tree of a bag, message by message (:meth:`add`): per child frame its parent and
    the :class:`PoseSeries` of ``T_parent_child`` (each child has one parent; a transform of a
    ``*tf_static`` topic is static, the last one sent kept)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._found: dict[str, tuple[str, list, list, str]] = {}
        self._edges: dict[str, PoseSeries] | None = None

    def add(self, message: Any, topic: str) -> None:
        """The transforms of a TFMessage of ``topic``."""
        where, self._edges = f"{self.path}: {topic}", None
        for transform in message.transforms:
            parent, child, stamp, pose = pose_of(transform, TRANSFORM_TYPE, where)
            known = self._found.setdefault(child, (parent, [], [], topic))
            if known[0] != parent:
                raise ValueError(
                    f"{where}: frame {child!r} has two parents, {known[0]!r} and {parent!r}"
                )
            known[1].append(stamp)
            known[2].append(pose)

    @property
    def edges(self) -> dict[str, PoseSeries]:
        """child frame -> :class:`PoseSeries` of ``T_parent_child`` (``frame`` the parent).

        Raises:
            ValueError: naming the bag and the edge: two transforms at one stamp.
        """
        if self._edges is None:
            self._edges = {}
            for child, (parent, stamps, poses, topic) in self._found.items():
                where = f"{self.path}: {topic} ({parent} -> {child})"
                if topic.endswith("tf_static"):
                    edge = PoseSeries(parent, child, None, poses[-1][None], where)
                else:
                    edge = pose_series(parent, child, stamps, poses, where)
                self._edges[child] = edge
        return self._edges

    def ancestors(self, frame: str) -> list[str]:
        """The frames above ``frame`` in the tree, nearest first."""
        out, edges = [], self.edges
        while frame in edges and len(out) <= len(edges):
            frame = edges[frame].frame
            out.append(frame)
        return out

    def chain(self, frame: str, target: str) -> list[PoseSeries]:
        """The edges from ``frame`` up to ``target`` (one of its :meth:`ancestors`, or itself)."""
        out = []
        while frame != target:
            out.append(self.edges[frame])
            frame = out[-1].frame
        return out

    def poses(self, frame: str, target: str, stamps_ns) -> tuple[np.ndarray, np.ndarray]:
        """``T_target_frame`` (N, 4, 4) at ``stamps_ns`` and (N,) bool where every changing edge
        between them covers the stamp."""
        poses = np.tile(np.eye(4), (len(stamps_ns), 1, 1))
        covered = np.ones(len(stamps_ns), bool)
        for edge in self.chain(frame, target):
            edge_poses, edge_covered = interpolate(edge, stamps_ns)
            poses, covered = edge_poses @ poses, covered & edge_covered
        return poses, covered

    def join(self, child: str, frame: str, stamps_ns) -> tuple[np.ndarray, np.ndarray] | None:
        """``T_child_frame`` (N, 4, 4) at the stamps and where it is covered: through the tree
        when ``child`` is above ``frame``, else through the static transforms of their common
        root; None when the tree does not join them."""
        if child in self.ancestors(frame):
            return self.poses(frame, child, stamps_ns)
        root_a, T_root_child = self._static_root(child)
        root_b, T_root_frame = self._static_root(frame)
        if root_a != root_b:
            return None
        pose = np.linalg.inv(T_root_child) @ T_root_frame
        return np.repeat(pose[None], len(stamps_ns), axis=0), np.ones(len(stamps_ns), bool)

    def _static_root(self, name: str) -> tuple[str, np.ndarray]:
        """The frame above ``name`` that static transforms reach, and ``T_that_name``."""
        pose, seen, edges = np.eye(4), {name}, self.edges
        while name in edges and edges[name].stamps is None:
            pose = edges[name].poses[0] @ pose
            name = edges[name].frame
            if name in seen:
                break
            seen.add(name)
        return name, pose


class BagPoses:
    """The pose topics and the TF tree of a bag, message by message (:meth:`add`, from one pass
    over the bag with other topics: :meth:`topics` are those it reads)."""

    def __init__(self, reader: Any, path: Path, pose_topics) -> None:
        self.path = path
        self.tree = TfTree(path)
        self.tf_topics = set(topics_of(reader, (TF_TYPE,)))
        self._pose_topics = set(pose_topics) - self.tf_topics
        self._found: dict[str, tuple] = {}

    @property
    def topics(self) -> list[str]:
        """The topics :meth:`add` takes: the pose topics and every TF topic."""
        return sorted(self._pose_topics | self.tf_topics)

    def add(self, topic: str, msgtype: str, message: Any) -> None:
        """A message of one of :attr:`topics`."""
        if topic in self.tf_topics:
            self.tree.add(message, topic)
            return
        where = f"{self.path}: {topic}"
        frame, child, stamp, pose = pose_of(message, msgtype, where)
        known = self._found.setdefault(topic, (frame, child, [], []))
        if known[:2] != (frame, child):
            raise ValueError(f"{where}: the frames change from {known[:2]} to {(frame, child)}")
        known[2].append(stamp)
        known[3].append(pose)

    def series(self, topic: str) -> PoseSeries:
        """The poses of a pose topic; ValueError naming the bag and topic when it has none."""
        if topic not in self._found:
            raise ValueError(f"{self.path}: {topic}: no message")
        frame, child, stamps, poses = self._found[topic]
        return pose_series(frame, child, stamps, poses, f"{self.path}: {topic}")


def read_bag_poses(reader: Any, path: Path, pose_topics: Sequence[str]) -> BagPoses:
    """The :class:`BagPoses` of ``pose_topics`` and the TF topics, read in one pass."""
    found = BagPoses(reader, path, [t for t in pose_topics if t is not None])
    for topic, msgtype, _, raw in messages(reader, path, found.topics):
        found.add(topic, msgtype, deserialize(reader, raw, msgtype, f"{path}: {topic}"))
    return found


def pick_odometry(reader: Any, path: Path, named: str | None) -> str | None:
    """The odometry's topic: ``named`` (a pose or TF topic; :data:`NO_ODOMETRY`: none), else the
    only ``nav_msgs/Odometry`` topic, else ``/tf`` when the bag has one, else None.

    Raises:
        ValueError: naming the bag: a named topic of another type or absent; several Odometry
            topics and none named (listing them).
    """
    tf = topics_of(reader, (TF_TYPE,))
    if named == NO_ODOMETRY:
        return None
    if named is not None:
        candidates = topics_of(reader, POSE_TYPES) + tf
        return pick_topic(reader, path, candidates, named, "nav_msgs/Odometry or /tf",
                          "odometry_topic")  # fmt: skip
    found = pick_topic(reader, path, topics_of(reader, (ODOMETRY_TYPE,)), None, "odometry",
                       "odometry_topic")  # fmt: skip
    if found is None and topic_types(reader).get(TF_TOPIC) == TF_TYPE:
        return TF_TOPIC
    return found


class Poses(NamedTuple):
    """A sensor's poses at its stamps: ``poses`` (N, 4, 4) float64, ``covered`` (N,) bool,
    ``first`` and ``last`` the stamps (ns) their source covers, ``where`` it (for errors)."""

    poses: np.ndarray
    covered: np.ndarray
    first: int
    last: int
    where: str


def sensor_poses(
    found: BagPoses,
    topic: str,
    frame: str,
    stamps_ns,
    what: str,
    fixed_frame: str | None = None,
    required: bool = True,
) -> Poses | None:
    """The poses of the sensor's ``frame`` at ``stamps_ns`` from ``topic``:

    * a pose topic: its poses interpolated, carried to ``frame`` through the TF tree where their
      child frame is another (:meth:`TfTree.join`; a PoseStamped's, or one without a
      ``frame_id`` on either side, are the sensor's own);
    * a TF topic: ``T_fixed_frame`` through the tree, ``fixed_frame`` by default ``odom`` where
      it is above ``frame``, else the tree's root; None when no changing transform lies between
      them and not ``required``.

    ``what`` names the sensor's messages in errors ("clouds").

    Raises:
        ValueError: naming the bag and topic: a tree that does not join the poses to ``frame``,
            a required TF that does not move it, bad poses.
    """
    path, frame, tree = found.path, _frame(frame), found.tree
    if topic in found.tf_topics:
        above = tree.ancestors(frame)
        target = fixed_frame or ("odom" if "odom" in above else (above[-1] if above else None))
        chain = tree.chain(frame, target) if target in above else []
        moving = [edge for edge in chain if edge.stamps is not None]
        if not moving:
            if not required:
                return None
            raise ValueError(
                f"{path}: {topic} does not move {what} frame {frame!r} relative to {target!r} "
                f"(frames above it: {above or 'none'})"
            )
        poses, covered = tree.poses(frame, target, stamps_ns)
        first = max(span(edge)[0] for edge in moving)
        last = min(span(edge)[1] for edge in moving)
        return Poses(poses, covered, first, last, f"{path}: {topic} ({target} -> {frame})")
    series = found.series(topic)
    poses, covered = interpolate(series, stamps_ns)
    if series.child and frame and series.child != frame:
        joined = tree.join(series.child, frame, stamps_ns)
        if joined is None:
            raise ValueError(
                f"{series.where}: poses of frame {series.child!r}, {what} in {frame!r}, and /tf "
                "and /tf_static do not join them"
            )
        poses, covered = poses @ joined[0], covered & joined[1]
    return Poses(poses, covered, *span(series), series.where)
