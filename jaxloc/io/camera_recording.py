"""A camera recording opened for SG2Loc in one call, and its estimated poses written for evo.

:func:`open_camera_recording` is :func:`~jaxloc.io.camera_sequence.read_camera_sequence` (or,
for a ROS bag, :func:`~jaxloc.io.rosbag_camera.read_bag_camera_sequence`) with the recording's
side files named as files: the map the recording is localized in (its
object embeddings' dimension, and its class embeddings for label images), a label table mapping
raw label ids to classes, and the transform of a 3RScan rescan into its reference scan's frame
(``3RScan.json``, or a 4x4 matrix file). It returns a :class:`~jaxloc.io.CameraRecording`: the query
:func:`jaxloc.sg2loc.localize` takes (``sequence``), the ground truth (``poses_gt``, ``tilt_gt``),
the frames' numbers and timestamps. :func:`write_camera_poses` writes estimated poses in TUM or
KITTI lines (:func:`camera_pose_matrices`: yaw poses with a tilt as 4x4 ``T_world_cam``).
"""

from __future__ import annotations

import os
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxloc.geometry import yaw_pose_to_se3
from jaxloc.io._map_file import read_map_file
from jaxloc.io.camera_frames import check_rigid, read_matrix
from jaxloc.io.camera_sequence import CameraRecording, read_camera_sequence
from jaxloc.io.poses import write_kitti, write_tum
from jaxloc.io.rosbag_camera import BAG_FORMAT, is_bag, read_bag_camera_sequence
from jaxloc.io.rscan_sequence import read_rescan_transform, scan_id_of
from jaxloc.io.scannet import read_label_table
from jaxloc.io.scene_map import FORMAT_NAME, FORMAT_VERSION, load_class_embeddings


def _embedding_dim(map_file: Path) -> int:
    """The dimension of a scene-graph map file's object embeddings (the scene is not built)."""
    embeddings = read_map_file(map_file, FORMAT_NAME, FORMAT_VERSION, "scene graph").get(
        "embeddings"
    )
    if embeddings is None or embeddings.ndim != 2:
        raise ValueError(f"{map_file}: no (objects, dims) 'embeddings' array")
    return int(embeddings.shape[1])


def open_camera_recording(
    path: str | os.PathLike,
    *,
    format: str | None = None,
    map_file: str | os.PathLike | None = None,
    width: int | None = None,
    height: int | None = None,
    embeddings_dir: str | os.PathLike | None = None,
    labels_dir: str | os.PathLike | None = None,
    label_table: str | os.PathLike | None = None,
    label_column: str = "nyu40id",
    patch_shape: tuple[int, int] = (9, 16),
    rescan_json: str | os.PathLike | None = None,
    scan_id: str | None = None,
    transform: str | os.PathLike | np.ndarray | None = None,
    odometry: str | os.PathLike | None = None,
    step: int = 1,
    max_frames: int | None = None,
    use_depth: bool = True,
    use_rgb: bool = True,
    image_topic: str | None = None,
    depth_topic: str | None = None,
    camera_info_topic: str | None = None,
    depth_info_topic: str | None = None,
    odometry_topic: str | None = None,
    odometry_frame: str | None = None,
    label_topic: str | None = None,
    gt_topic: str | None = None,
    gt: str | os.PathLike | None = None,
) -> CameraRecording:
    """Open a camera recording as a query for the map ``map_file`` (see the module docstring).

    Args:
        path: a ScanNet export folder, a ``.sens`` file, a 3RScan scan (or its ``sequence/``),
            or a ROS bag (a ``.bag``, ``.mcap`` or ``.db3`` file, or a ROS 2 bag folder;
            :mod:`jaxloc.io.rosbag_camera`).
        format: "scannet-export", "sens", "3rscan" or "rosbag" (default: detected).
        map_file: the scene-graph map (:func:`~jaxloc.io.save_scene`): embedding files must have
            its dimension, and label images become embeddings with its class embeddings.
        width: the working width, px (default the images'; given alone, the aspect is kept).
        height: the working height, px (likewise).
        embeddings_dir: per-frame ``N.npy`` patch embeddings (default ``embeddings/``).
        labels_dir: per-frame label images ``N.png``, used without an embeddings folder.
        label_table: a ScanNet label table (``.tsv``) mapping the images' raw ids to classes
            (``label_column``, default NYU40; :func:`~jaxloc.io.read_label_table`).
        patch_shape: (rows, cols) of the patch grid made from label images.
        rescan_json: 3RScan's ``3RScan.json``: the poses of rescan ``scan_id`` (default the
            folder's name) go to its reference scan's frame.
        transform: or a (4, 4) rigid transform applied to the poses (an array or a text file of
            four rows of four numbers).
        odometry: a camera-to-odometry pose file for the ego-motion and tilt (default
            ``odometry.txt`` beside the frames, when present).
        step: every ``step``-th frame; max_frames: at most this many frames.
        use_depth: read the depth images into the query.
        use_rgb: read the colour images into the query.
        image_topic: a bag's colour topic (default: the only one; the topics and their
            defaults: :func:`~jaxloc.io.rosbag_camera.read_bag_camera_sequence`; a bag's
            embedding files in ``embeddings_dir`` are named by the frame's stamp in ns).
        depth_topic: a bag's depth topic.
        camera_info_topic: a bag's colour CameraInfo topic.
        depth_info_topic: a bag's depth CameraInfo topic.
        odometry_topic: a bag's ``nav_msgs/Odometry`` topic, or ``"/tf"``.
        odometry_frame: the fixed frame of a bag's ``/tf`` odometry.
        label_topic: a bag's label-image topic (instead of ``labels_dir``).
        gt_topic: a bag's ground-truth topic (``nav_msgs/Odometry``,
            ``geometry_msgs/PoseStamped``).
        gt: a bag's ground truth as a pose file (TUM lines, interpolated to the frames).

    Returns:
        A :class:`~jaxloc.io.CameraRecording`.

    Raises:
        FileNotFoundError, ValueError: naming the file, as
            :func:`~jaxloc.io.camera_sequence.read_camera_sequence`; both ``rescan_json`` and
            ``transform``; a ``patch_shape`` below 1; label images without a ``map_file``
            holding class embeddings; bag options for a folder, folder options for a bag.
    """
    bag_options = {
        "image_topic": image_topic,
        "depth_topic": depth_topic,
        "camera_info_topic": camera_info_topic,
        "depth_info_topic": depth_info_topic,
        "odometry_topic": odometry_topic,
        "odometry_frame": odometry_frame,
        "label_topic": label_topic,
        "gt_topic": gt_topic,
        "gt": gt,
    }
    bag = format == BAG_FORMAT or (format is None and is_bag(path))
    given = [name for name, value in bag_options.items() if value is not None]
    if given and not bag:
        raise ValueError(f"{path}: {', '.join(given)} apply to ROS bags only")
    if bag and labels_dir is not None:
        raise ValueError(f"{path}: a bag's label images come from label_topic, not labels_dir")
    if rescan_json is not None and transform is not None:
        raise ValueError("give rescan_json or transform, not both")
    if min(patch_shape) < 1:
        raise ValueError(f"patch_shape must be >= 1, got {list(patch_shape)}")
    if isinstance(transform, str | os.PathLike):
        transform = check_rigid(read_matrix(transform), str(transform))
    elif rescan_json is not None:
        transform = read_rescan_transform(rescan_json, scan_id or scan_id_of(path))
    label_map = None
    if label_table is not None:
        table = read_label_table(label_table, label_column, key="id")
        label_map = {int(k): v for k, v in table.items() if k.isdigit()}
    dim = classes = None
    if map_file is not None:
        dim = _embedding_dim(Path(map_file))
        with_labels = labels_dir is not None or label_topic is not None
        classes = load_class_embeddings(map_file) if with_labels else None
    common = {
        "embedding_dim": dim,
        "embeddings_dir": embeddings_dir,
        "classes": classes,
        "label_map": label_map,
        "patch_shape": tuple(patch_shape),
        "transform": transform,
        "odometry": odometry,
        "step": step,
        "max_frames": max_frames,
        "use_depth": use_depth,
        "use_rgb": use_rgb,
    }
    if bag:
        return read_bag_camera_sequence(path, width, height, **bag_options, **common)
    return read_camera_sequence(path, format, width, height, labels_dir=labels_dir, **common)


def camera_pose_matrices(poses: np.ndarray, tilt: np.ndarray) -> np.ndarray:
    """(T, 4, 4) float64 ``T_world_cam`` of (T, 4) yaw poses ``(x, y, z, yaw)`` with their
    (T, 2) ``(pitch, roll)`` tilt (:func:`jaxloc.geometry.yaw_pose_to_se3`)."""
    se3 = jax.vmap(yaw_pose_to_se3)(jnp.asarray(poses, jnp.float32), jnp.asarray(tilt))
    return np.asarray(se3.as_matrix(), np.float64).reshape(-1, 4, 4)


def write_camera_poses(
    path: str | os.PathLike, recording: CameraRecording, poses: np.ndarray, format: str = "tum"
) -> None:
    """Write estimated camera-to-world poses of a recording's frames for evo (atomically): the
    (T, 4) yaw poses with the frames' known tilt (``recording.sequence.tilt``), as TUM lines (the
    frame's timestamp in seconds where the frames' timestamps all differ, else its number: a
    ``.sens`` file may carry zero timestamps) or KITTI lines (one 3x4 per frame)."""
    matrices = camera_pose_matrices(poses, recording.sequence.tilt)
    if format == "kitti":
        write_kitti(path, matrices)
        return
    if format != "tum":
        raise ValueError(f"format must be 'tum' or 'kitti', got {format!r}")
    stamps = recording.timestamps
    if stamps is None or len(np.unique(stamps)) != len(stamps):
        stamps = np.asarray(recording.frame_ids, np.float64)
    write_tum(path, matrices, stamps)
