"""Camera recordings from ROS bags, read with the ``rosbags`` library (no ROS installation
needed): a ROS 1 ``.bag``, a ROS 2 bag folder (sqlite3 or MCAP storage) or a bare ``.mcap`` /
``.db3`` file, opened as the same :class:`~jaxloc.io.CameraRecording` the folder
layouts give (:func:`jaxloc.io.open_camera_recording` calls :func:`read_bag_camera_sequence`).

Topics (each picked when it is the only one of its kind, else named by its keyword):

* colour (``image_topic``): ``sensor_msgs/Image`` in ``rgb8``, ``bgr8``, ``rgba8``, ``bgra8``
  or ``mono8``, or ``sensor_msgs/CompressedImage`` (JPEG or PNG). Its messages are the frames,
  numbered 0, 1, ... in the bag's order; a frame's time is its header stamp (the bag's receive
  time where the stamp is 0), and the stamps must increase.
* depth (``depth_topic``, optional): ``sensor_msgs/Image`` in ``16UC1`` (millimetres) or
  ``32FC1`` (metres; NaN, inf and values <= 0 are invalid), matched to each frame by stamp
  (within ``sync_tolerance``).
* intrinsics (``camera_info_topic``, ``depth_info_topic``): ``sensor_msgs/CameraInfo``, its
  first message's ``K`` (the images are taken as undistorted); by default the ``camera_info``
  beside the image topic (``/cam/color/image_raw`` -> ``/cam/color/camera_info``), else the only
  one. Depth of the colour images' size without one of its own uses the colour intrinsics.
* ego-motion (``odometry_topic``, optional): ``nav_msgs/Odometry`` (the pose of its
  ``child_frame_id``, carried to the camera's frame through ``/tf_static`` and ``/tf``) or
  another pose topic, or the ``/tf`` tree itself (``odometry_topic="/tf"``, the default without
  an Odometry topic): the camera frame's pose in ``odometry_frame`` (default ``odom`` when the
  tree has it above the camera, else the tree's root); ``"none"``: none. Poses are interpolated
  to the frame stamps (linear in position, slerp in rotation,
  :func:`jaxloc.io._rosbag_poses.interpolate`); a frame outside the poses' time span, or
  between two poses more than a second apart, is an error.
* ground truth (``gt_topic`` or ``gt``, optional): a ``nav_msgs/Odometry`` topic (carried to the
  camera as above) or a ``geometry_msgs/PoseStamped`` topic (the camera's own pose), or a pose
  file (:func:`~jaxloc.io.read_pose_file`: TUM lines interpolated to the frame stamps; KITTI or
  4x4 lines, one per colour message). Without odometry, the ground truth gives the ego-motion.
* patch embeddings: a label-image topic (``label_topic``: ``sensor_msgs/Image`` in ``mono8`` /
  ``8UC1`` / ``mono16`` / ``16UC1``, class ids, 0 = unknown; matched by stamp and turned into
  embeddings with the map's class embeddings as :mod:`jaxloc.io.label_images` does), or files
  ``<stamp>.npy`` named by the frame's stamp in integer nanoseconds (``embeddings_dir``, default
  ``embeddings/`` beside a bag file or inside a ROS 2 bag folder).

Frames are read one at a time (the bag's index gives each message's place), never the whole bag.
Conventions: the camera's frame is its optical frame (OpenCV axes: x right, y down, z forward;
REP 103's ``*_optical_frame``), the odometry frame is gravity-aligned with z up; poses are 4x4
``T_world_cam`` in metres. Every error is one line naming the bag and the topic.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable, Mapping
from pathlib import Path

import numpy as np

from jaxloc.io._rosbag import (
    first_message,
    is_bag as is_bag,
    no_topic,
    open_bag,
    pick_topic,
    seconds,
    topics_of,
)
from jaxloc.io._rosbag_images import (
    CAMERA_INFO,
    COMPRESSED,
    DEPTH_ENCODINGS,
    IMAGE,
    BagTopic,
    camera_intrinsics,
    color_image,
    depth_image,
    image_encoding,
    label_image,
)
from jaxloc.io._rosbag_poses import (
    NO_ODOMETRY,
    POSE_TYPES,
    Poses,
    interpolate,
    pick_odometry,
    pose_series,
    read_bag_poses,
    sensor_poses,
)
from jaxloc.io.camera_frames import Frame, FrameSource
from jaxloc.io.camera_sequence import (
    CameraRecording,
    Odometry,
    check_label_classes,
    check_working_size,
    embedding_files,
    sequence_from_frames,
    working_camera,
)
from jaxloc.io.label_images import patch_embeddings_from_labels
from jaxloc.io.poses import read_pose_file
from jaxloc.io.scene_map import ClassEmbeddings

#: The ``format`` of a recording read from a bag.
BAG_FORMAT = "rosbag"


def _info_topic(reader, path: Path, image: str, named: str | None, option: str):
    """The CameraInfo topic of ``image``: ``named``, the ``camera_info`` beside it, else None."""
    infos = topics_of(reader, (CAMERA_INFO,))
    if named is not None:
        return pick_topic(reader, path, infos, named, "sensor_msgs/CameraInfo", option)
    base = image.removesuffix("/compressed").rsplit("/", 1)[0]
    return f"{base}/camera_info" if f"{base}/camera_info" in infos else None


def read_bag_camera_sequence(
    path: str | os.PathLike,
    width: int | None = None,
    height: int | None = None,
    *,
    image_topic: str | None = None,
    depth_topic: str | None = None,
    camera_info_topic: str | None = None,
    depth_info_topic: str | None = None,
    odometry_topic: str | None = None,
    odometry_frame: str | None = None,
    odometry: str | os.PathLike | None = None,
    gt_topic: str | None = None,
    gt: str | os.PathLike | None = None,
    label_topic: str | None = None,
    embeddings_dir: str | os.PathLike | None = None,
    embedding_dim: int | None = None,
    classes: ClassEmbeddings | None = None,
    label_map: Mapping[int, int] | None = None,
    patch_shape: tuple[int, int] = (9, 16),
    transform: np.ndarray | None = None,
    step: int = 1,
    max_frames: int | None = None,
    use_depth: bool = True,
    use_rgb: bool = True,
    sync_tolerance: float = 0.02,
) -> CameraRecording:
    """A camera recording in a ROS bag as a query (see the module docstring).

    Args:
        path: a ``.bag``, ``.mcap`` or ``.db3`` file, or a ROS 2 bag folder.
        width: the working width, px (default the images'; given alone, the aspect is kept).
        height: the working height, px (likewise).
        image_topic: the colour topic (default: the only one).
        depth_topic: the depth topic (default: the only one; none: no depth).
        camera_info_topic: the colour intrinsics (default: ``camera_info`` beside the image
            topic, else the only CameraInfo topic).
        depth_info_topic: the depth intrinsics (default: ``camera_info`` beside the depth topic;
            none: the colour ones, for depth of the colour images' size).
        odometry_topic: a ``nav_msgs/Odometry`` (or other pose) topic or ``"/tf"`` (default: the
            only Odometry topic, else ``/tf`` where it moves the camera, else none; ``"none"``:
            none).
        odometry_frame: the fixed frame of the ``/tf`` odometry (default ``odom``, else the
            root of the camera's tree).
        odometry: or a pose file of camera-to-odometry poses (TUM: interpolated to the frames).
        gt_topic: a ``nav_msgs/Odometry`` or ``geometry_msgs/PoseStamped`` ground-truth topic.
        gt: or a pose file of camera-to-world poses.
        label_topic: label images (class ids), made into patch embeddings.
        embeddings_dir: or the folder of ``<stamp_ns>.npy`` patch embeddings (default
            ``embeddings/`` beside a bag file, inside a bag folder).
        embedding_dim: the map's embedding dimension, checked against those files.
        classes: the map's class embeddings (needed with ``label_topic``).
        label_map: raw label id -> class id for the label images.
        patch_shape: (rows, cols) of the patch grid made from label images.
        transform: optional (4, 4) rigid transform applied to the ground truth.
        step: every ``step``-th frame.
        max_frames: at most this many frames.
        use_depth: read the depth images into the query.
        use_rgb: read the colour images into the query.
        sync_tolerance: how far (s) a depth or label image's stamp may be from its frame's.

    Returns:
        A :class:`~jaxloc.io.CameraRecording` of format ``"rosbag"``; frame numbers are the
        colour messages' indices, timestamps their stamps in seconds.

    Raises:
        FileNotFoundError: no such bag, pose file or embedding file.
        ValueError: one line naming the bag and the topic (or option): a damaged bag, no colour
            topic or several without ``image_topic``, an unknown encoding, stamps that do not
            increase, a depth or label image missing at a frame's time, odometry or ground
            truth that does not cover the frames, neither odometry nor ground truth, no patch
            embeddings.
    """
    if step < 1 or (max_frames is not None and max_frames < 1):
        raise ValueError("step and max_frames must be >= 1")
    check_working_size(width, height)
    if min(patch_shape) < 1:
        raise ValueError(f"patch_shape must be >= 1, got {list(patch_shape)}")
    pairs = (
        ("odometry", odometry, "odometry_topic", odometry_topic),
        ("gt", gt, "gt_topic", gt_topic),
        ("embeddings_dir", embeddings_dir, "label_topic", label_topic),
    )
    for file, file_value, topic, topic_value in pairs:
        if file_value is not None and topic_value is not None:
            raise ValueError(f"give {file} or {topic}, not both")
    path = Path(path)
    with contextlib.closing(open_bag(path)) as reader:
        image_topic, depth_topic = _image_topics(reader, path, image_topic, depth_topic,
                                                 label_topic, use_depth)  # fmt: skip
        color = BagTopic(reader, path, image_topic)
        numbers = tuple(range(len(color.stamps)))
        selected = numbers[::step][:max_frames]
        stamps = color.stamps[list(selected)]
        first = color_image(color.first(), color.msgtype, f"{path}: {image_topic} (message 0)")
        native = first.size
        K_color = _color_intrinsics(reader, path, image_topic, camera_info_topic, native)
        depth, depth_of, K_depth, depth_size = None, {}, None, None
        if depth_topic is not None and use_depth:
            depth = BagTopic(reader, path, depth_topic)
            depth_of = depth.matched(stamps, sync_tolerance, selected)
            where = f"{path}: {depth_topic} (message 0)"
            depth_size = depth_image(depth.first(), depth.msgtype, where).shape[::-1]
            named = _info_topic(reader, path, depth_topic, depth_info_topic, "depth_info_topic")
            if named is not None:
                K_depth, _ = camera_intrinsics(first_message(reader, path, named), named)
            elif depth_size != native:
                raise ValueError(
                    f"{path}: {depth_topic} is {depth_size[0]}x{depth_size[1]}, {image_topic} "
                    f"{native[0]}x{native[1]}, and no CameraInfo is beside {depth_topic} (name "
                    "one with depth_info_topic=)"
                )
        camera_frame = str(color.first().header.frame_id).lstrip("/")
        from_bag = NO_ODOMETRY if odometry is not None else odometry_topic  # a file instead
        motion, truth = _bag_poses(
            reader, path, (from_bag, odometry_frame, gt_topic), camera_frame, image_topic, stamps,
            selected,
        )  # fmt: skip
        if odometry is not None:
            motion = _pose_file(odometry, numbers, color.stamps, selected)
        if gt is not None:
            truth = _pose_file(gt, numbers, color.stamps, selected)
        if motion is None and truth is None:
            raise ValueError(
                f"{path}: no poses for the ego-motion: no nav_msgs/Odometry topic, no /tf from "
                f"{image_topic}'s frame {camera_frame!r}, and no ground truth (odometry_topic=, "
                "odometry=, gt_topic= or gt=)"
            )
        embedding_of = _embeddings(
            reader, path, label_topic, embeddings_dir, embedding_dim, classes, label_map,
            patch_shape, color, stamps, selected, sync_tolerance,
        )  # fmt: skip

        def load(number: int, with_depth: bool) -> Frame:
            where = f"{path}: {image_topic} (message {number})"
            image = color_image(color.message(number), color.msgtype, where)
            if image.size != native:
                raise ValueError(f"{where}: size {image.size} differs from message 0's {native}")
            pixels = None
            if with_depth and depth is not None:
                index = depth_of[number]
                where = f"{path}: {depth_topic} (message {index})"
                pixels = depth_image(depth.message(index), depth.msgtype, where)
                if pixels.shape[::-1] != depth_size:
                    raise ValueError(f"{where}: size differs from message 0's")
            pose = None if truth is None else truth[number]
            return Frame(number, color.stamps[number] / 1e9, image, pixels, pose)

        source = FrameSource(
            BAG_FORMAT, path, K_color, native, K_depth, depth_size, numbers, truth is not None,
            load,
        )  # fmt: skip
        odometry_poses = None if motion is None else Odometry(path, motion, None, None, 0)
        return sequence_from_frames(
            source,
            selected,
            working_camera(K_color, native, width, height),
            embedding_of,
            odometry=odometry_poses,
            transform=transform,
            use_depth=use_depth and depth is not None,
            use_rgb=use_rgb,
        )


def _frame_poses(at: Poses, stamps_ns, frames) -> dict[int, np.ndarray]:
    """frame number -> (4, 4) pose; ValueError naming the poses' source and the first frame
    they do not cover."""
    if not at.covered.all():
        k = int(np.flatnonzero(~at.covered)[0])
        raise ValueError(
            f"{at.where} covers {seconds(at.first)} s to {seconds(at.last)} s; frame "
            f"{frames[k]} at {seconds(stamps_ns[k])} s is outside it (or in a gap of over 1 s)"
        )
    return dict(zip(frames, at.poses, strict=True))


def _bag_poses(reader, path: Path, topics, camera_frame, image_topic, stamps, frames) -> tuple:
    """(ego-motion, ground truth): frame number -> (4, 4) camera pose, or None, from the bag's
    odometry (``odometry_topic``, ``odometry_frame``) and ground-truth topic (``gt_topic``)."""
    odometry_topic, odometry_frame, gt_topic = topics
    odometry = pick_odometry(reader, path, odometry_topic)
    truth = gt_topic and pick_topic(reader, path, topics_of(reader, POSE_TYPES), gt_topic,
                                    "pose", "gt_topic")  # fmt: skip
    if odometry is None and truth is None:
        return None, None
    found = read_bag_poses(reader, path, [odometry, truth])
    what = f"{image_topic}'s images"
    motion = None
    if odometry is not None:
        required = odometry_topic is not None or odometry_frame is not None
        at = sensor_poses(found, odometry, camera_frame, stamps, what, odometry_frame, required)
        motion = None if at is None else _frame_poses(at, stamps, frames)
    if truth is not None:
        truth = _frame_poses(sensor_poses(found, truth, camera_frame, stamps, what), stamps, frames)
    return motion, truth


def _pose_file(path: str | os.PathLike, numbers, stamps_ns: np.ndarray, frames) -> dict:
    """frame number -> (4, 4) pose from a pose file: TUM lines interpolated to the frames'
    stamps (no gap too long), or KITTI / 4x4 lines, one per colour message (``numbers``) in
    order."""
    poses = read_pose_file(path)
    if poses.timestamps is None:
        if len(poses.poses) != len(numbers):
            raise ValueError(
                f"{path}: {len(poses.poses)} {poses.format} poses for the bag's {len(numbers)} "
                "colour messages (one per message, in order)"
            )
        return {n: poses.poses[n] for n in frames}
    series = pose_series(None, None, poses.timestamps, poses.poses, str(path))
    at = stamps_ns[list(frames)]
    tolerance = poses.match_tolerance_ns()
    found = interpolate(series, at, tolerance_ns=tolerance, max_gap_ns=None)
    return _frame_poses(Poses(*found, *series.stamps[[0, -1]], str(path)), at, frames)


def _image_topics(reader, path: Path, image_topic, depth_topic, label_topic, use_depth) -> tuple:
    """(colour topic, depth topic or None): named, else the only one of each kind (an image
    topic is depth when its first message is ``16UC1`` / ``32FC1`` or compressed depth; no
    depth topic is picked without ``use_depth``)."""
    images = topics_of(reader, (IMAGE, COMPRESSED))
    encodings = {t: image_encoding(reader, path, t) for t in images}
    depth_like = {t for t in images if encodings[t] in (*DEPTH_ENCODINGS, "compressedDepth")}
    colors = sorted(
        {t for t in images if t not in {depth_topic, label_topic} | depth_like}
        | ({image_topic} & set(images))
    )
    image_topic = pick_topic(reader, path, colors, image_topic, "colour image", "image_topic")
    if image_topic is None:
        raise no_topic(reader, path, "sensor_msgs/Image or CompressedImage colour")
    depths = sorted(({*depth_like, depth_topic} & set(images)) - {image_topic, label_topic})
    if use_depth:
        depth_topic = pick_topic(reader, path, depths, depth_topic, "depth image", "depth_topic")
    if label_topic is not None:
        others = [t for t in images if t != image_topic]
        pick_topic(reader, path, others, label_topic, "image", "label_topic")
    return image_topic, depth_topic


def _color_intrinsics(reader, path: Path, image_topic: str, named, size) -> np.ndarray:
    """(4, 4) intrinsics of the colour images of ``size`` (W, H) from their CameraInfo."""
    info = _info_topic(reader, path, image_topic, named, "camera_info_topic")
    infos = topics_of(reader, (CAMERA_INFO,))
    if info is None and named is None and len(infos) == 1:
        info = infos[0]
    if info is None:
        raise ValueError(
            f"{path}: no sensor_msgs/CameraInfo topic beside {image_topic} (CameraInfo topics: "
            f"{', '.join(infos) or 'none'}; name one with camera_info_topic=)"
        )
    K, info_size = camera_intrinsics(first_message(reader, path, info), f"{path}: {info}")
    if info_size not in (size, (0, 0)):
        raise ValueError(
            f"{path}: {info} is for {info_size[0]}x{info_size[1]} images, {image_topic} has "
            f"{size[0]}x{size[1]}"
        )
    return K


def _embeddings(
    reader, path: Path, label_topic, embeddings_dir, dim, classes, label_map, patch_shape,
    color: BagTopic, stamps, selected, tolerance,
) -> Callable[[int], np.ndarray]:  # fmt: skip
    """``embedding_of(number)``: from the label topic, else from ``<stamp_ns>.npy`` files."""
    if label_topic is not None:
        check_label_classes(classes)
        labels = BagTopic(reader, path, label_topic)
        label_of = labels.matched(stamps, tolerance, selected)

        def embedding_of(number: int) -> np.ndarray:
            index = label_of[number]
            where = f"{path}: {label_topic} (message {index})"
            image = label_image(labels.message(index), labels.msgtype, where)
            return patch_embeddings_from_labels(image, *patch_shape, classes, label_map)[0]

        return embedding_of
    folder = Path(embeddings_dir) if embeddings_dir is not None else None
    if folder is None:
        folder = (path if path.is_dir() else path.parent) / "embeddings"
        if not folder.is_dir():
            raise ValueError(
                f"{path}: no patch embeddings: name a label-image topic (label_topic=) or a "
                f"folder of <stamp_ns>.npy files (embeddings_dir=; default {folder})"
            )
    if not folder.is_dir():
        raise FileNotFoundError(2, "No such folder (the patch embeddings)", str(folder))
    return embedding_files(folder, dim, lambda number: f"{color.stamps[number]}.npy")
