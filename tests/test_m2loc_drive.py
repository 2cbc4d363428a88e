"""``jaxloc.m2loc.localize_drive``: a drive in one call, against the building blocks it is made of
(``localize_scan``, ``localize_window``, ``Tracker``) on simulated drives, its settings and errors,
and against the command line on a drive simulated on a real HeLiPR map (skipped without
``../shared/data``). The command line against the library on a sequence folder, for single scans
and for accumulation with tracking: tests/test_cli_lidar_maps.py."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from _drive_records import assert_same, cli_json

from jaxloc.io import open_lidar_recording, open_triplet_map, read_instance_map, read_road_normals
from jaxloc.m2loc import (
    DriveConfig,
    Tracker,
    build_map,
    localize_drive,
    localize_scan,
    localize_window,
    m2loc_config,
    pad_scan,
)
from jaxloc.m2loc._accumulation import WINDOW_MIN_CLIQUE
from jaxloc.m2loc._drive import STATUS_NAMES, ScanInstances, ScanSource
from jaxloc.m2loc._localization import query_capacity
from jaxloc.m2loc._tracking import LOST, RELOCALIZED, track_step
from jaxloc.synthetic.outdoor import make_drive, make_outdoor_world

REAL_MAPS = Path(__file__).resolve().parents[2] / "shared" / "data" / "helipr_instance_maps"


@pytest.fixture(scope="module")
def world_and_map():
    world = make_outdoor_world("dense", seed=3, blocks=2, bridge_length=150.0)
    config = m2loc_config(num_scales=1, hypotheses=0)
    return world, build_map(world.points, world.labels, config, world.road_normals)


@pytest.fixture(scope="module")
def drive(world_and_map):
    """Eight scans of at most 12 map vertices each (10-15 instances with the spurious ones), with
    their true poses as odometry."""
    world, _ = world_and_map
    rng = np.random.default_rng(11)
    scans = make_drive(world.points, world.labels, world.road_normals, rng, 8, max_kept=12)
    return scans, np.stack([s.T_map_scan for s in scans])


def test_single_scans_are_localize_scan(world_and_map, drive):
    _, triplet_map = world_and_map
    scans, _ = drive
    seen = []
    result = localize_drive(triplet_map, scans, progress=lambda i, step: seen.append(i))
    assert seen == list(range(len(scans)))
    for scan, step, pose, valid in zip(
        scans, result.steps, result.poses, result.valid, strict=True
    ):
        alone = localize_scan(triplet_map, None, scan.points, scan.labels)
        np.testing.assert_array_equal(pose, alone.pose)
        assert valid == alone.valid and step.result.clique_size == alone.clique_size
        assert step.fused is None and not step.small_clique
        np.testing.assert_array_equal(step.instances.points, scan.points)
    np.testing.assert_array_equal(result.status, np.where(result.valid, RELOCALIZED, LOST))
    np.testing.assert_array_equal(result.fused_scans, 1)
    assert 4 <= result.valid.sum() < len(scans), result.valid  # small scans: not all of them
    assert result.compile_s.shape == result.load_ms.shape == result.localize_ms.shape == (8,)


def test_accumulation_is_localize_window_of_the_last_scans(world_and_map, drive):
    """Scan i's query is the window of its last 3 scans grown up to 6 (localize_window of the
    newest-first scans through the odometry); the first scan is localized alone."""
    _, triplet_map = world_and_map
    scans, odometry = drive
    result = localize_drive(triplet_map, scans, odometry=odometry, accumulate=3)
    assert result.fused_scans[0] == 1 and result.steps[0].fused is None
    for i in range(1, len(scans)):
        window = range(i, max(i - 6, -1), -1)
        relative = np.stack([np.linalg.inv(odometry[i]) @ odometry[j] for j in window])
        expected, fused = localize_window(
            triplet_map,
            [scans[j].points for j in window],
            [scans[j].labels for j in window],
            relative,
            least_scans=3,
        )
        np.testing.assert_array_equal(result.poses[i], expected.pose)
        assert result.valid[i] == expected.valid
        assert result.fused_scans[i] == fused.members.shape[1] >= min(3, i + 1)
        np.testing.assert_array_equal(result.steps[i].fused.points, fused.points)
        raw = localize_scan(triplet_map, None, fused.points, fused.labels)
        small = bool(raw.valid) and raw.clique_size < WINDOW_MIN_CLIQUE
        assert result.steps[i].small_clique == small
    assert result.valid.all(), result.valid  # 30-40 fused instances: every window localizes
    grown = DriveConfig(most_scans=4, min_instances=1000)  # always too few: grow to the bound
    fused = localize_drive(triplet_map, scans, odometry=odometry, accumulate=3, config=grown)
    np.testing.assert_array_equal(fused.fused_scans, [1, 2, 3, 4, 4, 4, 4, 4])


def test_tracking_is_the_tracker_stepped_over_the_queries(world_and_map, drive):
    _, triplet_map = world_and_map
    scans, odometry = drive
    result = localize_drive(triplet_map, scans, odometry=odometry, track=True)
    tracker = Tracker(triplet_map)
    state = tracker.init()
    for i, scan in enumerate(scans):
        band = query_capacity(len(scan.points), triplet_map.config)
        padded = pad_scan(scan.points, scan.labels, triplet_map.config, band)
        previous = np.linalg.inv(odometry[i - 1]) @ odometry[i] if i else np.eye(4)
        state, out = track_step(tracker, state, padded, previous)
        np.testing.assert_array_equal(result.poses[i], np.asarray(out.T_map_scan, np.float64))
        assert result.valid[i] == bool(out.valid) and result.status[i] == int(out.mode)
    names = [STATUS_NAMES[s] for s in result.status]
    assert names[0] == "pending" and "relocalized" in names and names[-4:] == ["tracked"] * 4
    both = localize_drive(triplet_map, scans, odometry=odometry, accumulate=3, track=True)
    names = [STATUS_NAMES[s] for s in both.status]
    assert names[:2] == ["pending", "relocalized"] and names[2:] == ["tracked"] * 6
    np.testing.assert_array_equal(both.fused_scans, [1, 2, 3, 3, 3, 3, 3, 3])


class _Recorded:
    """A ScanSource of the drive's scans with poses for some of them."""

    def __init__(self, scans, poses, has_pose):
        self.scans, self.poses, self.has_pose = scans, poses, np.asarray(has_pose)

    def __len__(self):
        return len(self.scans)

    def instances(self, index, classes):
        scan = self.scans[index]
        return (
            ScanInstances(scan.points, scan.labels)
            if hasattr(scan, "points")
            else ScanInstances(*scan)
        )

    def name(self, index):
        return f"drive/{index}.txt"


def test_settings_and_errors(world_and_map, drive):
    _, triplet_map = world_and_map
    scans, odometry = drive
    source = _Recorded(scans, odometry, np.ones(8, bool))
    assert isinstance(source, ScanSource) and not isinstance(list(scans), ScanSource)
    own = localize_drive(triplet_map, source, accumulate=2)  # odometry: the source's poses
    given = localize_drive(triplet_map, scans, odometry=odometry, accumulate=2)
    np.testing.assert_array_equal(own.poses, given.poses)
    partial = _Recorded(scans, odometry, [True] * 5 + [False] * 3)
    for bad, kwargs, message in (
        (scans, {"accumulate": 2}, "the scans' own poses miss 8 of 8"),
        (partial, {"track": True}, r"miss 3 of 8 \(first: drive/5\.txt\): pass odometry="),
        (scans, {"track": True, "odometry": odometry[:3]}, r"odometry must be \(8, 4, 4\)"),
        (scans, {"accumulate": 0}, "accumulate must be >= 1"),
        (scans, {"accumulate": 3, "config": DriveConfig(most_scans=2)}, "most_scans must be >="),
    ):
        with pytest.raises(ValueError, match=message):
            localize_drive(triplet_map, bad, **kwargs)
    with pytest.raises(ValueError, match="min_instances >= 0"):
        DriveConfig(min_instances=-1)
    twice = list(scans)
    twice[2] = (np.concatenate([scans[2].points] * 2), np.concatenate([scans[2].labels] * 2))
    with pytest.raises(ValueError, match="^scan 2: "):  # the pipeline's refusal, naming the scan
        localize_drive(triplet_map, twice)
    with pytest.raises(ValueError, match="^drive/2.txt: "):
        localize_drive(triplet_map, _Recorded(twice, None, np.zeros(8, bool)))


# ----------------------------------------------------------------------------- the command line


@pytest.mark.slow
@pytest.mark.skipif(not REAL_MAPS.exists(), reason="needs ../shared/data/helipr_instance_maps")
def test_a_simulated_drive_on_a_real_map_through_files(tmp_path):
    """A drive of KAIST04 (as experiments/m2loc_drives.py makes them: noisy odometry) written as
    centroid files, a ground-truth file and an odometry file: ``open_lidar_recording`` +
    ``localize_drive(accumulate=3)`` gives what ``localize-lidar --accumulate 3`` gives."""
    folder = REAL_MAPS / "KAIST04"
    instances, normals = read_instance_map(folder), read_road_normals(folder)
    rng = np.random.default_rng(7000)
    scans = make_drive(instances.points, instances.labels, normals, rng, 6, max_kept=11)
    paths = []
    for i, scan in enumerate(scans):
        paths.append(tmp_path / f"{i:02d}.txt")
        np.savetxt(paths[-1], np.column_stack([scan.labels, scan.points]), fmt="%d %.6f %.6f %.6f")
    truth = np.stack([s.T_map_scan for s in scans])
    noise = np.eye(4)
    noise[:3, 3] = [0.05, -0.04, 0.01]
    chain = [truth[0]]
    for a, b in zip(truth, truth[1:], strict=False):
        chain.append(chain[-1] @ np.linalg.inv(a) @ b @ noise)
    gt, odometry = tmp_path / "gt.txt", tmp_path / "odometry.txt"
    np.savetxt(gt, truth[:, :3].reshape(-1, 12), fmt="%.17g")
    np.savetxt(odometry, np.stack(chain)[:, :3].reshape(-1, 12), fmt="%.17g")
    saved = tmp_path / "kaist04.npz"
    from jaxloc.io import save_triplet_map

    save_triplet_map(open_triplet_map(folder), saved)
    records = cli_json(["localize-lidar", saved, *paths, "--gt", gt, "--odometry", odometry,
                        "--accumulate", "3", "--json", "--no-progress"])  # fmt: skip
    recording = open_lidar_recording(paths, gt=gt)
    result = localize_drive(open_triplet_map(saved), recording.with_poses(odometry), accumulate=3)
    assert_same(records, result, track=False)
    assert result.valid[2:].all(), records
