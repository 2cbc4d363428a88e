"""A query :class:`~jaxloc.sg2loc.FrameSequence` from a camera recording on disk (with the
side files named as files: :func:`jaxloc.io.open_camera_recording`).

Three layouts, detected (or named with ``format=``):

* ``"scannet-export"``: a ScanNet export folder (:mod:`jaxloc.io.scannet_export`);
* ``"sens"``: a ScanNet ``.sens`` file, read frame by frame (:mod:`jaxloc.io.scannet_sens`);
* ``"3rscan"``: a 3RScan scan folder or its ``sequence/`` (:mod:`jaxloc.io.rscan_sequence`).

Patch embeddings, per frame number N: ``embeddings/N.npy`` ((rows, cols, d) arrays; the folder
``embeddings_dir``, by default ``embeddings/`` in the sequence folder, or beside a ``.sens``) take
precedence; without that folder, label images ``labels_dir/N.png`` become embeddings in the map's
class space (:mod:`jaxloc.io.label_images`).

The ego-motion and the tilt (pitch, roll) come from an odometry file when given (lines
``N m00 m01 ... m33``: frame number and a 4x4 camera-to-odometry pose, gravity-aligned, z up; or
TUM lines matched by time, or KITTI 3x4 / 4x4 lines, one per frame (:func:`read_odometry`); by
default ``odometry.txt`` in the sequence folder), else from the recording's poses, which are also
the ground truth (multiplied by ``transform`` first: 3RScan's rescan-to-reference transform puts a
rescan in its reference scan's frame). A camera-to-world matrix ``T`` maps to our pose by
``R_world_body = R_world_cam R_body_cam^T = R_z(yaw) R_y(pitch) R_x(roll)`` (see
:mod:`jaxloc.geometry`). Images are resized to the working size with the intrinsics scaled so that
pixel centres stay at integers: ``f' = s f``, ``c' = s (c + 0.5) - 0.5``. Depth is sampled
(nearest pixel) through its own intrinsics onto the working colour pixels, the depth and colour
cameras sharing their centre and axes (as the exporters of both datasets assume).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np
from PIL import Image

from jaxloc._lazy import renamed_names
from jaxloc.camera import Camera
from jaxloc.geometry import consecutive_ego_motions
from jaxloc.io._npy import read_numeric_npy
from jaxloc.io._text import data_lines, parse_finite_floats
from jaxloc.io.camera_frames import (
    FrameSource,
    check_rigid,
    sample_depth,
    scale_intrinsics,
    yaw_pose_and_tilt,
)
from jaxloc.io.label_images import patch_embeddings_from_labels, read_label_image
from jaxloc.io.poses import match_timestamps, read_pose_file
from jaxloc.io.rscan_sequence import open_rscan_sequence, sequence_folder
from jaxloc.io.scannet_export import is_scannet_export, open_scannet_export
from jaxloc.io.scannet_sens import open_sens
from jaxloc.io.scene_map import ClassEmbeddings
from jaxloc.sg2loc import FrameSequence

#: The camera recording layouts read (and detected): the ``format=`` of the camera openers.
CAMERA_FORMATS = ("scannet-export", "sens", "3rscan")


class CameraRecording(NamedTuple):
    """A camera recording loaded as a query.

    Attributes:
        sequence: the query, on the working camera.
        format: the layout read (one of :data:`CAMERA_FORMATS`, or ``"rosbag"``: a ROS bag,
            :mod:`jaxloc.io.rosbag_camera`).
        frame_ids: the T frame numbers, in order.
        timestamps: (T,) float64 seconds (``.sens``), or None.
        poses_gt: (T, 4) float64 ground truth (x, y, z, yaw), or None.
        tilt_gt: (T, 2) float64 ground-truth (pitch, roll), or None.
        skipped: frame numbers dropped because their pose is invalid (all -inf).
        camera_native: the colour camera at the images' own size.
    """

    sequence: FrameSequence
    format: str
    frame_ids: tuple[int, ...]
    timestamps: np.ndarray | None
    poses_gt: np.ndarray | None
    tilt_gt: np.ndarray | None
    skipped: tuple[int, ...]
    camera_native: Camera


def detect_camera_format(path: str | os.PathLike) -> str:
    """The layout of ``path`` (see :data:`CAMERA_FORMATS`).

    Raises:
        FileNotFoundError: nothing at ``path``.
        ValueError: a file or folder of none of the layouts.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(2, "No such file or folder", str(path))
    if path.is_file():
        if path.suffix.lower() == ".sens":
            return "sens"
        raise ValueError(f"{path}: a file, but not a ScanNet .sens file")
    if is_scannet_export(path):
        return "scannet-export"
    if sequence_folder(path) is not None:
        return "3rscan"
    raise ValueError(
        f"{path}: not a camera recording (a ScanNet export folder with color/ and intrinsic/, a "
        ".sens file, or a 3RScan scan with sequence/_info.txt)"
    )


def open_frame_source(path: str | os.PathLike, format: str | None = None) -> FrameSource:
    """The frame stream of ``path`` in its layout (detected unless ``format`` names one); the
    query itself: :func:`read_camera_sequence`, or :func:`jaxloc.io.open_camera_recording`."""
    if format is None:
        format = detect_camera_format(path)
    openers = {
        "scannet-export": open_scannet_export,
        "sens": open_sens,
        "3rscan": open_rscan_sequence,
    }
    if format not in openers:
        raise ValueError(f"format must be one of {CAMERA_FORMATS}, got {format!r}")
    return openers[format](path)


def _recording_folder(source: FrameSource) -> Path:
    """The folder the recording's side files (embeddings/, odometry.txt) sit in."""
    if source.format == "sens":
        return source.path.parent
    if source.format == "3rscan" and source.path.name == "sequence":
        return source.path.parent
    return source.path


class Odometry(NamedTuple):
    """Camera-to-odometry poses of a recording's frames, looked up by frame.

    Attributes:
        path: the file read.
        by_number: frame number -> (4, 4) pose (frame-numbered lines, or KITTI / 4x4 lines, line
            i for the recording's i-th frame); None for a TUM file.
        stamps_ns: (M,) int64 nanoseconds of a TUM file's lines, else None.
        poses: (M, 4, 4) the TUM file's poses, else None.
        tolerance_ns: how far a frame's time may be from a line's.
    """

    path: Path
    by_number: dict[int, np.ndarray] | None
    stamps_ns: np.ndarray | None
    poses: np.ndarray | None
    tolerance_ns: int

    def pose(self, number: int, timestamp: float | None) -> np.ndarray:
        """The pose of frame ``number`` (TUM lines: at its timestamp in seconds, or at its number
        for formats without timestamps, as ``--poses-out`` writes them). Raises ValueError when
        the file has none."""
        if self.by_number is not None:
            if number not in self.by_number:
                raise ValueError(f"{self.path}: no pose for frame {number}")
            return self.by_number[number]
        when = number if timestamp is None else timestamp
        stamp = np.asarray([round(when * 1e9)], np.int64)
        index = int(match_timestamps(stamp, self.stamps_ns, self.tolerance_ns)[0])
        if index < 0:
            raise ValueError(f"{self.path}: no pose at the time of frame {number} ({when} s)")
        return self.poses[index]


def read_odometry(path: str | os.PathLike, numbers: tuple[int, ...]) -> Odometry:
    """The odometry file of a recording whose frames are ``numbers``: lines ``N m00 ... m33``
    (frame number and a 4x4 camera-to-odometry pose, gravity-aligned, z up), or any pose file
    :func:`jaxloc.io.poses.read_pose_file` reads (TUM lines matched by time; KITTI 3x4 or 4x4
    lines, one per frame of the recording, in order).

    Raises:
        ValueError: naming file and line: another field count, a non-number, NaN/inf, a pose
            that is not rigid, a frame number on two lines (``1`` and ``01``), a TUM stamp on
            two lines; KITTI / 4x4 lines of another count than the frames.
    """
    path = Path(path)
    first = next(iter(data_lines(path, comments=True)), (0, ""))[1].split()
    if len(first) == 17:
        out: dict[int, np.ndarray] = {}
        line_of: dict[int, int] = {}
        for line_number, line in data_lines(path, comments=True):
            fields, where = line.split(), f"{path}:{line_number}"
            if len(fields) != 17 or not (fields[0].isascii() and fields[0].isdigit()):
                raise ValueError(
                    f"{where}: expected 'N m00 m01 ... m33' (frame number, 16 numbers)"
                )
            number = int(fields[0])
            if number in out:
                raise ValueError(
                    f"{where}: frame {number} appears more than once (line {line_of[number]} "
                    "has its pose too): two poses for one frame"
                )
            matrix = np.asarray(parse_finite_floats(fields[1:], where, "pose")).reshape(4, 4)
            out[number], line_of[number] = check_rigid(matrix, where), line_number
        return Odometry(path, out, None, None, 0)
    poses = read_pose_file(path)
    if poses.timestamps is not None:
        return Odometry(path, None, poses.timestamps, poses.poses, poses.match_tolerance_ns())
    if len(poses.poses) != len(numbers):
        raise ValueError(
            f"{path}: {len(poses.poses)} {poses.format} poses for the recording's "
            f"{len(numbers)} frames (one per frame, in order)"
        )
    return Odometry(path, dict(zip(numbers, poses.poses, strict=True)), None, None, 0)


def _read_embedding(path: Path, dim: int | None, shape) -> np.ndarray:
    array = read_numeric_npy(path, 3, "(rows, cols, d)", "the frame's patch embeddings")
    if dim is not None and array.shape[-1] != dim:
        raise ValueError(f"{path}: embeddings have {array.shape[-1]} dims, the map's have {dim}")
    if shape is not None and array.shape != shape:
        raise ValueError(f"{path}: shape {array.shape} differs from the first frame's {shape}")
    return array


def embedding_files(
    folder: Path, dim: int | None, name_of: Callable[[int], str] = lambda n: f"{n}.npy"
) -> Callable[[int], np.ndarray]:
    """``embedding_of(number)``: the (rows, cols, d) patch embeddings of a frame from the file
    ``folder / name_of(number)``, each checked to have ``dim`` dims and the first one's shape."""
    first: list[tuple[int, ...]] = []

    def embedding_of(number: int) -> np.ndarray:
        array = _read_embedding(folder / name_of(number), dim, first[0] if first else None)
        first[:] = first or [array.shape]
        return array

    return embedding_of


def _label_files(folder: Path) -> dict[int, Path]:
    if not folder.is_dir():
        raise FileNotFoundError(2, "No such folder (the label images)", str(folder))
    return {int(p.stem): p for p in folder.iterdir() if p.suffix == ".png" and p.stem.isdigit()}


def check_label_classes(classes: ClassEmbeddings | None) -> None:
    """ValueError unless the map's class embeddings are given (label images need them)."""
    if classes is None:
        raise ValueError(
            "label images need the map's class embeddings (maps built by build-scene-graph "
            "store them; a map with per-object embeddings has none)"
        )


def check_working_size(width: int | None, height: int | None) -> None:
    """ValueError naming ``width`` or ``height`` unless each is None or an integer >= 1."""
    for name, size in (("width", width), ("height", height)):
        if size is not None and (not isinstance(size, int | np.integer) or size < 1):
            raise ValueError(f"{name} must be an integer >= 1 (pixels), got {size!r}")


def working_camera(
    K_color: np.ndarray, native: tuple[int, int], width: int | None, height: int | None
) -> Camera:
    """The camera of images of size ``native = (W0, H0)`` with intrinsics ``K_color`` (4, 4)
    resized to ``width x height`` px (default the native size; one of the two alone keeps the
    aspect): :func:`~jaxloc.io.camera_frames.scale_intrinsics`. ValueError for a size below 1."""
    check_working_size(width, height)
    if width is None and height is None:
        width, height = native
    elif height is None:
        height = max(1, round(width * native[1] / native[0]))
    elif width is None:
        width = max(1, round(height * native[0] / native[1]))
    return scale_intrinsics(K_color, native, (width, height))


def read_camera_sequence(
    path: str | os.PathLike,
    format: str | None = None,
    width: int | None = None,
    height: int | None = None,
    *,
    embedding_dim: int | None = None,
    embeddings_dir: str | os.PathLike | None = None,
    labels_dir: str | os.PathLike | None = None,
    classes: ClassEmbeddings | None = None,
    label_map: Mapping[int, int] | None = None,
    patch_shape: tuple[int, int] = (9, 16),
    transform: np.ndarray | None = None,
    odometry: str | os.PathLike | None = None,
    step: int = 1,
    max_frames: int | None = None,
    use_depth: bool = True,
    use_rgb: bool = True,
) -> CameraRecording:
    """Load a camera recording (see the module docstring) on a ``width x height`` camera.

    Args:
        path: an export folder, a ``.sens`` file or a 3RScan scan folder.
        format: one of :data:`CAMERA_FORMATS` (default: detected).
        width: the working width (default the images' own; one of width and height alone keeps
            the aspect).
        height: the working height.
        embedding_dim: the map's embedding dimension, checked against every embedding file.
        embeddings_dir: the per-frame ``N.npy`` patch embeddings (default ``embeddings/``).
        labels_dir: per-frame label images ``N.png``, used when there is no embeddings folder.
        classes: the map's class embeddings (needed with ``labels_dir``).
        label_map: raw label id -> class id for the label images (e.g. ScanNet ids -> NYU40).
        patch_shape: (rows, cols) of the patch grid of embeddings made from label images.
        transform: optional (4, 4) rigid transform applied to the recording's poses (3RScan's
            rescan-to-reference transform).
        odometry: a file of camera-to-odometry poses (:func:`read_odometry`; default
            ``odometry.txt`` beside the frames, when present).
        step: keep every ``step``-th frame.
        max_frames: keep at most this many frames.
        use_depth: read the depth images into the sequence.
        use_rgb: read the colour images into the sequence.

    Raises:
        FileNotFoundError: a missing file or folder (the frame's pose, embedding, label image...).
        ValueError: naming the file: malformed or non-rigid poses, unreadable images,
            embeddings of another dimension or shape, labels without class embeddings; a
            ``width`` or ``height`` below 1, ``step`` or ``max_frames`` below 1.
    """
    if step < 1 or (max_frames is not None and max_frames < 1):
        raise ValueError("step and max_frames must be >= 1")
    check_working_size(width, height)
    if transform is not None:
        transform = check_rigid(np.asarray(transform, np.float64).reshape(4, 4), "transform")
    source = open_frame_source(path, format)
    folder = _recording_folder(source)
    camera = working_camera(source.K_color, source.color_size, width, height)
    odometry_path = Path(odometry) if odometry is not None else folder / "odometry.txt"
    odometry_poses = None
    if odometry_path.is_file():
        odometry_poses = read_odometry(odometry_path, source.numbers)
    if odometry is not None and odometry_poses is None:
        raise FileNotFoundError(2, "No such file (the odometry)", str(odometry_path))
    if not source.has_poses and odometry_poses is None:
        raise FileNotFoundError(2, "No poses: need pose/ or an odometry file", str(source.path))
    emb_dir = Path(embeddings_dir) if embeddings_dir is not None else folder / "embeddings"
    if emb_dir.is_dir():
        embedding_of = embedding_files(emb_dir, embedding_dim)
    elif embeddings_dir is not None:
        raise FileNotFoundError(2, "No such folder (the patch embeddings)", str(emb_dir))
    elif labels_dir is None:
        raise FileNotFoundError(
            2, "No patch embeddings: need embeddings/ or label images", str(emb_dir)
        )
    else:
        check_label_classes(classes)
        labels = _label_files(Path(labels_dir))

        def embedding_of(number: int) -> np.ndarray:
            if number not in labels:
                raise FileNotFoundError(
                    2, "No label image", str(Path(labels_dir) / f"{number}.png")
                )
            image = read_label_image(labels[number])
            return patch_embeddings_from_labels(image, *patch_shape, classes, label_map)[0]

    return sequence_from_frames(
        source,
        source.numbers[::step][:max_frames],
        camera,
        embedding_of,
        odometry=odometry_poses,
        transform=transform,
        use_depth=use_depth,
        use_rgb=use_rgb,
    )


def sequence_from_frames(
    source: FrameSource,
    numbers: Sequence[int],
    camera: Camera,
    embedding_of: Callable[[int], np.ndarray],
    *,
    odometry: Odometry | None = None,
    transform: np.ndarray | None = None,
    use_depth: bool = True,
    use_rgb: bool = True,
) -> CameraRecording:
    """The query of the frames ``numbers`` of ``source``, read one at a time, on ``camera`` (the
    working camera, :func:`working_camera`): each frame's colour resized to it, its depth sampled
    onto its pixels, its patch embeddings ``embedding_of(number)`` ((rows, cols, d)); the
    ego-motion and tilt from ``odometry`` where given, else from the frames' poses, which are the
    ground truth (``transform`` (4, 4) applied first); frames without a pose are skipped where
    the source has poses. Raises ValueError naming the source when no frame has a valid pose."""
    if transform is not None:
        transform = check_rigid(np.asarray(transform, np.float64).reshape(4, 4), "transform")
    K_depth = source.K_color if source.K_depth is None else source.K_depth
    with_depth = use_depth and source.depth_size is not None
    kept, stamps, gt, motion_poses, skipped = [], [], [], [], []
    embeddings, depths, rgbs = [], [], []
    for number in numbers:
        frame = source.load(number, with_depth)
        pose = frame.T_world_cam
        if source.has_poses:
            if pose is None:
                skipped.append(number)
                continue
            pose = pose if transform is None else transform @ pose
            gt.append(pose)
        if odometry is not None:
            by_time = odometry.by_number is None and frame.timestamp is not None
            if by_time and stamps and frame.timestamp <= stamps[-1]:
                raise ValueError(
                    f"{source.path} (frame {number}): timestamp {frame.timestamp} s is not after "
                    f"frame {kept[-1]}'s ({stamps[-1]} s); frames are matched to the odometry "
                    f"{odometry.path} by time, so their times must increase"
                )
            pose = odometry.pose(number, frame.timestamp)
        motion_poses.append(pose)
        kept.append(number)
        stamps.append(frame.timestamp)
        embeddings.append(embedding_of(number))
        if use_rgb:
            size = (camera.width, camera.height)
            resized = frame.color.convert("RGB").resize(size, Image.Resampling.BILINEAR)
            rgbs.append(np.asarray(resized, np.float64) / 255.0)
        if frame.depth is not None:
            depths.append(sample_depth(frame.depth, K_depth, camera))
    if not kept:
        raise ValueError(f"{source.path}: every selected frame has an invalid pose")
    pose_tilt = [yaw_pose_and_tilt(T) for T in motion_poses]
    poses = np.stack([p for p, _ in pose_tilt])
    tilt = np.stack([t for _, t in pose_tilt])
    motion = np.zeros((0, 4))
    if len(kept) > 1:
        motion = np.asarray(consecutive_ego_motions(poses), np.float64)
    sequence = FrameSequence(
        camera,
        np.stack(embeddings),
        motion,
        depth=np.stack(depths) if depths else None,
        rgb=np.stack(rgbs) if rgbs else None,
        tilt=tilt,
    )
    poses_gt = tilt_gt = None
    if gt:
        gt_pose_tilt = [yaw_pose_and_tilt(T) for T in gt]
        poses_gt = np.stack([p for p, _ in gt_pose_tilt])
        tilt_gt = np.stack([t for _, t in gt_pose_tilt])
    timestamps = None if any(s is None for s in stamps) else np.asarray(stamps, np.float64)
    native = source.color_size
    return CameraRecording(
        sequence,
        source.format,
        tuple(kept),
        timestamps,
        poses_gt,
        tilt_gt,
        tuple(skipped),
        scale_intrinsics(source.K_color, native, native),
    )


#: Names of jaxloc 0.2, kept with a DeprecationWarning for one more release.
__getattr__ = renamed_names(
    __name__,
    {
        "load_camera_sequence": "read_camera_sequence",
    },
)
