"""Posed RGB-D frames as every camera format gives them, before they become a query sequence.

A :class:`FrameSource` is what a reader of a camera recording returns (a ScanNet export folder,
:mod:`jaxloc.io.scannet_export`; a ScanNet ``.sens`` file, :mod:`jaxloc.io.scannet_sens`; a 3RScan
sequence, :mod:`jaxloc.io.rscan_sequence`): the colour and depth intrinsics and the frame numbers,
and a loader of one frame at a time, so a long recording is never held in memory.
:func:`jaxloc.io.camera_sequence.read_camera_sequence` turns the frames into a
:class:`~jaxloc.sg2loc.FrameSequence`.

Conventions: ``T_world_cam`` is a 4x4 camera-to-world matrix (OpenCV camera frame, metres), the
convention of all three datasets; intrinsics are 4x4 matrices ``[fx 0 cx 0; 0 fy cy 0; 0 0 1 0;
0 0 0 1]`` with pixel centres at integer coordinates; depth is metres along the optical axis,
0 = invalid.
"""

from __future__ import annotations

import os
import struct
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import numpy as np
from PIL import Image

from jaxloc.camera import Camera
from jaxloc.geometry import R_BODY_CAM
from jaxloc.io._numbering import check_distinct_numbers
from jaxloc.io._rigid import rigid_mask
from jaxloc.io._text import data_lines

#: How two camera frame files of one number are reported (:func:`check_distinct_numbers`).
FRAME_NUMBER_CLASH = "frame files with the same number"

#: What Pillow can raise on a damaged image file (its plugins report some broken headers and
#: streams as SyntaxError, struct.error, zlib.error or IndexError).
IMAGE_ERRORS = (
    OSError,
    ValueError,
    SyntaxError,
    EOFError,
    IndexError,
    struct.error,
    zlib.error,
    Image.DecompressionBombError,
)


class Frame(NamedTuple):
    """One frame of a recording.

    Attributes:
        number: the frame's number in its recording (file number or index in the file).
        timestamp: seconds, or None when the format has no timestamps.
        color: the colour image (8-bit RGB), at the recording's colour size.
        depth: (h, w) float64 metres at the depth size, 0 = invalid; None when not asked for or
            absent.
        T_world_cam: (4, 4) float64 camera-to-world, or None for a frame without a valid pose.
    """

    number: int
    timestamp: float | None
    color: Image.Image
    depth: np.ndarray | None
    T_world_cam: np.ndarray | None


class FrameSource(NamedTuple):
    """A camera recording opened for reading.

    Attributes:
        format: the layout's name ("scannet-export", "sens" or "3rscan").
        path: what was opened.
        K_color: (4, 4) float64 intrinsics of the colour images; color_size: their (W, H).
        K_depth: (4, 4) float64 intrinsics of the depth images (None: the colour ones);
            depth_size: their (W, H), or None without depth.
        numbers: the frame numbers, in recording order.
        has_poses: whether the frames carry camera-to-world poses (the ground truth).
        load: ``load(number, with_depth) -> Frame``.
    """

    format: str
    path: Path
    K_color: np.ndarray
    color_size: tuple[int, int]
    K_depth: np.ndarray | None
    depth_size: tuple[int, int] | None
    numbers: tuple[int, ...]
    has_poses: bool
    load: Callable[[int, bool], Frame]


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
    return checked(matrix, path)


def checked(matrix: np.ndarray, where: str | os.PathLike) -> np.ndarray:
    """``matrix`` if all its entries are finite, else ValueError naming ``where``."""
    if not np.all(np.isfinite(matrix)):
        raise ValueError(f"{where}: matrix has NaN or inf values")
    return matrix


def checked_pose(matrix: np.ndarray, where: str, allow_invalid: bool = True) -> np.ndarray | None:
    """A camera-to-world ``matrix`` checked rigid; None for the datasets' invalid pose (every
    entry -inf) when ``allow_invalid``. Raises ValueError naming ``where`` otherwise."""
    if allow_invalid and np.all(np.isneginf(matrix)):
        return None
    return check_rigid(checked(matrix, where), where)


def check_rigid(matrix: np.ndarray, where: str) -> np.ndarray:
    """``matrix`` if it is a rigid transform (orthonormal rotation, det +1, last row 0 0 0 1)."""
    if not rigid_mask(matrix):
        raise ValueError(f"{where}: not a rigid transform (rotation not orthonormal or last row)")
    return matrix


#: Tolerance on the entries of an intrinsic matrix that the pinhole form fixes (0 or 1).
PINHOLE_TOLERANCE = 1e-6


def check_intrinsics(K: np.ndarray, where: str) -> np.ndarray:
    """``K`` (4, 4) if it has the pinhole form of ScanNet's and 3RScan's files,
    ``[fx 0 cx 0; 0 fy cy 0; 0 0 1 0; 0 0 0 1]``, with finite entries and fx, fy > 0: jaxloc's
    camera has no skew, so a matrix of another form is refused rather than read in part."""
    checked(K, where)
    if K.shape != (4, 4) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(f"{where}: not a pinhole intrinsic matrix (fx, fy must be > 0)")
    form = np.array([[1, 0, 1, 0], [0, 1, 1, 0], [0, 0, 1, 0], [0, 0, 0, 1]], np.float64)
    free = np.zeros((4, 4), bool)
    free[0, 0] = free[1, 1] = free[0, 2] = free[1, 2] = True  # fx, fy, cx, cy
    if np.max(np.abs(np.where(free, 0.0, K - form))) > PINHOLE_TOLERANCE:
        raise ValueError(
            f"{where}: not a pinhole intrinsic matrix [fx 0 cx 0; 0 fy cy 0; 0 0 1 0; 0 0 0 1] "
            f"(a skew or another fixed entry differs: {np.round(K, 6).tolist()})"
        )
    return K


def yaw_pose_and_tilt(T_world_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(x, y, z, yaw)`` (4,) and ``(pitch, roll)`` (2,) of a 4x4 camera-to-world matrix, radians,
    with ``R_world_cam = R_z(yaw) R_y(pitch) R_x(roll) R_body_cam``."""
    r = np.asarray(T_world_cam, np.float64)[:3, :3] @ np.asarray(R_BODY_CAM, np.float64).T
    yaw = np.arctan2(r[1, 0], r[0, 0])
    pitch = np.arcsin(np.clip(-r[2, 0], -1.0, 1.0))
    roll = np.arctan2(r[2, 1], r[2, 2])
    return np.append(np.asarray(T_world_cam, np.float64)[:3, 3], yaw), np.array([pitch, roll])


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


def read_image(path: Path) -> Image.Image:
    """An image file, fully decoded; ValueError naming the file when it is not a readable image."""
    try:
        image = Image.open(path)
        image.load()
    except FileNotFoundError:
        raise FileNotFoundError(2, "No such file", str(path)) from None
    except IMAGE_ERRORS as err:
        raise ValueError(f"{path}: not a readable image ({type(err).__name__}: {err})") from None
    return image


def depth_metres(image: Image.Image, scale: float, where: str) -> np.ndarray:
    """(h, w) float64 metres of a 16-bit one-channel depth image whose values are ``scale`` per
    metre (1000: millimetres). ValueError naming ``where`` for any other image."""
    array = np.asarray(image)
    if image.mode not in ("I;16", "I;16B", "I;16L", "I") or array.ndim != 2:
        raise ValueError(f"{where}: expected a 16-bit one-channel depth image, got {image.mode}")
    if array.min(initial=0) < 0 or array.max(initial=0) > 65535:
        raise ValueError(f"{where}: depth values outside 16 bits")
    return array.astype(np.float64) / scale


def frame_numbers(folder: Path, suffixes: tuple[str, ...]) -> list[tuple[int, Path]]:
    """(number, file) of the files ``N.<suffix>`` of a folder, sorted as numbers.

    Raises:
        FileNotFoundError: no such folder.
        ValueError: a file not named by its number (ASCII digits), two files of one number
            (``1.jpg`` and ``01.jpg``, ``1.jpg`` and ``1.png``: which is the frame would be a
            guess), no such file at all.
    """
    if not folder.is_dir():
        raise FileNotFoundError(2, "No such folder", str(folder))
    found = []
    for path in folder.iterdir():
        if path.suffix.lower() in suffixes:
            if not (path.stem.isascii() and path.stem.isdigit()):
                raise ValueError(f"{path}: frame files must be named by their number")
            found.append((int(path.stem), path))
    if not found:
        raise ValueError(f"{folder}: no frames ({' or '.join(suffixes)} files)")
    found.sort()
    check_distinct_numbers(found, FRAME_NUMBER_CLASH)
    return found
