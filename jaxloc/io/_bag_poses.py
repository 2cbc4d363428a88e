"""Poses in a ROS bag, at the camera frames' stamps: the ``/tf`` tree (``tf2_msgs/TFMessage`` on
``/tf`` and ``/tf_static``), ``nav_msgs/Odometry`` and ``geometry_msgs/PoseStamped`` topics, and
pose files, each interpolated to the stamps (linear in position, slerp in rotation).

A pose is a 4x4 float64 ``T_parent_child`` (metres) mapping points of the moving frame into the
fixed one; stamps are int64 nanoseconds. Frame ids lose a leading ``/`` (ROS 1's ``/base_link``
is tf2's ``base_link``).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable
from functools import cached_property
from typing import NamedTuple

import numpy as np
from scipy.spatial.transform import Rotation

from jaxloc.io.poses import format_ns_as_seconds as seconds
from jaxloc.io.poses import read_pose_file

TF = "tf2_msgs/msg/TFMessage"
ODOMETRY = "nav_msgs/msg/Odometry"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"


class Track(NamedTuple):
    """The poses of one moving frame over time.

    Attributes:
        stamps: (M,) int64 ns, increasing; None for a static transform (M = 1).
        poses: (M, 4, 4) float64 ``T_parent_child``.
        where: what the poses came from (the bag and topic, or a file), for errors.
    """

    stamps: np.ndarray | None
    poses: np.ndarray
    where: str


def pose_matrix(position, orientation, where: str) -> np.ndarray:
    """(4, 4) of a ROS position (x, y, z) and quaternion (x, y, z, w); ValueError naming
    ``where`` for a non-finite value or a quaternion far from unit norm."""
    t = np.array([position.x, position.y, position.z], np.float64)
    q = np.array([orientation.x, orientation.y, orientation.z, orientation.w], np.float64)
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(q))) or abs(np.linalg.norm(q) - 1) > 1e-3:
        raise ValueError(f"{where}: a pose with NaN/inf or a quaternion of norm != 1")
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = Rotation.from_quat(q).as_matrix(), t
    return T


def make_track(stamps, poses, where: str) -> Track:
    """A :class:`Track` of poses in time order. ValueError naming ``where`` for a stamp before
    the previous one, or two different poses at one stamp (the same pose twice is kept once)."""
    stamps, poses = np.asarray(stamps, np.int64), np.asarray(poses, np.float64).reshape(-1, 4, 4)
    if not len(stamps):
        raise ValueError(f"{where}: no poses")
    step = np.diff(stamps)
    if np.any(step < 0):
        i = int(np.flatnonzero(step < 0)[0]) + 1
        raise ValueError(
            f"{where}: pose {i}'s stamp {seconds(stamps[i])} s is before pose {i - 1}'s "
            f"({seconds(stamps[i - 1])} s); stamps must increase"
        )
    repeated = np.flatnonzero(step == 0) + 1
    if np.any(np.abs(poses[repeated] - poses[repeated - 1]) > 1e-9):
        i = int(repeated[np.abs(poses[repeated] - poses[repeated - 1]).max(axis=(1, 2)) > 1e-9][0])
        raise ValueError(f"{where}: two different poses at {seconds(stamps[i])} s")
    keep = np.ones(len(stamps), bool)
    keep[repeated] = False
    return Track(stamps[keep], poses[keep], where)


def interpolate(track: Track, at_ns: np.ndarray, frames, tolerance_ns: int = 0) -> np.ndarray:
    """(K, 4, 4) poses of ``track`` at the stamps ``at_ns`` (K,) of the frames ``frames``.
    ValueError naming the track and the first frame outside its span (by more than
    ``tolerance_ns``: those take the nearest end's pose)."""
    at = np.asarray(at_ns, np.int64)
    if track.stamps is None:
        return np.repeat(track.poses[:1], len(at), axis=0)
    lo, hi = track.stamps[0], track.stamps[-1]
    outside = np.flatnonzero((at < lo - tolerance_ns) | (at > hi + tolerance_ns))
    if outside.size:
        k = int(outside[0])
        raise ValueError(
            f"{track.where} covers {seconds(lo)}-{seconds(hi)} s; frame {frames[k]} at "
            f"{seconds(at[k])} s is outside it"
        )
    at = np.clip(at, lo, hi)
    if len(track.stamps) == 1:
        return np.repeat(track.poses[:1], len(at), axis=0)
    i = np.clip(np.searchsorted(track.stamps, at, side="right") - 1, 0, len(track.stamps) - 2)
    span = (track.stamps[i + 1] - track.stamps[i]).astype(np.float64)
    w = (at - track.stamps[i]).astype(np.float64) / span
    a, b = track.poses[i], track.poses[i + 1]
    ra, rb = Rotation.from_matrix(a[:, :3, :3]), Rotation.from_matrix(b[:, :3, :3])
    out = np.repeat(np.eye(4)[None], len(at), axis=0)
    out[:, :3, :3] = (
        ra * Rotation.from_rotvec(w[:, None] * (ra.inv() * rb).as_rotvec())
    ).as_matrix()
    out[:, :3, 3] = (1 - w)[:, None] * a[:, :3, 3] + w[:, None] * b[:, :3, 3]
    exact = at == track.stamps[i]
    out[exact] = a[exact]
    exact = at == track.stamps[i + 1]
    out[exact] = b[exact]
    return out


def _frame(frame_id) -> str:
    return str(frame_id).lstrip("/")


class TfTree:
    """The ``/tf`` tree of an open bag (read on first use): per child frame, its parent and the
    :class:`Track` of ``T_parent_child``.

    Args:
        topics: the bag's topics (``AnyReader.topics``: name -> info with ``msgtype``).
        bag: the bag's path, for errors.
        messages: ``messages(topic)``, the deserialized messages of a topic in the bag's order.
    """

    def __init__(self, topics, bag: str, messages: Callable[[str], Iterable]):
        self.topics, self.bag, self.messages = topics, bag, messages

    @cached_property
    def edges(self) -> dict[str, tuple[str, Track]]:
        """child frame -> (parent frame, track)."""
        found: dict[str, tuple[str, list, list, bool]] = {}
        for topic, info in sorted(self.topics.items()):
            if info.msgtype != TF:
                continue
            static, where = topic.endswith("tf_static"), f"{self.bag}: {topic}"
            for message in self.messages(topic):
                for tf in message.transforms:
                    parent, child = _frame(tf.header.frame_id), _frame(tf.child_frame_id)
                    entry = found.setdefault(child, (parent, [], [], static))
                    if entry[0] != parent:
                        raise ValueError(
                            f"{where}: frame {child!r} has two parents ({entry[0]!r}, {parent!r})"
                        )
                    stamp = tf.header.stamp.sec * 10**9 + tf.header.stamp.nanosec
                    transform = tf.transform
                    entry[1].append(stamp)
                    entry[2].append(pose_matrix(transform.translation, transform.rotation, where))
        edges = {}
        for child, (parent, stamps, poses, static) in found.items():
            where = f"{self.bag}: {'/tf_static' if static else '/tf'} ({parent} -> {child})"
            track = (
                Track(None, poses[-1][None], where) if static else make_track(stamps, poses, where)
            )
            edges[child] = (parent, track)
        return edges

    def ancestors(self, frame: str) -> list[str]:
        """The frames above ``frame`` in the tree, nearest first."""
        out = []
        while frame in self.edges and len(out) <= len(self.edges):
            frame = self.edges[frame][0]
            out.append(frame)
        return out

    def moves(self, frame: str, target: str) -> bool:
        """Whether a /tf (not static) transform lies between ``frame`` and ``target`` above it."""
        while frame != target:
            parent, track = self.edges[frame]
            if track.stamps is not None:
                return True
            frame = parent
        return False

    def poses(self, frame: str, target: str, at_ns, frames) -> np.ndarray:
        """(K, 4, 4) ``T_target_frame`` at the stamps ``at_ns`` (K,) (``target`` must be an
        ancestor of ``frame``, or ``frame`` itself)."""
        out = np.repeat(np.eye(4)[None], len(at_ns), axis=0)
        while frame != target:
            parent, track = self.edges[frame]
            out = interpolate(track, at_ns, frames) @ out
            frame = parent
        return out


def frame_poses(
    tree: TfTree, topics, topic, camera_frame, at_ns, frames, image_topic, option
) -> dict[int, np.ndarray]:
    """frame number -> (4, 4) camera pose from an Odometry topic (its child frame carried to the
    camera through the tree) or a PoseStamped topic (the camera's own pose). Images without a
    ``frame_id``, or an Odometry without a ``child_frame_id``, take the pose as the camera's."""
    kinds = sorted(t for t, i in topics.items() if i.msgtype in (ODOMETRY, POSE_STAMPED))
    if topic not in kinds:
        kind = f"a {topics[topic].msgtype}" if topic in topics else "not in the bag"
        raise ValueError(
            f"{tree.bag}: {option}={topic!r} is {kind}; nav_msgs/Odometry or "
            f"geometry_msgs/PoseStamped topics: {', '.join(kinds) or 'none'}"
        )
    where, stamps, poses, child = f"{tree.bag}: {topic}", [], [], None
    for message in tree.messages(topic):
        stamps.append(message.header.stamp.sec * 10**9 + message.header.stamp.nanosec)
        pose = message.pose.pose if topics[topic].msgtype == ODOMETRY else message.pose
        poses.append(pose_matrix(pose.position, pose.orientation, where))
        if topics[topic].msgtype == ODOMETRY:
            child = _frame(message.child_frame_id)
    out = interpolate(make_track(stamps, poses, where), at_ns, frames)
    if child and camera_frame and child != camera_frame:
        if child not in tree.ancestors(camera_frame):
            raise ValueError(
                f"{where}: /tf and /tf_static do not carry its frame {child!r} to the camera's "
                f"{camera_frame!r} ({image_topic})"
            )
        out = out @ tree.poses(camera_frame, child, at_ns, frames)
    return dict(zip(frames, out, strict=True))


def track_poses(
    tree: TfTree, topics, camera_frame, topic, fixed_frame, at_ns, frames, image_topic
) -> dict[int, np.ndarray] | None:
    """frame number -> (4, 4) camera-to-odometry pose from the Odometry topic (``topic``, or the
    only one), else from the /tf tree (``topic`` "/tf", or none named and no Odometry topic):
    the camera frame in ``fixed_frame`` (default ``odom`` when above it, else the root). None
    when nothing gives one and nothing was named."""
    odometries = sorted(t for t, i in topics.items() if i.msgtype == ODOMETRY)
    tf_topics = sorted(t for t, i in topics.items() if i.msgtype == TF)
    if topic is None and len(odometries) > 1:
        raise ValueError(
            f"{tree.bag}: {len(odometries)} nav_msgs/Odometry topics ({', '.join(odometries)}); "
            "name one with odometry_topic="
        )
    topic = topic if topic is not None or not odometries else odometries[0]
    if topic is not None and topic not in tf_topics:
        if topic not in odometries:
            raise ValueError(
                f"{tree.bag}: odometry_topic={topic!r} is not a nav_msgs/Odometry or /tf topic "
                f"(candidates: {', '.join(odometries + tf_topics) or 'none'})"
            )
        return frame_poses(tree, topics, topic, camera_frame, at_ns, frames, image_topic,
                           "odometry_topic")  # fmt: skip
    above = tree.ancestors(camera_frame)
    target = fixed_frame if fixed_frame is not None else ("odom" if "odom" in above else None)
    target = target or (above[-1] if above else None)
    if target is None or target not in above or not tree.moves(camera_frame, target):
        if topic is None and fixed_frame is None:
            return None
        raise ValueError(
            f"{tree.bag}: /tf has no moving chain from {image_topic}'s frame {camera_frame!r} "
            f"up to {target!r} (frames above it: {', '.join(above) or 'none'}; odometry_frame=)"
        )
    return dict(zip(frames, tree.poses(camera_frame, target, at_ns, frames), strict=True))


def pose_file_track(
    path: str | os.PathLike, numbers, stamps_ns: np.ndarray, frames
) -> dict[int, np.ndarray]:
    """frame number -> (4, 4) pose from a pose file: TUM lines interpolated to the frames'
    stamps, or KITTI / 4x4 lines, one per colour message (``numbers``) in order."""
    poses = read_pose_file(path)
    if poses.timestamps is None:
        if len(poses.poses) != len(numbers):
            raise ValueError(
                f"{path}: {len(poses.poses)} {poses.format} poses for the bag's {len(numbers)} "
                "colour messages (one per message, in order)"
            )
        return {n: poses.poses[n] for n in frames}
    order = np.argsort(poses.timestamps, kind="stable")
    track = make_track(poses.timestamps[order], poses.poses[order], str(path))
    at = stamps_ns[list(frames)]
    return dict(
        zip(frames, interpolate(track, at, frames, poses.match_tolerance_ns()), strict=True)
    )
