"""``jaxloc.io.open_lidar_recording`` on every recording jaxloc reads (a SemanticKITTI sequence, a
plain folder, a HeLiPR sequence, a list of scan files, centroid files and instance-map folders),
its ground truth by time and by order, its errors on each layout's broken forms, the poses it
writes for evo (``write_lidar_poses``), and ``open_triplet_map`` on a folder and a saved map.

The scans are six synthetic labelled scans of a one-block world (``make_lidar_sequence``), written
in each layout; what a recording reads is checked against the layout readers it is built on
(``open_lidar_sequence``, ``read_sequence_scan``, ``cluster_instances``)."""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import numpy as np
import pytest
from _helipr_fixtures import FIRST_STAMP, PERIOD_NS, ns_to_seconds, tum_line, write_helipr_sequence

from jaxloc.io import (
    open_lidar_recording,
    open_triplet_map,
    read_centroid_scan,
    read_instance_map,
    read_road_normals,
    save_triplet_map,
    write_instance_maps,
    write_lidar_poses,
)
from jaxloc.io.lidar_sequence import open_lidar_sequence, read_sequence_scan
from jaxloc.m2loc import Instances, SmallMapWarning, build_map, cluster_instances, m2loc_config
from jaxloc.synthetic.lidar_scans import make_lidar_sequence, write_semantickitti_sequence
from jaxloc.synthetic.outdoor import make_outdoor_world

STAMPS = [FIRST_STAMP + PERIOD_NS * i for i in range(6)]


@pytest.fixture(scope="module")
def world():
    return make_outdoor_world("dense", seed=4, blocks=1, bridge_length=0)


@pytest.fixture(scope="module")
def scans(world):
    """Six scans of a 100 m drive through the world."""
    return make_lidar_sequence(
        world, (20.0, 0.0), (120.0, 0.0), 6, seed=5, max_range=30.0, road_points=3000,
        clutter_points=300,
    )  # fmt: skip


@pytest.fixture(scope="module")
def layouts(world, scans, tmp_path_factory) -> dict[str, Path]:
    """The scans as a SemanticKITTI sequence, a plain folder (velodyne/ + labels/, poses.txt of
    T_map_scan) and a HeLiPR sequence; the world as an instance-map folder ("map")."""
    root = tmp_path_factory.mktemp("layouts")
    write_semantickitti_sequence(root / "kitti", scans)
    plain = root / "plain"
    shutil.copytree(root / "kitti", plain)
    (plain / "calib.txt").unlink()
    np.savetxt(plain / "poses.txt", scans.T_map_scan[:, :3].reshape(6, 12), fmt="%.17g")
    write_helipr_sequence(root / "helipr" / "KAIST05", scans)
    sizes = np.ones(len(world.points), np.int64)
    write_instance_maps(
        root / "map", Instances(world.points, world.labels, sizes), world.road_normals
    )
    return {
        "semantickitti": root / "kitti",
        "plain": plain,
        "helipr": root / "helipr" / "KAIST05",
        "map": root / "map",
    }


def write_centroids(path: Path, points, labels) -> Path:
    np.savetxt(path, np.column_stack([labels, points]), fmt="%d %.6f %.6f %.6f")
    return path


# ----------------------------------------------------------------------------- layouts


@pytest.mark.parametrize("layout", ["semantickitti", "plain", "helipr"])
def test_a_sequence_folder_is_its_scans_in_order(scans, layouts, layout):
    """Every ``every``-th scan with its number, stamp and pose; points, labels and instances as
    the layout's own reader and TripletLoc's clustering give them."""
    folder = layouts[layout]
    recording = open_lidar_recording(folder, every=2)
    sequence = open_lidar_sequence(folder)
    assert len(recording) == 3 and recording.numbers == (0, 2, 4)
    assert recording.paths == sequence.bins[::2]
    assert [s.layout for s in recording.sequences] == [layout]
    np.testing.assert_array_equal(recording.has_pose, True)
    np.testing.assert_array_equal(recording.poses, sequence.T_map_scan[::2])
    np.testing.assert_allclose(recording.poses, scans.T_map_scan[::2], atol=1e-6)
    if layout == "helipr":
        assert recording.stamps == tuple(STAMPS[::2])
        np.testing.assert_array_equal(recording.timestamps, STAMPS[::2])
    else:
        assert recording.stamps == (None,) * 3 and recording.timestamps is None
    for i, index in enumerate((0, 2, 4)):
        expected = read_sequence_scan(sequence, index)
        np.testing.assert_array_equal(recording.scan(i).points, expected.points)
        np.testing.assert_array_equal(recording.scan(i).labels, expected.labels)
        clustered = cluster_instances(expected.points, expected.labels)
        found = recording.instances(i)
        np.testing.assert_array_equal(found.points, clustered.points)
        np.testing.assert_array_equal(found.labels, clustered.labels)
    assert recording.name(1) == str(sequence.bins[2])


def test_scan_files_centroids_and_folders_in_one_recording(world, layouts, tmp_path):
    """A list mixing a SemanticKITTI .bin, a HeLiPR .bin (its stamp kept), a centroid file and an
    instance-map folder: numbered by position, each read in its own format; ``gt=`` by order."""
    kitti_bin = layouts["semantickitti"] / "velodyne" / "000003.bin"
    helipr_bin = layouts["helipr"] / "LiDAR" / "Ouster" / f"{STAMPS[4]}.bin"
    centroids = write_centroids(tmp_path / "c.txt", world.points[:7], world.labels[:7])
    paths = [kitti_bin, helipr_bin, centroids, layouts["map"]]
    recording = open_lidar_recording(paths)
    assert recording.numbers == (0, 1, 2, 3) and recording.poses is None
    assert recording.stamps == (None, STAMPS[4], None, None) and recording.timestamps is None
    assert recording.sequences == () and recording.sources == (-1, -1, -1, -1)
    sequence = open_lidar_sequence(layouts["semantickitti"])
    expected = cluster_instances(*read_sequence_scan(sequence, 3)[:2])
    np.testing.assert_array_equal(recording.instances(0).points, expected.points)
    helipr = open_lidar_sequence(layouts["helipr"])
    expected = cluster_instances(*read_sequence_scan(helipr, 4)[:2])
    np.testing.assert_array_equal(recording.instances(1).points, expected.points)
    points, labels = read_centroid_scan(centroids)
    np.testing.assert_array_equal(recording.instances(2).points, points)
    np.testing.assert_array_equal(recording.instances(2).labels, labels)
    as_map = read_instance_map(layouts["map"])
    np.testing.assert_array_equal(recording.instances(3).points, as_map.points)
    for index in (2, 3):
        with pytest.raises(ValueError, match="instance centroids, not a labelled point scan"):
            recording.scan(index)
    gt = tmp_path / "gt.txt"
    poses = np.tile(np.eye(4), (4, 1, 1))
    poses[:, 0, 3] = np.arange(4)
    np.savetxt(gt, poses[:, :3].reshape(4, 12))
    judged = open_lidar_recording(paths, gt=gt)
    assert judged.paths == recording.paths and judged.has_pose.all()
    np.testing.assert_array_equal(judged.poses, poses)


def test_ground_truth_by_time_matches_stamps_and_leaves_unmatched_scans_without(
    scans, layouts, tmp_path
):
    """A TUM file in seconds matched to HeLiPR stamps within 1 ms: a scan without a line there has
    no pose; a file by order must have one line per scan."""
    lines = [tum_line(ns_to_seconds(t), p) for t, p in zip(STAMPS, scans.T_map_scan, strict=True)]
    del lines[2]
    gt = tmp_path / "gt.tum"
    gt.write_text("\n".join(lines) + "\n")
    recording = open_lidar_recording(layouts["helipr"], gt=gt)
    np.testing.assert_array_equal(recording.has_pose, [True, True, False, True, True, True])
    np.testing.assert_array_equal(recording.poses[2], np.eye(4))
    np.testing.assert_allclose(recording.poses[[0, 1, 3]], scans.T_map_scan[[0, 1, 3]], atol=1e-9)
    by_order = tmp_path / "five.txt"
    np.savetxt(by_order, scans.T_map_scan[:5, :3].reshape(5, 12))
    with pytest.raises(ValueError, match=r"five\.txt: 5 poses for 6 scan\(s\)"):
        open_lidar_recording(layouts["semantickitti"], gt=by_order)
    without_stamps = open_lidar_recording(layouts["semantickitti"])
    with pytest.raises(ValueError, match=r"gt\.tum: 5 poses for 6 scan\(s\)"):  # then by order
        without_stamps.with_poses(gt)


# ----------------------------------------------------------------------------- broken forms


def _broken(layouts: dict[str, Path], root: Path) -> dict[str, tuple[list, dict, type, str]]:
    """name -> (paths, options, exception type, message part) of one broken form each."""

    def copy(name: str, layout: str) -> Path:
        return shutil.copytree(layouts[layout], root / name / layouts[layout].name)

    cases = {}
    scan = root / "loose" / "velodyne" / "000001.bin"
    scan.parent.mkdir(parents=True)
    shutil.copy(layouts["semantickitti"] / "velodyne" / "000001.bin", scan)
    cases["bin without labels"] = ([scan], {}, FileNotFoundError, "000001.bin: no label file")
    cases["missing scan"] = ([root / "absent.txt"], {}, FileNotFoundError, "missing scan: ")
    ply = root / "scan.ply"
    ply.write_text("ply\n")
    cases["unknown suffix"] = ([ply], {}, ValueError, "scan.ply: unknown scan format")
    calib = copy("calib", "semantickitti")
    (calib / "calib.txt").write_text("Tr: 1 2 3\n")
    cases["SemanticKITTI calib"] = ([calib], {}, ValueError, "calib.txt:1: expected 'KEY: 12")
    label = copy("label", "semantickitti")
    (label / "labels" / "000002.label").unlink()
    cases["SemanticKITTI label"] = ([label], {}, FileNotFoundError, "000002.label: missing label")
    poses = copy("poses", "plain")
    rows = (poses / "poses.txt").read_text().splitlines()
    (poses / "poses.txt").write_text("\n".join(rows[:-1]) + "\n")
    cases["plain pose count"] = ([poses], {}, ValueError, "poses.txt: 5 poses for 6 scans")
    forced = ([layouts["helipr"]], {"layout": "semantickitti"}, FileNotFoundError, "calib.txt")
    cases["HeLiPR read as SemanticKITTI"] = forced
    cases["HeLiPR sensor"] = (
        [layouts["helipr"]], {"sensor": "Avia"}, ValueError, "no scans in LiDAR/Avia/",
    )  # fmt: skip
    gt = copy("gt", "helipr")
    rows = (gt / "LiDAR_GT" / "Ouster_gt.txt").read_text().splitlines()
    rows[1] = " ".join([*rows[1].split()[:2], "nan", *rows[1].split()[3:]])
    (gt / "LiDAR_GT" / "Ouster_gt.txt").write_text("\n".join(rows) + "\n")
    cases["HeLiPR NaN GT"] = ([gt], {}, ValueError, "Ouster_gt.txt:2: pose has NaN or inf")
    named = copy("named", "helipr")
    bad_name = named / "LiDAR" / "Ouster" / "first.bin"
    shutil.copy(named / "LiDAR" / "Ouster" / f"{STAMPS[0]}.bin", bad_name)
    shutil.copy(named / "labels" / f"{STAMPS[0]}.label", named / "labels" / "first.label")
    cases["HeLiPR scan not named by its stamp"] = (
        [bad_name], {}, ValueError, "a HeLiPR scan is named <stamp_ns>.bin",
    )  # fmt: skip
    unlabelled = copy("unlabelled", "helipr")
    alone = unlabelled / "LiDAR" / "Ouster" / f"{STAMPS[1]}.bin"
    (unlabelled / "labels" / f"{STAMPS[1]}.label").unlink()
    cases["HeLiPR scan without labels"] = ([alone], {}, FileNotFoundError, "no label file")
    cases["every 0"] = ([layouts["plain"]], {"every": 0}, ValueError, "every must be >= 1")
    return cases


def test_broken_forms_of_each_layout_raise_naming_the_file(layouts, tmp_path):
    for name, (paths, options, kind, message) in _broken(layouts, tmp_path).items():
        with pytest.raises(kind) as caught:
            open_lidar_recording(paths, **options)
        assert message in str(caught.value), (name, str(caught.value))


def test_broken_scans_raise_when_read(world, layouts, tmp_path):
    """What only reading finds (malformed centroid lines, unknown classes, truncated points)
    raises from ``instances`` and ``scan``, naming the file and line."""
    short = tmp_path / "short.txt"
    short.write_text("15 1.0 2.0\n")
    unknown = write_centroids(tmp_path / "unknown.txt", world.points[:2], [15, 12])
    folder = shutil.copytree(layouts["semantickitti"], tmp_path / "truncated")
    path = folder / "velodyne" / "000004.bin"
    path.write_bytes(path.read_bytes()[:-4])
    recording = open_lidar_recording([short, unknown, folder])
    with pytest.raises(ValueError, match=r"short\.txt:1: expected 4 numbers"):
        recording.instances(0)
    with pytest.raises(ValueError, match=r"unknown\.txt: unknown class ids \[12\]"):
        recording.instances(1)
    with pytest.raises(ValueError, match=r"000004\.bin: .* not a multiple of 4"):
        recording.instances(2 + 4)
    recording.instances(2 + 3)  # the others read


# ----------------------------------------------------------------------------- poses out


def test_poses_out_leaves_invalid_scans_out_of_tum_only(world, tmp_path):
    """TUM: valid scans, stamped with their time or else their scan number; KITTI: every scan in
    order, a failed one with the pose given for it (the identity)."""
    from evo.tools.file_interface import read_kitti_poses_file, read_tum_trajectory_file

    paths = [write_centroids(tmp_path / f"{n}.txt", world.points[:3], world.labels[:3])
             for n in "abc"]  # fmt: skip
    recording = open_lidar_recording(paths)
    moved = np.eye(4)
    moved[:3, 3] = [1.0, 2.0, 3.0]
    poses, valid = np.stack([moved, np.eye(4), moved]), np.array([True, False, True])
    assert write_lidar_poses(tmp_path / "n.tum", recording, poses, valid) == 1
    trajectory = read_tum_trajectory_file(str(tmp_path / "n.tum"))
    np.testing.assert_array_equal(trajectory.timestamps, [0.0, 2.0])  # numbers 0, 1, 2
    np.testing.assert_array_equal(trajectory.positions_xyz, [[1, 2, 3], [1, 2, 3]])
    timed = dataclasses.replace(recording, stamps=tuple(FIRST_STAMP + n for n in range(3)))
    write_lidar_poses(tmp_path / "t.tum", timed, poses, valid)
    first = (tmp_path / "t.tum").read_text().splitlines()[0].split(" ")[0]
    assert first == "1691900000.123456789"
    assert write_lidar_poses(tmp_path / "k.txt", recording, poses, valid, "kitti") == 0
    kitti = read_kitti_poses_file(str(tmp_path / "k.txt"))
    np.testing.assert_array_equal(np.asarray(kitti.poses_se3), [moved, np.eye(4), moved])
    with pytest.raises(ValueError, match="one pose and flag per scan"):
        write_lidar_poses(tmp_path / "x.tum", recording, poses[:2], valid[:2])


# ----------------------------------------------------------------------------- maps


def test_open_triplet_map_of_a_folder_and_of_its_saved_file(world, layouts, tmp_path):
    """A folder is described with the configuration (road normals read unless ``use_rsn`` is
    off); its saved file loads to the same map; ``replace`` changes matching settings of either
    and fits ``top_k`` to the map; broken forms raise naming the file."""
    config = m2loc_config(1, top_k=10)
    described = open_triplet_map(layouts["map"], config)
    files = read_instance_map(layouts["map"])
    direct = build_map(files.points, files.labels, config, read_road_normals(layouts["map"]))
    for name in ("points", "descriptors", "rsn_normals"):
        np.testing.assert_array_equal(getattr(described, name), getattr(direct, name), name)
    assert described.has_rsn and described.config == config
    assert not open_triplet_map(layouts["map"], config, replace={"use_rsn": False}).has_rsn
    saved = tmp_path / "map.npz"
    save_triplet_map(described, saved)
    loaded = open_triplet_map(saved, replace={"min_clique": 4})
    np.testing.assert_array_equal(np.asarray(loaded.descriptors), np.asarray(described.descriptors))
    assert loaded.config.min_clique == 4 and loaded.config.top_k == 10
    with pytest.warns(SmallMapWarning, match="exceeds the"):
        clamped = open_triplet_map(saved, replace={"top_k": 10**6})
    assert clamped.config.top_k == len(world.points)
    with pytest.raises(ValueError, match="a saved map keeps the configuration"):
        open_triplet_map(saved, config)
    with pytest.raises(FileNotFoundError, match="map folder not found"):
        open_triplet_map(tmp_path / "absent")
    partial = shutil.copytree(layouts["map"], tmp_path / "partial")
    (partial / "instances" / "17.txt").unlink()
    with pytest.raises(FileNotFoundError, match=r"partial: missing instances/17\.txt"):
        open_triplet_map(partial)
