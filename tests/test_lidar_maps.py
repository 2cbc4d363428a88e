"""Maps from a labelled LiDAR sequence: the SemanticKITTI conventions, the instance and road-normal
maps of a synthetic sequence of a known world, plane fits, the real scan, and bad input."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from jaxloc.io import read_instance_map, read_road_normals, write_instance_maps
from jaxloc.io.lidar_sequence import open_lidar_sequence, read_kitti_calibration
from jaxloc.mapping import MapBuildConfig, build_lidar_maps, fit_plane
from jaxloc.synthetic.lidar_scans import KITTI_TR, make_lidar_sequence, write_semantickitti_sequence
from jaxloc.synthetic.outdoor import _terrain_normal, make_outdoor_world

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
REAL_SCAN = DATA / "semantickitti_scan" / "000000.bin"
EVERY = 3


@pytest.fixture(scope="module")
def world():
    return make_outdoor_world("dense", seed=0, blocks=1, bridge_length=0)


@pytest.fixture(scope="module")
def scans(world):
    """24 scans along the road y = 200 m of a one-block world (a turn-free 180 m drive)."""
    return make_lidar_sequence(world, (10.0, 200.0), (190.0, 200.0), 24, seed=1, max_range=35.0)


@pytest.fixture(scope="module")
def sequence_dir(scans, tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("seq")
    write_semantickitti_sequence(root, scans)
    return root


@pytest.fixture(scope="module")
def built(sequence_dir):
    return build_lidar_maps(open_lidar_sequence(sequence_dir), MapBuildConfig(every=EVERY))


def write_text(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def write_scan(folder: Path, name: str, points: np.ndarray, raw: np.ndarray) -> None:
    (folder / "velodyne").mkdir(parents=True, exist_ok=True)
    (folder / "labels").mkdir(exist_ok=True)
    xyzi = np.column_stack([points, np.zeros(len(points))]).astype("<f4")
    xyzi.tofile(folder / "velodyne" / f"{name}.bin")
    np.asarray(raw, "<u4").tofile(folder / "labels" / f"{name}.label")


# ----------------------------------------------------------------------------- conventions


def test_kitti_camera_pose_and_tr_give_the_scan_to_map_transform(tmp_path):
    """Worked by hand, not with the formula under test: the car drives 10 m forward, then turns
    90 deg left. In cam0 coordinates (x right, y down, z forward) its camera centre is (0, 0, 10)
    and its axes are x -> (0, 0, 1), y -> (0, 1, 0), z -> (-1, 0, 0). The velodyne (x forward,
    y left, z up) sits at (0.1, -0.5, -0.3) in camera coordinates. So in the map frame (the first
    scan's velodyne frame) the second scan is yawed +90 deg, and its origin is the camera centre
    (10 m forward) plus the lever arm turned by 90 deg, minus the first scan's lever arm."""
    camera_rotation = np.array([[0.0, 0, -1], [0, 1, 0], [1, 0, 0]])  # columns: the axes above
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = camera_rotation, [0.0, 0.0, 10.0]
    lever = np.array([0.1, -0.5, -0.3])  # velodyne origin, camera coordinates
    tr = np.eye(4)
    tr[:3, :3] = [[0.0, -1, 0], [0, 0, -1], [1, 0, 0]]  # velodyne -> camera axes
    tr[:3, 3] = lever
    write_text(
        tmp_path / "calib.txt",
        "P0: 7 0 6 0 0 7 1 0 0 0 1 0\nTr: " + " ".join(map(str, tr[:3].ravel())) + "\n",
    )
    rows = [np.eye(4)[:3].ravel(), pose[:3].ravel()]
    write_text(tmp_path / "poses.txt", "\n".join(" ".join(map(str, r)) for r in rows) + "\n")
    for name in ("000000", "000001"):
        write_scan(tmp_path, name, np.zeros((1, 3)), np.zeros(1))
    sequence = open_lidar_sequence(tmp_path)
    assert sequence.layout == "semantickitti"
    np.testing.assert_allclose(sequence.T_map_scan[0], np.eye(4), atol=1e-12)
    yaw_left = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    # camera coordinates -> map (velodyne) coordinates: forward = cam z, left = -cam x, up = -cam y
    to_map = np.array([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]])
    origin_cam0 = np.array([0.0, 0, 10]) + camera_rotation @ lever  # velodyne 1 in cam0 coords
    expected_origin = to_map @ (origin_cam0 - lever)
    np.testing.assert_allclose(sequence.T_map_scan[1][:3, :3], yaw_left, atol=1e-12)
    np.testing.assert_allclose(sequence.T_map_scan[1][:3, 3], expected_origin, atol=1e-12)
    assert expected_origin[0] > 9.0  # ~10 m forward


def test_scans_sort_numerically_and_plain_layout_reads_map_poses(tmp_path):
    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[:, 0, 3] = [0.0, 11.0, 102.0]
    for name in ("0", "11", "102"):
        write_scan(tmp_path, name, np.zeros((1, 3)), np.zeros(1))
    # 4x4 rows, one with a '#' comment
    text = "\n".join(" ".join(map(str, p.ravel())) for p in poses) + "  # last\n"
    write_text(tmp_path / "poses.txt", text)
    sequence = open_lidar_sequence(tmp_path)
    assert sequence.layout == "plain"
    assert [p.stem for p in sequence.bins] == ["0", "11", "102"]
    assert [p.name for p in sequence.labels] == ["0.label", "11.label", "102.label"]
    np.testing.assert_array_equal(sequence.T_map_scan, poses)


def test_calibration_reader_and_its_errors(tmp_path):
    calib = read_kitti_calibration(write_text(tmp_path / "c.txt", "Tr: 1 0 0 1 0 1 0 2 0 0 1 3\n"))
    np.testing.assert_array_equal(calib["Tr"][:3, 3], [1, 2, 3])
    bad = write_text(tmp_path / "bad.txt", "P0: 1 2 3\n")
    with pytest.raises(ValueError, match=r"bad.txt:1: expected 'KEY: 12 numbers'"):
        read_kitti_calibration(bad)


# ----------------------------------------------------------------------------- plane fits


def test_plane_fit_matches_least_squares_and_ignores_outliers():
    rng = np.random.default_rng(0)
    xy = rng.uniform(-5, 5, (400, 2))
    z = 0.05 * xy[:, 0] - 0.02 * xy[:, 1] + 1.0 + rng.normal(0, 0.01, 400)
    points = np.column_stack([xy, z])
    truth = np.array([-0.05, 0.02, 1.0]) / np.linalg.norm([-0.05, 0.02, 1.0])
    # numpy reference: least squares z = a x + b y + c on the clean points
    (a, b, _), *_ = np.linalg.lstsq(np.column_stack([xy, np.ones(400)]), z, rcond=None)
    reference = np.array([-a, -b, 1.0]) / np.linalg.norm([-a, -b, 1.0])
    clean, _ = fit_plane(points)
    assert np.degrees(np.arccos(min(clean @ reference, 1.0))) < 0.05
    polluted = points.copy()
    side = np.argsort(xy[:, 0])[-80:]  # 20 % of the points, on one side: a parked car
    polluted[side, 2] += rng.uniform(0.5, 1.5, 80)
    robust, inliers = fit_plane(polluted)
    assert robust[2] > 0 and np.degrees(np.arccos(min(robust @ truth, 1.0))) < 0.5
    assert inliers[side].sum() == 0 and np.delete(inliers, side).mean() > 0.95
    plain = np.linalg.svd(polluted - polluted.mean(0))[2][-1]
    assert np.degrees(np.arccos(abs(plain @ truth))) > 2.0  # the outliers do tilt a plain fit


# ----------------------------------------------------------------------------- built maps


def test_instance_map_recall_and_precision(world, scans, built):
    truth = world.points[scans.visible]
    found = built.instances.points
    distance, nearest = cKDTree(truth).query(found)
    precision = np.mean(distance < 0.5)
    back, _ = cKDTree(found).query(truth)
    recall = np.mean(back < 0.5)
    assert precision >= 0.9 and recall >= 0.9, (precision, recall)
    matched = nearest[distance < 0.5]
    assert len(set(matched.tolist())) == matched.size  # fused: one instance per object
    labels = built.instances.labels[distance < 0.5]
    assert np.mean(labels == world.labels[scans.visible][matched]) >= 0.99
    np.testing.assert_array_equal(built.scans_used, np.arange(0, 24, EVERY))


def test_road_normal_map_within_two_degrees(built):
    cells = built.road_normals
    assert len(cells.xy) >= 20
    truth = _terrain_normal(cells.xy)
    error = np.degrees(np.arccos(np.clip(np.sum(truth * cells.normals, axis=1), -1, 1)))
    assert error.max() < 2.0, error.max()
    assert np.all(cells.std_deg >= 0) and np.all(cells.std_deg < 2.0)
    spacing, _ = cKDTree(cells.xy).query(cells.xy, 2)
    assert spacing[:, 1].min() >= 3.5  # fused within 3.5 m


def test_written_maps_load_back(built, tmp_path):
    write_instance_maps(tmp_path, built.instances, built.road_normals)
    instances = read_instance_map(tmp_path)
    by_class = np.concatenate([np.flatnonzero(built.instances.labels == c) for c in (15, 17, 18)])
    np.testing.assert_allclose(instances.points, built.instances.points[by_class], atol=1e-4)
    np.testing.assert_array_equal(instances.labels, built.instances.labels[by_class])
    normals = read_road_normals(tmp_path)
    np.testing.assert_allclose(normals.xy, built.road_normals.xy, atol=1e-4)
    np.testing.assert_allclose(normals.normals, built.road_normals.normals, atol=1e-6)


def test_plain_layout_gives_the_same_maps(scans, built, tmp_path):
    """The same scans as a plain folder (.bin/.label side by side, 4x4 T_map_scan poses)."""
    for index, (points, raw) in enumerate(zip(scans.points, scans.raw_labels, strict=True)):
        np.column_stack([points, np.zeros(len(points))]).astype("<f4").tofile(
            tmp_path / f"{index}.bin"
        )
        raw.astype("<u4").tofile(tmp_path / f"{index}.label")
    np.savetxt(tmp_path / "poses.txt", scans.T_map_scan.reshape(-1, 16))
    plain = build_lidar_maps(open_lidar_sequence(tmp_path), MapBuildConfig(every=EVERY))
    np.testing.assert_allclose(plain.instances.points, built.instances.points, atol=1e-5)
    np.testing.assert_allclose(plain.road_normals.normals, built.road_normals.normals, atol=1e-6)


@pytest.mark.skipif(not REAL_SCAN.is_file(), reason="no ../shared/data")
def test_real_semantickitti_scan_is_a_one_scan_sequence(tmp_path):
    for suffix in (".bin", ".label"):
        (tmp_path / f"000000{suffix}").write_bytes(REAL_SCAN.with_suffix(suffix).read_bytes())
    write_text(tmp_path / "poses.txt", " ".join(map(str, np.eye(4)[:3].ravel())) + "\n")
    maps = build_lidar_maps(open_lidar_sequence(tmp_path), MapBuildConfig(every=1))
    assert len(maps.instances.points) >= 10  # trunks, poles and signs of a real street
    assert set(maps.instances.labels.tolist()) <= {15, 17, 18}
    assert len(maps.road_normals.xy) >= 5
    # the sensor is mounted level on the car: the road is flat to within a few degrees
    tilt = np.degrees(np.arccos(maps.road_normals.normals[:, 2]))
    assert np.median(tilt) < 5.0, tilt


def test_sequence_without_graph_points_is_an_error(scans, tmp_path):
    road_only = scans.raw_labels[0] == 40
    write_scan(tmp_path, "000000", scans.points[0][road_only], scans.raw_labels[0][road_only])
    np.savetxt(tmp_path / "poses.txt", np.eye(4)[:3].reshape(1, 12))
    with pytest.raises(ValueError, match="no instance of the classes"):
        build_lidar_maps(open_lidar_sequence(tmp_path), MapBuildConfig(every=1))


def test_kitti_tr_is_the_documented_axes():
    forward = KITTI_TR[:3, :3] @ np.array([1.0, 0, 0])
    np.testing.assert_array_equal(forward, [0, 0, 1])  # velodyne x (forward) -> camera z
