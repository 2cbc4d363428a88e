"""M2Loc metrics: success rate P, RTE/RRE over successes, clique sizes, times (numpy)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from jaxloc.metrics import position_error, rotation_error_deg

#: TripletLoc/M2Loc success threshold on the translation error: RTE < 7.5 m.
SUCCESS_RTE_M = 7.5
#: TripletLoc/M2Loc success threshold on the rotation error: RRE < 10 degrees.
SUCCESS_RRE_DEG = 10.0


def localization_errors(T_est: np.ndarray, T_gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """RTE (m) and RRE (deg, geodesic) between 4x4 poses (..., 4, 4)."""
    T_est, T_gt = np.asarray(T_est, np.float64), np.asarray(T_gt, np.float64)
    return (
        position_error(T_est[..., :3, 3], T_gt[..., :3, 3]),
        rotation_error_deg(T_est[..., :3, :3], T_gt[..., :3, :3]),
    )


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
    success = valid & (rte < SUCCESS_RTE_M) & (rre < SUCCESS_RRE_DEG)

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
