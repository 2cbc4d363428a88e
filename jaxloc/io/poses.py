"""Pose files: every trajectory jaxloc reads or writes, in the formats tools use.

Three text formats, told apart per file by the number of fields on a line (blank lines and
``#`` comments are skipped; any whitespace separates fields)::

    KITTI   12 numbers per line: the 3x4 [R | t] of a 4x4 pose, row-major
    4x4     16 numbers per line: the whole 4x4 pose, row-major (last row 0 0 0 1)
    TUM      8 numbers per line: ``t x y z qx qy qz qw`` (t in seconds, unit quaternion in
            x y z w order, as evo's ``read_tum_trajectory_file`` reads it); HeLiPR's
            ``LiDAR_GT/<Sensor>_gt.txt`` has the same columns with ``t`` an integer in
            nanoseconds (see :func:`read_pose_file` for how the unit is told)

Each pose maps points of the moving frame (a scan, a camera) into the fixed one (the map, the
world): ``p_map = T @ p_scan``. Timestamps are kept as int64 **nanoseconds**, parsed from the text
exactly (a float64 holds an epoch time in seconds to ~0.24 us only, and HeLiPR's scan files are
named by the exact integer). The stamps of a TUM file must all differ: poses are matched to scans
and frames by time, and of two poses at one time only one could be used.

The writers (:func:`write_tum`, :func:`write_kitti`) write what evo's readers accept: one
single space between fields, no trailing space, no comment, each number as Python's shortest
round-trip repr (full float64 precision), atomically (a temporary file, then a rename).
"""

from __future__ import annotations

import os
import re
from collections.abc import Sequence
from decimal import ROUND_HALF_EVEN, Decimal, InvalidOperation, localcontext
from typing import NamedTuple

import numpy as np

from jaxloc.io._atomic import write_text_atomic
from jaxloc.io._rigid import rigid_mask
from jaxloc.io._text import data_lines, parse_finite_floats

#: Field counts of the three formats.
FIELDS = {12: "kitti", 16: "4x4", 8: "tum"}
#: Largest deviation of a TUM quaternion's norm from 1 that is accepted (then it is normalised).
QUATERNION_TOLERANCE = 1e-3
#: An all-integer timestamp column whose largest value reaches this is in nanoseconds: 1e15 s
#: is 32 million years, 1e15 ns is 11.6 days (HeLiPR's stamps are ~1.69e18 ns).
NANOSECOND_THRESHOLD = 10**15
#: Stamps written in seconds match a scan within 1 ms: far above the float64 rounding of an epoch
#: time (~0.24 us) and the 6 decimals many tools write, far below a LiDAR's scan period (50-100 ms).
SECONDS_TOLERANCE_NS = 1_000_000
_INTEGER = re.compile(r"[+-]?[0-9]+")
_INT64_MAX = np.iinfo(np.int64).max


class PoseFile(NamedTuple):
    """What :func:`read_pose_file` returns.

    Attributes:
        poses: (N, 4, 4) float64 rigid transforms (moving frame -> fixed frame).
        timestamps: (N,) int64 nanoseconds (TUM / HeLiPR files), or None (KITTI, 4x4).
        format: "kitti", "4x4" or "tum".
        time_unit: the unit the timestamps were written in, "s" or "ns" (None without them).
    """

    poses: np.ndarray
    timestamps: np.ndarray | None
    format: str
    time_unit: str | None = None

    def match_tolerance_ns(self) -> int:
        """How far a scan's stamp may be from a line's to match it: 0 for stamps written in
        integer nanoseconds (exact), :data:`SECONDS_TOLERANCE_NS` for stamps in seconds."""
        return 0 if self.time_unit == "ns" else SECONDS_TOLERANCE_NS


def check_rigid(poses: np.ndarray, path: str | os.PathLike) -> None:
    """Raise ``ValueError`` naming ``path`` and the 1-based pose unless every (4, 4) pose is
    rigid (:func:`jaxloc.io._rigid.rigid_mask`)."""
    bad = np.flatnonzero(~rigid_mask(poses))
    if bad.size:
        raise ValueError(f"{path}: pose {bad[0] + 1} is not rigid (a rotation and a translation)")


def seconds_to_ns(text: str, where: str) -> int:
    """A decimal number of seconds (``"1691936557.946849179"``, ``"1.5e-3"``) as int nanoseconds,
    exactly (rounded half to even below 1 ns), whatever the number of digits: the text is parsed
    exactly, shifted by nine decimal places with a precision that holds all its digits, and
    rounded once, to an integer. Raises ``ValueError`` naming ``where``."""
    try:
        value = Decimal(text)
    except InvalidOperation:
        raise ValueError(f"{where}: timestamp {text[:40]!r} is not a number") from None
    if not value.is_finite():
        raise ValueError(f"{where}: timestamp is NaN or inf")
    if abs(value) > Decimal(_INT64_MAX).scaleb(-9):
        raise ValueError(f"{where}: timestamp {text[:40]!r} s is out of range")
    # scaleb keeps the digits and moves the exponent; the default 28-digit context would round
    # the digits first (1691936557.94684917949999999999999 s to ...180 ns instead of ...179)
    with localcontext() as exact:
        exact.prec = max(exact.prec, len(value.as_tuple().digits))
        nanoseconds = value.scaleb(9)
    return int(nanoseconds.to_integral_value(rounding=ROUND_HALF_EVEN))


def check_distinct_stamps(
    stamps_ns: np.ndarray,
    tokens: Sequence[str],
    line_numbers: Sequence[int],
    path: str | os.PathLike,
) -> None:
    """Raise ``ValueError`` naming ``path`` and both lines unless every stamp differs: two poses at
    one time make matching by time keep one and drop the other.

    Args:
        stamps_ns: (N,) int64 nanoseconds, one per line.
        tokens: the stamps as written (for the message).
        line_numbers: the 1-based line of each stamp.
        path: the file.
    """
    first_line: dict[int, int] = {}
    for stamp, token, line_number in zip(stamps_ns.tolist(), tokens, line_numbers, strict=True):
        if stamp in first_line:
            raise ValueError(
                f"{path}:{line_number}: stamp {token[:40]} appears more than once (line "
                f"{first_line[stamp]} has the same time): two poses at one time"
            )
        first_line[stamp] = line_number


def _stamps_ns(tokens: list[str], wheres: list[str], time_unit: str) -> tuple[np.ndarray, str]:
    integers = all(_INTEGER.fullmatch(token) for token in tokens)
    if time_unit == "auto":
        large = integers and max(abs(int(token)) for token in tokens) >= NANOSECOND_THRESHOLD
        time_unit = "ns" if large else "s"
    if time_unit == "ns":
        for token, where in zip(tokens, wheres, strict=True):
            if not _INTEGER.fullmatch(token):
                raise ValueError(f"{where}: timestamp {token[:40]!r} is not an integer (ns)")
            if abs(int(token)) > _INT64_MAX:
                raise ValueError(f"{where}: timestamp {token[:40]!r} ns is out of range")
        return np.array([int(token) for token in tokens], np.int64), "ns"
    stamps = [seconds_to_ns(token, where) for token, where in zip(tokens, wheres, strict=True)]
    return np.array(stamps, np.int64), "s"


def _tum_pose(values: list[float], where: str) -> np.ndarray:
    quaternion = np.asarray(values[3:7])
    norm = float(np.linalg.norm(quaternion))
    if abs(norm - 1.0) > QUATERNION_TOLERANCE:
        raise ValueError(f"{where}: quaternion (qx qy qz qw) has norm {norm:.6g}, not 1")
    from scipy.spatial.transform import Rotation  # here: scipy.spatial costs ~0.3 s to import

    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_quat(quaternion / norm).as_matrix()  # scalar-last: x y z w
    pose[:3, 3] = values[:3]
    return pose


def read_pose_file(path: str | os.PathLike, time_unit: str = "auto") -> PoseFile:
    """Read a KITTI (12 numbers a line), 4x4 (16) or TUM (8) pose file (module docstring).

    Args:
        path: the text file.
        time_unit: of a TUM file's first column: "s" (seconds, TUM), "ns" (integer nanoseconds,
            HeLiPR) or "auto": nanoseconds when every stamp is an integer literal and the
            largest is at least :data:`NANOSECOND_THRESHOLD`, else seconds.

    Returns:
        A :class:`PoseFile`: (N, 4, 4) float64 poses, (N,) int64 nanosecond timestamps or None,
        and the format found.

    Raises:
        FileNotFoundError: no such file.
        ValueError: naming ``file:line``: a field count other than 8, 12 or 16, a line whose
            count differs from the first line's, a non-number, NaN/inf, a TUM quaternion whose
            norm is not 1 (within :data:`QUATERNION_TOLERANCE`), a TUM stamp that repeats an
            earlier line's (:func:`check_distinct_stamps`: two poses at one time); naming the
            file: not UTF-8 text, no pose at all, a pose that is not rigid.
    """
    if time_unit not in ("auto", "s", "ns"):
        raise ValueError(f"time_unit must be 'auto', 's' or 'ns', got {time_unit!r}")
    count, rows, stamps, wheres, line_numbers = None, [], [], [], []
    for line_number, line in data_lines(path, comments=True):
        fields = line.split()
        where = f"{path}:{line_number}"
        if count is None:
            if len(fields) not in FIELDS:
                raise ValueError(
                    f"{where}: expected 12 (KITTI 3x4), 16 (4x4) or 8 (TUM: t x y z qx qy qz "
                    f"qw) numbers, got {len(fields)}"
                )
            count = len(fields)
        elif len(fields) != count:
            raise ValueError(
                f"{where}: {len(fields)} numbers where the file's first pose line has {count}"
                f" ({FIELDS[count]})"
            )
        if count == 8:
            values = parse_finite_floats(fields[1:], where, "pose")
            rows.append(_tum_pose(values, where))
            stamps.append(fields[0])
            wheres.append(where)
            line_numbers.append(line_number)
        else:
            pose = np.eye(4)
            pose.flat[:count] = parse_finite_floats(fields, where, "pose")
            rows.append(pose)
    if count is None:
        raise ValueError(f"{path}: no pose (an empty file)")
    poses = np.asarray(rows, np.float64).reshape(-1, 4, 4)
    check_rigid(poses, path)
    if count != 8:
        return PoseFile(poses, None, FIELDS[count])
    timestamps, unit = _stamps_ns(stamps, wheres, time_unit)
    check_distinct_stamps(timestamps, stamps, line_numbers, path)
    return PoseFile(poses, timestamps, "tum", unit)


def read_poses(path: str | os.PathLike) -> np.ndarray:
    """The (N, 4, 4) float64 poses of a KITTI, 4x4 or TUM file (:func:`read_pose_file` without
    the timestamps). Raises like :func:`read_pose_file`."""
    return read_pose_file(path).poses


def match_timestamps(
    wanted_ns: np.ndarray, available_ns: np.ndarray, tolerance_ns: int = 0
) -> np.ndarray:
    """For each wanted stamp, the index of the available stamp nearest to it, if within
    ``tolerance_ns`` (0: the same integer), else -1.

    Args:
        wanted_ns: (N,) int64 nanoseconds (e.g. the scans').
        available_ns: (M,) int64 nanoseconds (e.g. a pose file's lines).
        tolerance_ns: the largest accepted difference.

    Returns:
        (N,) int64 indices into ``available_ns``; -1 where no stamp is close enough. Ties go to
        the earlier stamp.
    """
    wanted = np.asarray(wanted_ns, np.int64)
    available = np.asarray(available_ns, np.int64)
    if available.size == 0:
        return np.full(wanted.shape, -1, np.int64)
    order = np.argsort(available, kind="stable")
    ordered = available[order]
    right = np.clip(np.searchsorted(ordered, wanted), 0, len(ordered) - 1)
    left = np.clip(right - 1, 0, len(ordered) - 1)
    # Python-int differences: exact, and no int64 overflow for stamps of opposite signs
    d_left = np.abs(wanted.astype(object) - ordered[left].astype(object))
    d_right = np.abs(wanted.astype(object) - ordered[right].astype(object))
    nearest = np.where(d_left <= d_right, left, right)
    distance = np.minimum(d_left, d_right)
    close = np.asarray(distance <= tolerance_ns, bool)
    return np.where(close, order[nearest], -1).astype(np.int64)


def format_ns_as_seconds(ns: int) -> str:
    """Integer nanoseconds as exact decimal seconds: ``1691936557946849179`` ->
    ``"1691936557.946849179"``, ``-1`` -> ``"-0.000000001"``."""
    ns = int(ns)
    sign, magnitude = ("-" if ns < 0 else ""), abs(ns)
    return f"{sign}{magnitude // 10**9}.{magnitude % 10**9:09d}"


def _check_poses(poses: np.ndarray, path: str | os.PathLike) -> np.ndarray:
    poses = np.asarray(poses, np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise ValueError(f"{path}: poses must have shape (N, 4, 4), got {poses.shape}")
    if not np.all(np.isfinite(poses)):
        raise ValueError(f"{path}: poses contain NaN or inf")
    check_rigid(poses, path)
    return poses


def _number(value: float) -> str:
    return repr(float(value))


def write_tum(
    path: str | os.PathLike, poses: np.ndarray, timestamps: np.ndarray | list | tuple
) -> None:
    """Write a TUM trajectory: one line ``t x y z qx qy qz qw`` per pose (evo's
    ``read_tum_trajectory_file`` reads it).

    Args:
        path: the file to create or replace (atomically).
        poses: (N, 4, 4) rigid transforms.
        timestamps: (N,) integer nanoseconds (written exactly as decimal seconds with nine
            digits) or float seconds (written with full float64 precision).

    The quaternion is written with ``qw >= 0`` (q and -q are the same rotation).

    Raises:
        ValueError: wrong shapes, NaN/inf, a pose that is not rigid, a count mismatch, or two
            poses at one time (a TUM file has one pose per time; :func:`read_pose_file` refuses
            repeats).
    """
    poses = _check_poses(poses, path)
    stamps = np.asarray(timestamps)
    if stamps.shape != (len(poses),):
        raise ValueError(f"{path}: {stamps.shape} timestamps for {len(poses)} poses")
    if np.issubdtype(stamps.dtype, np.integer):
        times = [format_ns_as_seconds(t) for t in stamps.tolist()]
    elif np.issubdtype(stamps.dtype, np.floating) and np.all(np.isfinite(stamps)):
        times = [_number(t) for t in stamps]
    else:
        raise ValueError(f"{path}: timestamps must be integer ns or finite float seconds")
    if len(set(times)) != len(times):  # the reader refuses such a file (check_distinct_stamps)
        repeated = next(t for t in times if times.count(t) > 1)
        raise ValueError(f"{path}: two poses share the timestamp {repeated} s: nothing written")
    from scipy.spatial.transform import Rotation

    quaternions = Rotation.from_matrix(poses[:, :3, :3]).as_quat().reshape(-1, 4)
    quaternions *= np.where(quaternions[:, 3:] < 0, -1.0, 1.0)
    lines = [
        " ".join([t, *map(_number, pose[:3, 3]), *map(_number, q)])
        for t, pose, q in zip(times, poses, quaternions, strict=True)
    ]
    write_text_atomic(path, "".join(line + "\n" for line in lines))


def write_kitti(path: str | os.PathLike, poses: np.ndarray) -> None:
    """Write a KITTI pose file: one line of 12 numbers (the 3x4 [R | t], row-major) per pose
    (evo's ``read_kitti_poses_file`` reads it), atomically.

    Raises:
        ValueError: wrong shapes, NaN/inf or a pose that is not rigid.
    """
    poses = _check_poses(poses, path)
    lines = [" ".join(map(_number, pose[:3].ravel())) for pose in poses]
    write_text_atomic(path, "".join(line + "\n" for line in lines))
