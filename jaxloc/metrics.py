"""Localization errors and recalls (numpy; used on results, outside jit).

Rotation errors are geodesic on SO(3): ``arccos((trace(R_gt^T R_est) - 1) / 2)``, in degrees.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

#: The recall thresholds SG2Loc reports: (metres, degrees).
SG2LOC_RECALL_THRESHOLDS: tuple[tuple[float, float], ...] = ((0.25, 2.0), (0.10, 5.0), (0.25, 10.0))


def rotation_error_deg(R_est: np.ndarray, R_gt: np.ndarray) -> np.ndarray:
    """Geodesic angle (degrees) between rotation matrices (..., 3, 3)."""
    R_est, R_gt = np.asarray(R_est, np.float64), np.asarray(R_gt, np.float64)
    trace = np.einsum("...ji,...ji->...", R_gt, R_est)
    return np.rad2deg(np.arccos(np.clip((trace - 1.0) / 2.0, -1.0, 1.0)))


def position_error(p_est: np.ndarray, p_gt: np.ndarray) -> np.ndarray:
    """Euclidean distance (metres) between positions (..., 3)."""
    return np.linalg.norm(np.asarray(p_est, np.float64) - np.asarray(p_gt, np.float64), axis=-1)


def pose_errors(T_est: np.ndarray, T_gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Position (m) and geodesic rotation (deg) errors of 4x4 rigid poses (..., 4, 4)."""
    T_est, T_gt = np.asarray(T_est, np.float64), np.asarray(T_gt, np.float64)
    return (
        position_error(T_est[..., :3, 3], T_gt[..., :3, 3]),
        rotation_error_deg(T_est[..., :3, :3], T_gt[..., :3, :3]),
    )


def yaw_pose_errors(poses_est: np.ndarray, poses_gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Position (m) and geodesic rotation (deg) errors of 4-DoF poses (..., 4) = (x, y, z, yaw).

    Estimate and ground truth share the known tilt, and the geodesic angle of
    ``R_gt^T R_est = C^T R_z(yaw_est - yaw_gt) C`` (C the tilt and camera axes) is invariant to
    that conjugation, so the rotation error is exactly ``|wrap(yaw_est - yaw_gt)|`` for any tilt.
    """
    est, gt = np.asarray(poses_est, np.float64), np.asarray(poses_gt, np.float64)
    dyaw = (est[..., 3] - gt[..., 3] + np.pi) % (2.0 * np.pi) - np.pi
    return position_error(est[..., :3], gt[..., :3]), np.rad2deg(np.abs(dyaw))


def summarize_sequence(poses_est: np.ndarray, poses_gt: np.ndarray) -> dict:
    """Per-frame errors of 4-DoF poses (T, 4) (:func:`yaw_pose_errors`) and the summaries
    (:func:`summarize`) of all frames and of the last, as JSON-ready values: keys
    ``position_error_m``, ``rotation_error_deg`` (lists), ``all_frames``, ``last_frame``."""
    pos_err, rot_err = yaw_pose_errors(poses_est, poses_gt)
    return {
        "position_error_m": pos_err.tolist(),
        "rotation_error_deg": rot_err.tolist(),
        "all_frames": summarize(pos_err, rot_err),
        "last_frame": summarize(pos_err[-1:], rot_err[-1:]),
    }


def recall(
    pos_err: np.ndarray, rot_err_deg: np.ndarray, max_pos: float, max_rot_deg: float
) -> float:
    """Fraction of estimates with position error < max_pos and rotation error < max_rot_deg."""
    pos_err, rot_err_deg = np.asarray(pos_err), np.asarray(rot_err_deg)
    if pos_err.size == 0:
        return float("nan")
    return float(np.mean((pos_err < max_pos) & (rot_err_deg < max_rot_deg)))


def summarize(
    pos_err: np.ndarray,
    rot_err_deg: np.ndarray,
    thresholds: Sequence[tuple[float, float]] = SG2LOC_RECALL_THRESHOLDS,
) -> dict[str, float]:
    """Means, medians and recalls of a set of errors, as a flat dict for tables."""
    pos_err, rot_err_deg = np.asarray(pos_err, np.float64), np.asarray(rot_err_deg, np.float64)
    out = {
        "mean_pos_m": float(np.mean(pos_err)),
        "median_pos_m": float(np.median(pos_err)),
        "mean_rot_deg": float(np.mean(rot_err_deg)),
        "median_rot_deg": float(np.median(rot_err_deg)),
    }
    for max_pos, max_rot in thresholds:
        out[f"R@{max_pos:g}m,{max_rot:g}deg"] = recall(pos_err, rot_err_deg, max_pos, max_rot)
    return out
