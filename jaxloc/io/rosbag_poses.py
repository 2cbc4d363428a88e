"""Estimated poses as a bag that Foxglove, RViz (through ``ros2 bag play``) and any ROS 2 tool
show without jaxloc: standard messages only, written with ``rosbags``.

:func:`write_pose_bag` writes, for each input (a scan, a frame) in order:

* on ``/jaxloc/pose`` (:data:`POSE_TOPIC`), a ``geometry_msgs/PoseStamped`` of each VALID
  estimate, stamped as its input (header stamp and log time), in the frame ``map`` (the pose
  ``T_map_sensor``: the sensor's position and orientation in the map);
* on ``/jaxloc/valid`` (:data:`VALID_TOPIC`), a ``std_msgs/Bool`` per input, valid or not,
  logged at its stamp.

A path ending in ``.mcap`` is one MCAP file (ROS 2 profile, message definitions inside), which
Foxglove opens as it is; any other path is a new ROS 2 bag folder (``metadata.yaml`` and an MCAP
or sqlite3 storage file) for ``ros2 bag play``. Either is written whole or not at all (in a
temporary folder beside it, then renamed).
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from jaxloc.io._rigid import rigid_mask

#: The topic of the estimates (``geometry_msgs/PoseStamped``).
POSE_TOPIC = "/jaxloc/pose"
#: The topic of the verdicts (``std_msgs/Bool``, one per input).
VALID_TOPIC = "/jaxloc/valid"
#: The poses' frame by default.
MAP_FRAME = "map"
#: Storage of a bag folder: "mcap" (ROS 2 Iron and later by default) or "sqlite3" (Humble).
STORAGES = ("mcap", "sqlite3")
_MAX_STAMP_NS = (2**31 - 1) * 10**9  # a ROS 2 Time's sec is an int32


def _checked(path: Path, stamps_ns, poses, valid) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    stamps = np.asarray(stamps_ns)
    poses = np.asarray(poses, np.float64)
    valid = np.asarray(valid)
    count = len(stamps) if stamps.ndim == 1 else -1
    if poses.shape != (count, 4, 4) or valid.shape != (count,) or valid.dtype != bool:
        raise ValueError(
            f"{path}: need (N,) integer stamps, (N, 4, 4) poses and (N,) bool flags, got "
            f"{stamps.shape}, {poses.shape}, {valid.shape} {valid.dtype}"
        )
    if not np.issubdtype(stamps.dtype, np.integer):
        raise ValueError(f"{path}: stamps must be integer nanoseconds, got {stamps.dtype}")
    stamps = stamps.astype(np.int64)
    if count and (stamps.min() < 0 or stamps.max() > _MAX_STAMP_NS):
        raise ValueError(f"{path}: stamps must be in [0, 2**31) seconds (a ROS time)")
    if len(np.unique(stamps)) != count:
        raise ValueError(f"{path}: two inputs share a stamp: nothing written")
    bad = np.flatnonzero(valid & ~rigid_mask(poses))
    if bad.size:
        raise ValueError(
            f"{path}: the pose of input {bad[0]} is valid but not a finite rigid transform"
        )
    return stamps, poses, valid


def _messages(typestore, stamps, poses, valid, frame_id: str):
    """``(topic, stamp, message)`` in time order."""
    from scipy.spatial.transform import Rotation

    types = typestore.types
    Time, Header = types["builtin_interfaces/msg/Time"], types["std_msgs/msg/Header"]
    Point, Quaternion = types["geometry_msgs/msg/Point"], types["geometry_msgs/msg/Quaternion"]
    Pose, PoseStamped = types["geometry_msgs/msg/Pose"], types["geometry_msgs/msg/PoseStamped"]
    Bool = types["std_msgs/msg/Bool"]
    quaternions = (
        Rotation.from_matrix(poses[:, :3, :3]).as_quat().reshape(-1, 4) if len(poses) else []
    )
    for stamp, pose, ok, q in zip(stamps.tolist(), poses, valid.tolist(), quaternions, strict=True):
        if ok:
            q = q if q[3] >= 0 else -q
            header = Header(
                stamp=Time(sec=stamp // 10**9, nanosec=stamp % 10**9), frame_id=frame_id
            )
            body = Pose(
                position=Point(x=float(pose[0, 3]), y=float(pose[1, 3]), z=float(pose[2, 3])),
                orientation=Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])),
            )
            yield POSE_TOPIC, stamp, PoseStamped(header=header, pose=body)
        yield VALID_TOPIC, stamp, Bool(data=bool(ok))


def write_pose_bag(
    path: str | os.PathLike,
    stamps_ns: np.ndarray,
    poses: np.ndarray,
    valid: np.ndarray,
    *,
    frame_id: str = MAP_FRAME,
    storage: str = "mcap",
) -> int:
    """Write estimated poses as a bag (see the module docstring).

    Args:
        path: ``NAME.mcap`` (one MCAP file, replaced if it exists) or a new bag folder.
        stamps_ns: (N,) integer nanoseconds of the inputs, distinct, in [0, 2**31) s.
        poses: (N, 4, 4) float64 ``T_map_sensor`` (those of invalid inputs are not written).
        valid: (N,) bool.
        frame_id: the poses' frame.
        storage: of a bag folder, "mcap" or "sqlite3".

    Returns:
        The number of poses written (the valid inputs).

    Raises:
        ValueError: naming ``path``: shapes or dtypes, stamps out of range or repeated, a valid
            pose that is not finite or not rigid, an unknown storage, a folder that exists.
    """
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    path = Path(path)
    stamps, poses, valid = _checked(path, stamps_ns, poses, valid)
    single = path.suffix == ".mcap"
    if storage not in STORAGES or (single and storage != "mcap"):
        raise ValueError(f"{path}: storage must be one of {STORAGES} (an .mcap file is mcap)")
    if not single and path.exists():
        raise ValueError(f"{path}: exists; a bag folder is written new (remove it first)")
    typestore = get_typestore(Stores.ROS2_HUMBLE)
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    path.parent.mkdir(parents=True, exist_ok=True)
    scratch = Path(tempfile.mkdtemp(prefix=f".{path.name}.", dir=path.parent))
    try:
        folder = scratch / "bag"
        with Writer(folder, version=8, storage_plugin=plugin) as writer:
            connections = {
                POSE_TOPIC: writer.add_connection(
                    POSE_TOPIC, "geometry_msgs/msg/PoseStamped", typestore=typestore
                ),
                VALID_TOPIC: writer.add_connection(
                    VALID_TOPIC, "std_msgs/msg/Bool", typestore=typestore
                ),
            }
            for topic, stamp, message in _messages(typestore, stamps, poses, valid, frame_id):
                data = typestore.serialize_cdr(message, message.__msgtype__)
                writer.write(connections[topic], stamp, data)
        if single:
            os.replace(folder / "bag.mcap", path)
        else:
            os.rename(folder, path)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    return int(valid.sum())
