"""The record of a camera localization run as ``jaxloc localize-camera`` reports it: the
refinement of the last frame as JSON-ready values, and the text of a whole report."""

from __future__ import annotations

import numpy as np

from jaxloc.metrics import pose_errors


def refinement_record(scene, sequence, last_pose, T_gt: np.ndarray | None = None) -> dict:
    """:func:`jaxloc.sg2loc.refine.refine` of the last frame of ``sequence`` from ``last_pose``
    (x, y, z m, yaw rad) as ``ok``, ``status`` and ``T_world_cam`` (4 x 4 list); with the
    ground-truth ``T_gt`` (4, 4) also ``position_error_m`` (m) and ``rotation_error_deg`` (deg)."""
    from jaxloc.sg2loc.refine import refine

    refined = refine(scene, sequence, last_pose)
    T = np.asarray(refined.pose.as_matrix(), np.float64)
    out = {"ok": bool(refined.ok), "status": int(refined.status), "T_world_cam": T.tolist()}
    if T_gt is not None:
        out["position_error_m"], out["rotation_error_deg"] = map(float, pose_errors(T, T_gt))
    return out


def run_record(result, folder, map_file, seq_dir, online: bool) -> dict:
    """The JSON-ready record of a :func:`~jaxloc.sg2loc.localize` result (``online``: of
    :func:`~jaxloc.sg2loc.online.filter_sequence`) on the camera recording ``folder``
    (:func:`jaxloc.io.open_camera_recording`): the files, frames, mode, ``poses`` (x, y, z m,
    yaw rad), ``localized`` and ``confidence`` per frame."""
    poses = result.pose if online else result.poses
    verdict = result.verdict if online else result.info.verdict
    return {
        "map": str(map_file),
        "sequence": str(seq_dir),
        "format": folder.format,
        "frames": list(folder.frame_ids),
        "skipped": list(folder.skipped),
        "mode": "online" if online else "offline",
        "poses": np.asarray(poses, np.float64).tolist(),
        "localized": np.asarray(result.localized, bool).tolist(),
        "confidence": np.round(np.asarray(verdict.confidence, np.float64), 4).tolist(),
    }


def format_report(report: dict) -> str:
    """The text of a run's JSON ``report`` (``frames``, ``poses`` (x, y, z m, yaw rad),
    ``localized``; optionally ``confidence``, ``depth_check`` (per frame), the per-frame errors,
    the ``all_frames`` / ``last_frame`` summaries of :func:`jaxloc.metrics.summarize_sequence`,
    ``refined`` (:func:`refinement_record`), ``figure`` and ``rerun``): a line per frame (yaw in
    deg), the summaries, the refinement."""
    lines = []
    for t, number in enumerate(report["frames"]):
        (x, y, z, yaw), verdict = report["poses"][t], report["localized"][t]
        line = f"frame {number}: {'localized' if verdict else 'NOT localized'}"
        if "confidence" in report:
            line += f" (confidence {report['confidence'][t]:.2f})"
        if "depth_check" in report:
            line += f", depth check {'passed' if report['depth_check'][t] else 'failed'}"
        line += f", x {x:.3f} y "
        line += f"{y:.3f} z {z:.3f} m, yaw {np.degrees(yaw):.1f} deg"
        if "position_error_m" in report:
            line += f" | error {report['position_error_m'][t]:.3f} m, "
            line += f"{report['rotation_error_deg'][t]:.2f} deg"
        lines.append(line)
    lines.append(f"localized: {sum(report['localized'])} of {len(report['frames'])} frames")
    if "depth_check" in report:
        lines.append(f"depth check passed: {sum(report['depth_check'])} frames")
    for name in ("all_frames", "last_frame"):
        if name in report:
            values = ", ".join(f"{k} {v:.3f}" for k, v in report[name].items())
            lines.append(f"{name.replace('_', ' ')}: {values}")
    if refined := report.get("refined"):
        line = f"refined last frame: ok {refined['ok']} (status {refined['status']})"
        if "position_error_m" in refined:
            line += f", error {refined['position_error_m']:.3f} m, "
            line += f"{refined['rotation_error_deg']:.2f} deg"
        matrix = np.array2string(np.asarray(refined["T_world_cam"]), precision=4)
        lines.append(f"{line}\nT_world_cam =\n{matrix}")
    lines += [f"{key}: {report[key]}" for key in ("figure", "rerun") if key in report]
    return "\n".join(lines)
