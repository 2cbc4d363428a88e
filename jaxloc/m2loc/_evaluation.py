"""M2Loc metrics: success rate P, RTE/RRE over successes, clique sizes, times (numpy), and the
record of one scan of a drive (and its text)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from jaxloc.m2loc._accumulation import WINDOW_MIN_CLIQUE
from jaxloc.m2loc._drive import STATUS_NAMES, DriveStep
from jaxloc.metrics import pose_errors

#: TripletLoc/M2Loc success threshold on the translation error: RTE < 7.5 m.
SUCCESS_RTE_M = 7.5
#: TripletLoc/M2Loc success threshold on the rotation error: RRE < 10 degrees.
SUCCESS_RRE_DEG = 10.0


def localization_errors(T_est: np.ndarray, T_gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """RTE (m) and RRE (deg, geodesic) between 4x4 poses (..., 4, 4)."""
    return pose_errors(T_est, T_gt)


def localization_success(T_est: np.ndarray, T_gt: np.ndarray, valid) -> np.ndarray:
    """(...,) bool, TripletLoc's and M2Loc's success of each pose (..., 4, 4): valid, RTE <
    :data:`SUCCESS_RTE_M` and RRE < :data:`SUCCESS_RRE_DEG`."""
    rte, rre = localization_errors(T_est, T_gt)
    return np.asarray(valid, bool) & (rte < SUCCESS_RTE_M) & (rre < SUCCESS_RRE_DEG)


def summarize_localization(
    T_est: np.ndarray,
    T_gt: np.ndarray,
    valid: Sequence[bool],
    clique_sizes: Sequence[int],
    descriptor_ms: Sequence[float] = (),
    match_ms: Sequence[float] = (),
) -> dict[str, float]:
    """Table-I row values: P (%), RTE/RRE mean and std over successes, clique size and times
    (mean and std over all queries; NaN where no times are given, as for
    :func:`~jaxloc.m2loc.query`'s untimed results)."""
    rte, rre = localization_errors(T_est, T_gt)
    valid = np.asarray(valid, bool)
    success = localization_success(T_est, T_gt, valid)

    def stats(values):
        values = np.asarray(values, np.float64)
        if values.size == 0:
            return float("nan"), float("nan")
        return float(np.mean(values)), float(np.std(values))

    out = {
        "queries": int(valid.size),
        "P": 100.0 * float(np.mean(success)) if valid.size else float("nan"),
    }
    for name, values in (
        ("RTE", rte[success]),
        ("RRE", rre[success]),
        ("MaxClique", clique_sizes),
        ("DescTime", descriptor_ms),
        ("MatchTime", match_ms),
    ):
        out[f"{name}_mean"], out[f"{name}_std"] = stats(values)
    return out


def step_record(step: DriveStep, T_gt: np.ndarray | None = None, track: bool = False) -> dict:
    """The record of one scan of a drive (a ``DriveStep``) as JSON-ready
    values: its instances (in all and per class), ``valid``, ``ambiguous``, ``clique_size``,
    ``scales_used``, ``T_map_scan`` (rounded to 1e-6), the times (ms, compile s); with ``T_gt``
    its ``rte_m`` and ``rre_deg``; with ``track`` the tracking status (:data:`STATUS_NAMES`);
    for a fused window the scans and instances fused (and, untracked, whether its pose was
    refused for a small clique)."""
    scan, result = step.instances, step.result
    labels = np.asarray(scan.labels)
    record = {
        "instances": int(len(scan.points)),
        "instances_per_class": {str(int(c)): int(np.sum(labels == c)) for c in np.unique(labels)},
        "valid": bool(result.valid),
        "ambiguous": bool(result.ambiguous),
        "clique_size": int(result.clique_size),
        "scales_used": int(result.scales_used),
        "T_map_scan": np.round(result.pose, 6).tolist(),
        "load_ms": round(step.load_ms, 3),
        "descriptor_ms": round(result.descriptor_time_ms, 3),
        "match_ms": round(result.match_time_ms, 3),
        "compile_s": round(step.compile_s, 3),
    }
    if T_gt is not None:
        rte, rre = localization_errors(result.pose, T_gt)
        record["rte_m"], record["rre_deg"] = float(rte), float(rre)
    if track:
        record["track"] = STATUS_NAMES[step.status]
    if step.fused is not None:
        record["fused_scans"] = int(step.fused.members.shape[1])
        record["fused_instances"] = len(step.fused.points)
        if not track:
            record["small_clique"] = step.small_clique
    return record


def format_record(record: dict) -> str:
    """The text of a scan's record (:func:`step_record`, with its ``scan`` name), as
    ``jaxloc localize-lidar`` prints it: the instances, the verdict and why, the pose, the times
    and, with ground truth, the errors."""

    why = ""  # why a pose that passed the clique and verification tests was refused
    if record["ambiguous"]:
        why = " (ambiguous: another place fits as well)"
    elif record.get("small_clique"):
        why = f" (a window's pose needs a clique of {WINDOW_MIN_CLIQUE})"
    classes = ", ".join(f"{n} x {c}" for c, n in record["instances_per_class"].items())
    how = f"clique {record['clique_size']}, scales used {record['scales_used']}"
    timing = (
        f"  time: load {record['load_ms']:.1f} ms, descriptors {record['descriptor_ms']:.1f} ms, "
        f"match + clique + pose {record['match_ms']:.1f} ms"
    )
    if "track" in record:
        how = f"{record['track']}, {record['clique_size']} local associations"
        timing = f"  time: load {record['load_ms']:.1f} ms, step {record['match_ms']:.1f} ms"
    if record["compile_s"]:
        timing += f" (first scan of this size: +{record['compile_s']:.1f} s compile or load)"
    lines = [
        f"{record['scan']}: {record['instances']} instances ({classes or 'none'}); "
        f"{'valid' if record['valid'] else 'NOT valid'}{why}, {how}",
        "  T_map_scan =",
        *("    " + " ".join(f"{v:12.4f}" for v in row) for row in record["T_map_scan"]),
        timing,
    ]
    if "rte_m" in record:
        lines.append(f"  RTE {record['rte_m']:.3f} m, RRE {record['rre_deg']:.3f} deg")
    return "\n".join(lines)
