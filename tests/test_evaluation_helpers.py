"""The library functions that hold the rules the command line used to write out itself, against
those rules as the command line wrote them: the capacity-to-KLD rule, 4x4 pose errors, a
sequence's error summaries, M2Loc's success rule, the record of a drive's scan, and the published
M2Loc settings."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from jaxloc.m2loc import (
    FusedScans,
    LocalizationResult,
    localization_errors,
    m2loc_config,
    summarize_localization,
)
from jaxloc.m2loc._config import PUBLISHED_SETTINGS
from jaxloc.m2loc._drive import DriveStep, ScanInstances
from jaxloc.m2loc._evaluation import (
    SUCCESS_RRE_DEG,
    SUCCESS_RTE_M,
    localization_success,
    step_record,
)
from jaxloc.metrics import (
    pose_errors,
    position_error,
    rotation_error_deg,
    summarize,
    summarize_sequence,
    yaw_pose_errors,
)
from jaxloc.sg2loc import KLDConfig
from jaxloc.sg2loc._resampling import kld_for_capacity


def _equal_kld(a: KLDConfig, b: KLDConfig) -> bool:
    fields = ("epsilon", "z", "bin_sizes", "min_particles", "max_particles")
    same = all(np.array_equal(getattr(a, f), getattr(b, f)) for f in fields)
    return same and a.method == b.method


@pytest.mark.parametrize("capacity", [1, 32, 300, 500, 1000, 2500, 20000])
def test_kld_for_capacity_is_the_command_lines_rule(capacity):
    old = KLDConfig(min_particles=min(500, capacity), max_particles=capacity)
    assert _equal_kld(kld_for_capacity(capacity), old)
    bench = KLDConfig(min_particles=min(300, capacity), max_particles=capacity)
    assert _equal_kld(kld_for_capacity(capacity, KLDConfig(min_particles=300)), bench)
    kept = kld_for_capacity(capacity, KLDConfig(epsilon=0.05, method="systematic"))
    assert float(kept.epsilon) == pytest.approx(0.05) and kept.method == "systematic"


def _random_poses(rng, count: int) -> np.ndarray:
    """(count, 4, 4) random rigid poses."""
    q, _ = np.linalg.qr(rng.normal(size=(count, 3, 3)))
    q *= np.sign(np.linalg.det(q))[:, None, None]
    T = np.tile(np.eye(4), (count, 1, 1))
    T[:, :3, :3], T[:, :3, 3] = q, rng.normal(scale=5.0, size=(count, 3))
    return T


def test_pose_errors_are_the_position_and_geodesic_rotation_errors():
    rng = np.random.default_rng(0)
    est, gt = _random_poses(rng, 6), _random_poses(rng, 6)
    position, rotation = pose_errors(est, gt)
    np.testing.assert_array_equal(position, position_error(est[:, :3, 3], gt[:, :3, 3]))
    np.testing.assert_array_equal(rotation, rotation_error_deg(est[:, :3, :3], gt[:, :3, :3]))
    for a, b in zip(localization_errors(est, gt), (position, rotation), strict=True):
        np.testing.assert_array_equal(a, b)
    one = pose_errors(est[0], gt[0])
    assert np.shape(one[0]) == () and float(one[0]) == pytest.approx(position[0])


def test_summarize_sequence_is_the_per_frame_errors_and_the_two_summaries():
    rng = np.random.default_rng(1)
    est, gt = rng.normal(size=(5, 4)), rng.normal(size=(5, 4))
    pos_err, rot_err = yaw_pose_errors(est, gt)
    assert summarize_sequence(est, gt) == {
        "position_error_m": pos_err.tolist(),
        "rotation_error_deg": rot_err.tolist(),
        "all_frames": summarize(pos_err, rot_err),
        "last_frame": summarize(pos_err[-1:], rot_err[-1:]),
    }


def test_localization_success_is_valid_and_within_both_thresholds():
    rng = np.random.default_rng(2)
    gt = _random_poses(rng, 40)
    est = gt.copy()
    est[:, :3, 3] += rng.uniform(0.0, 2 * SUCCESS_RTE_M, (40, 1)) * [1.0, 0.0, 0.0]
    est[::3] = _random_poses(rng, len(est[::3]))  # some far off in rotation too
    valid = rng.uniform(size=40) < 0.8
    success = localization_success(est, gt, valid)
    rte, rre = localization_errors(est, gt)
    rows = zip(valid, rte, rre, strict=True)
    expected = [bool(v and t < SUCCESS_RTE_M and r < SUCCESS_RRE_DEG) for v, t, r in rows]
    assert success.tolist() == expected and 0 < success.sum() < 40
    row = summarize_localization(est, gt, valid, np.full(40, 5))
    assert row["P"] == pytest.approx(100.0 * np.mean(expected))


@pytest.mark.parametrize("fused", [False, True])
@pytest.mark.parametrize("track", [False, True])
def test_step_record_is_the_command_lines_record(fused, track):
    rng = np.random.default_rng(3)
    pose, truth = _random_poses(rng, 2)
    result = LocalizationResult(
        pose=pose, valid=True, clique_size=np.int32(7), inliers=np.zeros((0, 2), np.int64),
        scales_used=2, clique_exact=True, num_associations=40, inlier_fraction=0.8,
        descriptor_time_ms=1.23456, match_time_ms=7.891011, ambiguous=np.bool_(False),
    )  # fmt: skip
    instances = ScanInstances(
        rng.normal(size=(9, 3)), np.array([15, 17, 15, 18, 15, 17, 15, 15, 18])
    )
    window = FusedScans(rng.normal(size=(12, 3)), np.full(12, 15), np.ones(12), np.zeros((12, 3)))
    step = DriveStep(result, 1, instances, window if fused else None, True, 0.4567, 2.34567)
    expected = {
        "instances": 9,
        "instances_per_class": {"15": 5, "17": 2, "18": 2},
        "valid": True,
        "ambiguous": False,
        "clique_size": 7,
        "scales_used": 2,
        "T_map_scan": np.round(pose, 6).tolist(),
        "load_ms": 0.457,
        "descriptor_ms": 1.235,
        "match_ms": 7.891,
        "compile_s": 2.346,
    }
    if track:
        expected["track"] = "relocalized"  # status 1
    if fused:
        expected.update(fused_scans=3, fused_instances=12)
        if not track:
            expected["small_clique"] = True
    assert step_record(step, None, track) == expected
    rte, rre = localization_errors(pose, truth)
    with_truth = step_record(step, truth, track)
    assert with_truth == {**expected, "rte_m": float(rte), "rre_deg": float(rre)}
    assert rte > 0 and rre > 0


def test_published_settings_make_a_saved_robust_config_the_papers():
    """``--no-robust`` on a map saved with the robust defaults: replacing the published settings
    (the uniqueness check included, which needs hypotheses) gives ``robust=False``'s config."""
    robust, published = m2loc_config(3), m2loc_config(3, robust=False)
    assert robust.ambiguity_margin is not None
    assert dataclasses.replace(robust, **PUBLISHED_SETTINGS) == published
    assert m2loc_config(3, **PUBLISHED_SETTINGS) == published
