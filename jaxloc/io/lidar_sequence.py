"""Labelled LiDAR sequences on disk: the SemanticKITTI layout and a plain one.

SemanticKITTI (checked against the dataset's documentation and its API code, PRBonn's
``semantic-kitti-api``, ``generate_sequential.py``: ``parse_calibration`` / ``parse_poses``)::

    SEQ_DIR/velodyne/NNNNNN.bin   float32 x y z intensity per point (sensor frame, metres)
    SEQ_DIR/labels/NNNNNN.label   uint32 per point: semantic id (low 16 bits), instance (high 16)
    SEQ_DIR/poses.txt             one line per scan: 12 numbers, the 3x4 pose P of the left camera
                                  (cam0) in the frame of the first cam0, row-major
    SEQ_DIR/calib.txt             lines "KEY: 12 numbers" (P0..P3, Tr); Tr maps velodyne points to
                                  cam0 points

    T_map_scan = inv(Tr) @ P @ Tr   (the map frame is the velodyne frame of the first scan)

Plain: ``NNN.bin`` with ``NNN.label`` in ``SEQ_DIR`` (or ``velodyne/`` + ``labels/``) and a
``poses.txt`` of ``T_map_scan`` rows (12 numbers: 3x4, or 16: 4x4, row-major) and no
``calib.txt``. Scans are ordered by their file names, numerically when the names are numbers
(``0, 11, 102``); line i of ``poses.txt`` is the pose of the i-th scan.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import NamedTuple

import numpy as np

from jaxloc.io._rigid import rigid_mask
from jaxloc.io._text import data_lines, parse_finite_floats


class LidarSequence(NamedTuple):
    """A labelled LiDAR sequence found on disk (nothing is read but the poses and calibration).

    Attributes:
        root: the sequence folder.
        bins: per scan the ``.bin`` path; labels: the matching ``.label`` paths.
        T_map_scan: (N, 4, 4) float64 scan-to-map poses, or None when the folder has no poses.
        layout: "semantickitti" (``calib.txt`` present, camera poses converted) or "plain".
    """

    root: Path
    bins: tuple[Path, ...]
    labels: tuple[Path, ...]
    T_map_scan: np.ndarray | None
    layout: str


def scan_order_key(path: Path) -> tuple:
    """Sort key of a scan file: numeric stems as numbers (``0 < 11 < 102``), then by name."""
    stem = path.stem
    return (0, int(stem), stem) if stem.isdigit() else (1, 0, stem)


def is_sequence_dir(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a folder with ``velodyne/*.bin`` scans (a SemanticKITTI sequence)."""
    folder = Path(path) / "velodyne"
    return folder.is_dir() and any(folder.glob("*.bin"))


def check_rigid(poses: np.ndarray, path: str | os.PathLike) -> None:
    """Raise ``ValueError`` naming ``path`` and the 1-based row unless every (4, 4) pose is rigid
    (:func:`jaxloc.io._rigid.rigid_mask`)."""
    bad = np.flatnonzero(~rigid_mask(poses))
    if bad.size:
        raise ValueError(f"{path}: pose {bad[0] + 1} is not rigid (a rotation and a translation)")


def read_poses(path: str | os.PathLike) -> np.ndarray:
    """Poses, one per non-blank line: 12 numbers (3x4) or 16 (4x4), row-major.

    Returns:
        (N, 4, 4) float64 rigid transforms.

    Raises:
        ValueError: a line with another field count, a non-number or NaN/inf (file:line), or a
            pose that is not rigid (naming the file and the pose).
    """
    rows = []
    for line_number, line in data_lines(path, comments=True):
        fields = line.split()
        where = f"{path}:{line_number}"
        if len(fields) not in (12, 16):
            raise ValueError(f"{where}: expected 12 or 16 numbers (a pose), got {len(fields)}")
        pose = np.eye(4)
        pose.flat[: len(fields)] = parse_finite_floats(fields, where, "pose")
        rows.append(pose)
    poses = np.asarray(rows, np.float64).reshape(-1, 4, 4)
    check_rigid(poses, path)
    return poses


def read_kitti_calibration(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """A KITTI ``calib.txt``: lines ``KEY: 12 numbers`` as (4, 4) float64 matrices by key.

    Raises:
        ValueError: a line without ``KEY:``, not 12 numbers, or NaN/inf (file:line).
    """
    calibration = {}
    for line_number, line in data_lines(path):
        where = f"{path}:{line_number}"
        key, colon, values = line.partition(":")
        fields = values.split()
        if not colon or not key.strip() or len(fields) != 12:
            raise ValueError(f"{where}: expected 'KEY: 12 numbers', got {line[:60]!r}")
        matrix = np.eye(4)
        matrix[:3] = np.reshape(parse_finite_floats(fields, where, key.strip()), (3, 4))
        calibration[key.strip()] = matrix
    return calibration


def velodyne_to_camera(path: str | os.PathLike) -> np.ndarray:
    """``Tr`` (4, 4) of a KITTI ``calib.txt`` (``Tr`` or ``Tr_velo_to_cam``), checked rigid."""
    calibration = read_kitti_calibration(path)
    for key in ("Tr", "Tr_velo_to_cam"):
        if key in calibration:
            check_rigid(calibration[key][None], f"{path} ({key})")
            return calibration[key]
    raise ValueError(f"{path}: no 'Tr:' line (the velodyne-to-camera transform)")


def _scan_files(root: Path) -> tuple[list[Path], list[Path]]:
    if (root / "velodyne").is_dir():
        bins = sorted((root / "velodyne").glob("*.bin"), key=scan_order_key)
        labels = [root / "labels" / path.with_suffix(".label").name for path in bins]
    else:
        bins = sorted(root.glob("*.bin"), key=scan_order_key)
        labels = [path.with_suffix(".label") for path in bins]
    if not bins:
        raise ValueError(f"{root}: no scans (expected velodyne/*.bin or *.bin)")
    for label in labels:
        if not label.is_file():
            raise FileNotFoundError(f"{label}: missing label file")
    return bins, labels


def load_lidar_sequence(seq_dir: str | os.PathLike, require_poses: bool = True) -> LidarSequence:
    """Find the scans of a sequence folder and read its poses (see the module docstring).

    Args:
        seq_dir: the sequence folder.
        require_poses: raise when ``poses.txt`` is missing (else ``T_map_scan`` is None).

    Raises:
        FileNotFoundError: no such folder, a scan without its label file, no ``poses.txt``.
        ValueError: no scans, a malformed ``poses.txt`` or ``calib.txt``, or a pose count that
            differs from the scan count (each naming the file).
    """
    root = Path(seq_dir)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: no such sequence folder")
    bins, labels = _scan_files(root)
    poses_path, calib_path = root / "poses.txt", root / "calib.txt"
    layout = "semantickitti" if calib_path.is_file() else "plain"
    if not poses_path.is_file():
        if require_poses:
            raise FileNotFoundError(f"{poses_path}: missing poses (one per scan)")
        return LidarSequence(root, tuple(bins), tuple(labels), None, layout)
    poses = read_poses(poses_path)
    if len(poses) != len(bins):
        raise ValueError(f"{poses_path}: {len(poses)} poses for {len(bins)} scans")
    if layout == "semantickitti":
        tr = velodyne_to_camera(calib_path)
        poses = np.linalg.inv(tr) @ poses @ tr
    return LidarSequence(root, tuple(bins), tuple(labels), poses, layout)
