"""A query :class:`~jaxloc.sg2loc.sequence.Sequence` from a folder of RGB-D frames (ScanNet's
export).

Layout (ScanNet's ``SensReader/python/SensorData.py`` export, plus the user's patch embeddings)::

    SEQ_DIR/color/N.jpg                     colour frames (N = 0, 1, ...; sorted as numbers)
    SEQ_DIR/depth/N.png                     optional: uint16 depth in millimetres, 0 = invalid
    SEQ_DIR/pose/N.txt                      optional: 4x4 camera-to-world matrix (text rows);
                                            all -inf marks a frame without a pose (skipped)
    SEQ_DIR/intrinsic/intrinsic_color.txt   4x4 matrix K of the colour camera (text rows)
    SEQ_DIR/intrinsic/intrinsic_depth.txt   K of the depth camera (needed when the depth images
                                            have another size than the colour ones)
    SEQ_DIR/embeddings/N.npy                (rows, cols, d) patch embeddings of frame N
    SEQ_DIR/odometry.txt                    optional: lines "N m00 m01 ... m33", a 4x4
                                            camera-to-odometry pose per frame (gravity-aligned,
                                            z up; any origin and heading)

The ego-motion and the tilt (pitch, roll) come from ``odometry.txt`` when present, else from
``pose/``; ``pose/`` gives the ground truth. A camera-to-world matrix ``T`` maps to our pose by
``R_world_body = R_world_cam R_body_cam^T = R_z(yaw) R_y(pitch) R_x(roll)`` (see
:mod:`jaxloc.geometry`). Images are resized to the working size with the intrinsics scaled so that
pixel centres stay at integers: ``f' = s f``, ``c' = s (c + 0.5) - 0.5``. Depth is sampled
(nearest pixel) through its own intrinsics onto the working colour pixels, assuming the depth and
colour cameras share their centre and axes (ScanNet's exported extrinsics are identities).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import NamedTuple

import jax
import numpy as np
from PIL import Image

from jaxloc.camera import Camera
from jaxloc.geometry import R_BODY_CAM, ego_motion
from jaxloc.io._npy import read_numeric_npy
from jaxloc.io._rigid import rigid_mask
from jaxloc.io._text import data_lines, parse_finite_floats
from jaxloc.sg2loc.sequence import Sequence

#: ScanNet's depth shift: depth png value / 1000 = metres.
DEPTH_SCALE = 1000.0


class CameraFolder(NamedTuple):
    """A loaded sequence folder.

    Attributes:
        sequence: the query, on the working camera.
        frame_ids: the T frame numbers, in order.
        poses_gt: (T, 4) float64 ground truth (x, y, z, yaw) from ``pose/``, or None.
        tilt_gt: (T, 2) float64 ground-truth (pitch, roll) from ``pose/``, or None.
        skipped: frame numbers dropped because their pose is invalid (all -inf).
        camera_native: the colour camera at the images' own size.
    """

    sequence: Sequence
    frame_ids: tuple[int, ...]
    poses_gt: np.ndarray | None
    tilt_gt: np.ndarray | None
    skipped: tuple[int, ...]
    camera_native: Camera


def yaw_pose_and_tilt(T_world_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(x, y, z, yaw)`` (4,) and ``(pitch, roll)`` (2,) of a 4x4 camera-to-world matrix, radians,
    with ``R_world_cam = R_z(yaw) R_y(pitch) R_x(roll) R_body_cam``."""
    r = np.asarray(T_world_cam, np.float64)[:3, :3] @ np.asarray(R_BODY_CAM, np.float64).T
    yaw = np.arctan2(r[1, 0], r[0, 0])
    pitch = np.arcsin(np.clip(-r[2, 0], -1.0, 1.0))
    roll = np.arctan2(r[2, 1], r[2, 2])
    return np.append(np.asarray(T_world_cam, np.float64)[:3, 3], yaw), np.array([pitch, roll])


def read_matrix(path: str | os.PathLike, allow_invalid: bool = False) -> np.ndarray | None:
    """A 4x4 matrix from a text file of four rows of four numbers.

    Returns None for ScanNet's invalid pose (every entry -inf) when ``allow_invalid``.

    Raises:
        ValueError: naming the file: not 4x4, non-numeric, NaN or inf values.
    """
    path = Path(path)
    rows = [line.split() for _, line in data_lines(path)]
    if len(rows) != 4 or any(len(row) != 4 for row in rows):
        raise ValueError(f"{path}: expected a 4x4 matrix (4 lines of 4 numbers)")
    try:
        matrix = np.asarray([[float(v) for v in row] for row in rows], np.float64)
    except ValueError as err:
        raise ValueError(f"{path}: non-numeric value ({err})") from None
    if allow_invalid and np.all(np.isneginf(matrix)):
        return None
    if not np.all(np.isfinite(matrix)):
        raise ValueError(f"{path}: matrix has NaN or inf values")
    return matrix


def check_rigid(matrix: np.ndarray, where: str) -> np.ndarray:
    """``matrix`` if it is a rigid transform (orthonormal rotation, det +1, last row 0 0 0 1)."""
    if not rigid_mask(matrix):
        raise ValueError(f"{where}: not a rigid transform (rotation not orthonormal or last row)")
    return matrix


def scale_intrinsics(K: np.ndarray, native: tuple[int, int], size: tuple[int, int]) -> Camera:
    """The camera of a ``native = (W0, H0)`` image resized to ``size = (W, H)`` (pixel centres at
    integers: ``f' = s f``, ``c' = s (c + 0.5) - 0.5``, per axis)."""
    sx, sy = size[0] / native[0], size[1] / native[1]
    return Camera(
        float(K[0, 0] * sx),
        float(K[1, 1] * sy),
        float((K[0, 2] + 0.5) * sx - 0.5),
        float((K[1, 2] + 0.5) * sy - 0.5),
        int(size[0]),
        int(size[1]),
    )


def sample_depth(depth: np.ndarray, K_depth: np.ndarray, camera: Camera) -> np.ndarray:
    """(H, W) depth on ``camera``'s pixels: each pixel's ray through the depth camera ``K_depth``
    (same centre and axes), nearest depth pixel; 0 outside the depth image."""
    u, v = np.meshgrid(np.arange(camera.width), np.arange(camera.height))
    x, y = (u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy
    ud = np.rint(K_depth[0, 0] * x + K_depth[0, 2]).astype(np.int64)
    vd = np.rint(K_depth[1, 1] * y + K_depth[1, 2]).astype(np.int64)
    inside = (ud >= 0) & (ud < depth.shape[1]) & (vd >= 0) & (vd < depth.shape[0])
    out = np.zeros(u.shape, np.float64)
    out[inside] = depth[vd[inside], ud[inside]]
    return out


def frame_numbers(folder: Path, suffixes: tuple[str, ...]) -> list[tuple[int, Path]]:
    """(number, file) of the files ``N.<suffix>`` of a folder, sorted as numbers."""
    if not folder.is_dir():
        raise FileNotFoundError(2, "No such folder", str(folder))
    found = []
    for path in folder.iterdir():
        if path.suffix.lower() in suffixes:
            if not path.stem.isdigit():
                raise ValueError(f"{path}: frame files must be named by their number")
            found.append((int(path.stem), path))
    if not found:
        raise ValueError(f"{folder}: no frames ({' or '.join(suffixes)} files)")
    return sorted(found)


def _read_image(path: Path) -> Image.Image:
    try:
        image = Image.open(path)
        image.load()
    except FileNotFoundError:
        raise FileNotFoundError(2, "No such file", str(path)) from None
    except OSError as err:
        raise ValueError(f"{path}: not a readable image ({err})") from None
    return image


def _read_depth(path: Path) -> np.ndarray:
    image = _read_image(path)
    array = np.asarray(image)
    if image.mode not in ("I;16", "I;16B", "I;16L", "I") or array.ndim != 2:
        raise ValueError(f"{path}: expected a 16-bit one-channel depth PNG, got mode {image.mode}")
    return array.astype(np.float64) / DEPTH_SCALE


def _read_embedding(path: Path, dim: int | None, shape) -> np.ndarray:
    array = read_numeric_npy(path, 3, "(rows, cols, d)", "the frame's patch embeddings")
    if dim is not None and array.shape[-1] != dim:
        raise ValueError(f"{path}: embeddings have {array.shape[-1]} dims, the map's have {dim}")
    if shape is not None and array.shape != shape:
        raise ValueError(f"{path}: shape {array.shape} differs from the first frame's {shape}")
    if np.any(np.linalg.norm(array, axis=-1) == 0):
        raise ValueError(f"{path}: embeddings contain zero vectors")
    return array


def _read_odometry(path: Path) -> dict[int, np.ndarray]:
    out = {}
    for line_number, line in data_lines(path, comments=True):
        fields, where = line.split(), f"{path}:{line_number}"
        if len(fields) != 17 or not fields[0].isdigit():
            raise ValueError(f"{where}: expected 'N m00 m01 ... m33' (frame number, 16 numbers)")
        matrix = np.asarray(parse_finite_floats(fields[1:], where, "pose")).reshape(4, 4)
        out[int(fields[0])] = check_rigid(matrix, where)
    return out


def load_camera_folder(
    folder: str | os.PathLike,
    width: int | None = None,
    height: int | None = None,
    *,
    embedding_dim: int | None = None,
    step: int = 1,
    max_frames: int | None = None,
    use_depth: bool = True,
    use_rgb: bool = True,
) -> CameraFolder:
    """Load a sequence folder (layout in the module docstring) on a ``width x height`` camera.

    Args:
        folder: the sequence folder.
        width: the working width (default the images' own; one of width and height alone keeps
            the aspect).
        height: the working height.
        embedding_dim: the map's embedding dimension, checked against every embedding file.
        step: keep every ``step``-th frame.
        max_frames: keep at most this many frames.
        use_depth: read ``depth/`` into the sequence.
        use_rgb: read the colour images into the sequence.

    Raises:
        FileNotFoundError: a missing folder or file (the frame's pose, depth, embedding...).
        ValueError: naming the file: a malformed or non-rigid pose, a depth image of another
            size without ``intrinsic_depth.txt``, embeddings of another dimension or shape.
    """
    folder = Path(folder)
    if step < 1 or (max_frames is not None and max_frames < 1):
        raise ValueError("step and max_frames must be >= 1")
    frames = frame_numbers(folder / "color", (".jpg", ".jpeg", ".png"))[::step][:max_frames]
    K = read_matrix(folder / "intrinsic" / "intrinsic_color.txt")
    native = _read_image(frames[0][1]).size
    if width is None and height is None:
        width, height = native
    elif height is None:
        height = max(1, round(width * native[1] / native[0]))
    elif width is None:
        width = max(1, round(height * native[0] / native[1]))
    camera = scale_intrinsics(K, native, (width, height))
    has_poses = (folder / "pose").is_dir()
    odometry_path = folder / "odometry.txt"
    odometry = _read_odometry(odometry_path) if odometry_path.is_file() else None
    if not has_poses and odometry is None:
        raise FileNotFoundError(2, "No poses: need pose/ or odometry.txt", str(folder / "pose"))
    depth_K = None
    depth_K_path = folder / "intrinsic" / "intrinsic_depth.txt"
    if use_depth and (folder / "depth").is_dir() and depth_K_path.is_file():
        depth_K = read_matrix(depth_K_path)
    kept, gt, motion_poses, skipped = [], [], [], []
    embeddings, depths, rgbs = [], [], []
    for number, color_path in frames:
        pose = None
        if has_poses:
            path = folder / "pose" / f"{number}.txt"
            if not path.is_file():
                raise FileNotFoundError(2, "No such file (the frame's pose)", str(path))
            pose = read_matrix(path, allow_invalid=True)
            if pose is None:
                skipped.append(number)
                continue
            gt.append(check_rigid(pose, str(path)))
        if odometry is not None:
            if number not in odometry:
                raise ValueError(f"{odometry_path}: no pose for frame {number}")
            pose = odometry[number]
        motion_poses.append(pose)
        kept.append(number)
        shape = embeddings[0].shape if embeddings else None
        path = folder / "embeddings" / f"{number}.npy"
        embeddings.append(_read_embedding(path, embedding_dim, shape))
        image = _read_image(color_path)
        if image.size != native:
            raise ValueError(f"{color_path}: size {image.size} differs from the first frame's")
        if use_rgb:
            resized = image.convert("RGB").resize((width, height), Image.Resampling.BILINEAR)
            rgbs.append(np.asarray(resized, np.float64) / 255.0)
        if use_depth and (folder / "depth").is_dir():
            path = folder / "depth" / f"{number}.png"
            depth = _read_depth(path)
            if depth_K is None:
                if depth.shape[::-1] != native:
                    raise ValueError(
                        f"{path}: depth is {depth.shape[1]}x{depth.shape[0]}, the colour images "
                        f"{native[0]}x{native[1]}, and there is no {depth_K_path}"
                    )
                depths.append(sample_depth(depth, K, camera))
            else:
                depths.append(sample_depth(depth, depth_K, camera))
    if not kept:
        raise ValueError(f"{folder}: every selected frame has an invalid pose")
    pose_tilt = [yaw_pose_and_tilt(T) for T in motion_poses]
    poses = np.stack([p for p, _ in pose_tilt])
    tilt = np.stack([t for _, t in pose_tilt])
    motion = np.zeros((0, 4))
    if len(kept) > 1:
        motion = np.asarray(jax.vmap(ego_motion)(poses[:-1], poses[1:]), np.float64)
    sequence = Sequence(
        camera,
        np.stack(embeddings),
        motion,
        depth=np.stack(depths) if depths else None,
        rgb=np.stack(rgbs) if rgbs else None,
        tilt=tilt,
    )
    poses_gt = tilt_gt = None
    if has_poses:
        gt_pose_tilt = [yaw_pose_and_tilt(T) for T in gt]
        poses_gt = np.stack([p for p, _ in gt_pose_tilt])
        tilt_gt = np.stack([t for _, t in gt_pose_tilt])
    camera_native = scale_intrinsics(K, native, native)
    return CameraFolder(sequence, tuple(kept), poses_gt, tilt_gt, tuple(skipped), camera_native)
