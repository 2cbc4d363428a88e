"""HeLiPR / TripletLoc sequences: point records of the four sensors, SPVNAS labels, GT lines,
scans matched to poses by timestamp, and the same map as the SemanticKITTI layout.

The fixtures are written byte by byte by ``tests/_helipr_fixtures.py`` in the order of the C++
readers that define the formats (HeLiPR-File-Player ``src/ROSThread.h`` / ``src/ROSThread.cpp``,
HeLiPR-Pointcloud-Toolbox ``src/PointCloudProcessor.cpp``, TripletLoc ``src/TripletLoc.cpp``);
single records are also packed with ``struct`` from the C++ field order, to check every field.
"""

from __future__ import annotations

import shutil
import struct
from pathlib import Path

import numpy as np
import pytest
from _helipr_fixtures import (
    AEVA_THRESHOLD,
    FIRST_STAMP,
    PERIOD_NS,
    pack_labels,
    tum_line,
    write_helipr_sequence,
    write_kitti_twin,
)
from scipy.spatial.transform import Rotation

from jaxloc.io import read_helipr_scan
from jaxloc.io.helipr import choose_sensor, read_helipr_gt, read_helipr_points, read_spvnas_labels
from jaxloc.io.lidar_sequence import (
    detect_layout,
    is_sequence_dir,
    open_lidar_sequence,
    read_sequence_scan,
)
from jaxloc.mapping import MapBuildConfig, build_lidar_maps
from jaxloc.synthetic.lidar_scans import make_lidar_sequence
from jaxloc.synthetic.outdoor import make_outdoor_world

SENSORS = ("Ouster", "Velodyne", "Avia", "Aeva")
#: Point format of each scan folder.
FORMATS = {"Ouster": "ouster", "Velodyne": "velodyne", "Avia": "avia", "Aeva": "aeva"}
FORMATS["Ouster_filterd"] = "ouster"


@pytest.fixture(scope="module")
def scans():
    """Six scans of a 100 m drive through a one-block world."""
    world = make_outdoor_world("dense", seed=4, blocks=1, bridge_length=0)
    return make_lidar_sequence(
        world, (20.0, 0.0), (120.0, 0.0), 6, seed=5, max_range=30.0, road_points=3000,
        clutter_points=300,
    )  # fmt: skip


@pytest.fixture(scope="module")
def helipr_dir(scans, tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("helipr") / "KAIST05"
    write_helipr_sequence(root, scans)
    return root


# ----------------------------------------------------------------------------- records


def _packed(sensor: str, stamp: int) -> tuple[bytes, dict]:
    """One record packed with struct in the C++ readers' field order, and its field values."""
    if sensor == "Ouster":  # float x y z intensity, uint32 t, uint16 reflectivity ring ambient
        values = dict(x=1.5, y=-2.25, z=3.125, intensity=40.5, t=123456789, reflectivity=7,
                      ring=127, ambient=65000)  # fmt: skip
        return struct.pack("<4fI3H", *values.values()), values
    if sensor == "Velodyne":  # float x y z intensity, uint16 ring, float time
        values = dict(x=1.5, y=-2.25, z=3.125, intensity=12.0, ring=15, time=-0.0625)
        return struct.pack("<4fHf", *values.values()), values
    if sensor == "Avia":  # float x y z, uint8 reflectivity tag line, uint32 offset_time
        values = dict(x=1.5, y=-2.25, z=3.125, reflectivity=200, tag=16, line=5,
                      offset_time=99999999)  # fmt: skip
        return struct.pack("<3f3BI", *values.values()), values
    # Aeva: float x y z reflectivity velocity, int32 time_offset_ns, uint8 line_index
    # [, float intensity after the threshold stamp]
    values = dict(x=1.5, y=-2.25, z=3.125, reflectivity=0.75, velocity=-12.5,
                  time_offset_ns=-50000, line_index=63)  # fmt: skip
    if stamp > AEVA_THRESHOLD:
        values["intensity"] = 0.5
        return struct.pack("<5fiBf", *values.values()), values
    return struct.pack("<5fiB", *values.values()), values


@pytest.mark.parametrize(
    ("sensor", "stamp", "size"),
    [
        ("Ouster", FIRST_STAMP, 26),
        ("Velodyne", FIRST_STAMP, 22),
        ("Avia", FIRST_STAMP, 19),
        ("Aeva", AEVA_THRESHOLD, 25),  # "if (data > 1691936557946849179)": not at the threshold
        ("Aeva", AEVA_THRESHOLD + 1, 29),
    ],
)
def test_records_match_the_cpp_readers(tmp_path, sensor, stamp, size):
    record, values = _packed(sensor, stamp)
    assert len(record) == size
    path = tmp_path / "LiDAR" / sensor / f"{stamp}.bin"
    path.parent.mkdir(parents=True)
    path.write_bytes(record * 3)
    read = read_helipr_points(path, FORMATS[sensor])
    assert read.dtype.itemsize == size and len(read) == 3
    for name, value in values.items():
        np.testing.assert_array_equal(read[name], [value] * 3, err_msg=name)
    path.write_bytes(record * 3 + record[:-1])  # a partial record: the C++ loop's garbage point
    with pytest.raises(ValueError, match=rf"{stamp}\.bin: {4 * size - 1} bytes is not a whole"):
        read_helipr_points(path, FORMATS[sensor])


def test_labels_are_spvnas_class_ids_with_instances(tmp_path):
    """uint16 class + uint16 instance: the bytes of a SemanticKITTI uint32 word, but the class
    is SPVNAS's (8 road, 15 trunk, 17 pole, 18 sign), used as it is; ids > 18 are unlabelled."""
    words = np.array([[8, 0], [15, 3], [17, 65535], [18, 1], [19, 2], [255, 0]], "<u2")
    (tmp_path / "a.label").write_bytes(words.tobytes())
    classes, instances = read_spvnas_labels(tmp_path / "a.label")
    np.testing.assert_array_equal(classes, [8, 15, 17, 18, -1, -1])
    np.testing.assert_array_equal(instances, [0, 3, 65535, 1, 2, 0])
    (tmp_path / "b.label").write_bytes(words.tobytes()[:-2])
    with pytest.raises(ValueError, match=r"b\.label: 22 bytes is not a whole number of 4-byte"):
        read_spvnas_labels(tmp_path / "b.label")


def test_scan_reads_points_and_labels_of_every_sensor(scans, tmp_path):
    for sensor in (*SENSORS, "Ouster_filterd"):
        stamp = AEVA_THRESHOLD + 1 if sensor == "Aeva" else FIRST_STAMP
        root = tmp_path / sensor
        write_helipr_sequence(root, scans, sensor, stamps=[stamp + i for i in range(6)])
        bin_path = root / "LiDAR" / sensor / f"{stamp + 2}.bin"
        scan = read_helipr_scan(bin_path, root / "labels" / f"{stamp + 2}.label", FORMATS[sensor])
        np.testing.assert_array_equal(scan.points, scans.points[2])
        raw = scans.raw_labels[2]
        assert set(np.unique(scan.labels)) <= {8, 12, 15, 17, 18}
        np.testing.assert_array_equal(scan.labels == 15, (raw & 0xFFFF) == 71)
        np.testing.assert_array_equal(scan.instance_ids, raw >> 16)


def test_label_count_and_non_finite_points_are_errors(scans, helipr_dir, tmp_path):
    root = tmp_path / "seq"
    shutil.copytree(helipr_dir, root)
    label = root / "labels" / f"{FIRST_STAMP}.label"
    label.write_bytes(label.read_bytes()[:-4])
    bin_path = root / "LiDAR" / "Ouster" / f"{FIRST_STAMP}.bin"
    with pytest.raises(ValueError, match=rf"{FIRST_STAMP}\.label: \d+ labels for \d+ points"):
        read_helipr_scan(bin_path, label, "ouster")
    data = bytearray(bin_path.read_bytes())
    data[26 * 5 : 26 * 5 + 4] = struct.pack("<f", np.nan)  # x of point 5
    bin_path.write_bytes(bytes(data))
    label.write_bytes(pack_labels(scans.raw_labels[0]))
    with pytest.raises(ValueError, match=rf"{FIRST_STAMP}\.bin: non-finite point coordinates"):
        read_helipr_scan(bin_path, label, "ouster")


# ----------------------------------------------------------------------------- ground truth


def test_gt_lines_give_exact_stamps_and_xyzw_rotations(tmp_path):
    """TripletLoc builds ``Quaterniond(c[6], c[3], c[4], c[5])`` from the fields after the stamp,
    i.e. x y z w order; a yaw of 90 deg is q = (0, 0, sin 45, cos 45)."""
    s = float(np.sqrt(0.5))
    gt = tmp_path / "Ouster_gt.txt"
    gt.write_text(
        f"1691936557946849179 10.5 -2 0.25 0 0 {s!r} {s!r}\n"
        "1691936558046849180 1 2 3 0.1 0.2 0.3 0.9273618495495703\n"
    )
    read = read_helipr_gt(gt)
    assert read.stamps.dtype == np.int64
    np.testing.assert_array_equal(read.stamps, [1691936557946849179, 1691936558046849180])
    np.testing.assert_allclose(read.T_world_lidar[0][:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]],
                               atol=1e-15)  # fmt: skip
    np.testing.assert_array_equal(read.T_world_lidar[0][:3, 3], [10.5, -2, 0.25])
    q = np.array([0.1, 0.2, 0.3, 0.9273618495495703])
    reference = Rotation.from_quat(q / np.linalg.norm(q)).as_matrix()  # scipy: scalar last
    np.testing.assert_allclose(read.T_world_lidar[1][:3, :3], reference, atol=1e-15)
    gt.write_text("1691936557946849179 1 2 3 0 0 0 1\n1691936557946849179 1 2 3 0 0 0 1\n")
    with pytest.raises(ValueError, match="stamp 1691936557946849179 appears more than once"):
        read_helipr_gt(gt)
    gt.write_text("1691936557.946849179 1 2 3 0 0 0 1\n")
    with pytest.raises(ValueError, match=r"Ouster_gt\.txt:1: timestamp .* is not an integer"):
        read_helipr_gt(gt)


def test_scans_match_gt_lines_by_exact_stamp(scans, helipr_dir, tmp_path):
    """Every scan has its GT line here; then: a scan without a line is left out (skipped), a
    line without a scan is ignored, and a line 1 ns off matches nothing."""
    sequence = open_lidar_sequence(helipr_dir)
    assert (sequence.layout, sequence.sensor, sequence.point_format, sequence.label_ids) == (
        "helipr", "Ouster", "ouster", "spvnas",
    )  # fmt: skip
    np.testing.assert_array_equal(sequence.timestamps, FIRST_STAMP + PERIOD_NS * np.arange(6))
    np.testing.assert_allclose(sequence.T_map_scan, scans.T_map_scan, atol=1e-12)
    assert sequence.skipped == () and sequence.unused_poses == 0
    root = tmp_path / "partial"
    stamps = [FIRST_STAMP + PERIOD_NS * i for i in range(6)]
    gt_stamps = [stamps[0] - PERIOD_NS, stamps[0], stamps[1] + 1, *stamps[2:5]]  # no scan 1, 5
    gt_poses = np.concatenate([scans.T_map_scan[:1], scans.T_map_scan[:5]])
    write_helipr_sequence(root, scans, stamps=stamps, gt_poses=gt_poses, gt_stamps=gt_stamps)
    partial = open_lidar_sequence(root)
    np.testing.assert_array_equal(partial.timestamps, [stamps[i] for i in (0, 2, 3, 4)])
    assert [p.stem for p in partial.skipped] == [str(stamps[1]), str(stamps[5])]
    assert partial.unused_poses == 2  # the line before the first scan and the one 1 ns off
    np.testing.assert_allclose(partial.T_map_scan, scans.T_map_scan[[0, 2, 3, 4]], atol=1e-12)
    assert [p.stem for p in partial.labels] == [str(stamps[i]) for i in (0, 2, 3, 4)]
    wrong = tmp_path / "wrong_unit"
    write_helipr_sequence(wrong, scans, gt_stamps=[s // 1000 for s in stamps])
    with pytest.raises(ValueError, match="Ouster_gt.txt: no pose has the time of a scan"):
        open_lidar_sequence(wrong)


def test_layout_detection_label_folders_and_sensor_choice(scans, helipr_dir, tmp_path):
    assert detect_layout(helipr_dir) == "helipr" and is_sequence_dir(helipr_dir)
    readme = tmp_path / "readme_layout"  # TripletLoc's README: label/, LiDAR/Ouster_filterd/
    write_helipr_sequence(readme, scans, "Ouster_filterd", label_folder="label")
    sequence = open_lidar_sequence(readme)
    assert sequence.sensor == "Ouster_filterd" and sequence.labels[0].parent.name == "label"
    assert (readme / "LiDAR_GT" / "Ouster_gt.txt").is_file()
    both = tmp_path / "two_sensors"
    write_helipr_sequence(both, scans, "Velodyne")
    write_helipr_sequence(both, scans, "Aeva")
    with pytest.raises(ValueError, match=r"several sensors \['Velodyne', 'Aeva'\]"):
        choose_sensor(both)
    assert open_lidar_sequence(both, sensor="aeva").sensor == "Aeva"
    write_helipr_sequence(both, scans, "Ouster")
    assert open_lidar_sequence(both).sensor == "Ouster"  # several: Ouster
    with pytest.raises(ValueError, match=r"no scans in LiDAR/Avia/"):
        open_lidar_sequence(both, sensor="Avia")
    (both / "LiDAR_GT" / "Velodyne_gt.txt").unlink()
    with pytest.raises(FileNotFoundError, match="Velodyne_gt.txt: missing ground-truth poses"):
        open_lidar_sequence(both, sensor="Velodyne")
    assert open_lidar_sequence(both, require_poses=False, sensor="Velodyne").T_map_scan is None
    (both / "labels" / f"{FIRST_STAMP}.label").unlink()
    with pytest.raises(FileNotFoundError, match=rf"{FIRST_STAMP}\.label: missing label file"):
        open_lidar_sequence(both)


# ----------------------------------------------------------------------------- same maps


@pytest.mark.parametrize("sensor", SENSORS)
def test_helipr_layout_builds_the_same_map_as_semantickitti(scans, tmp_path, sensor):
    """The same points, labels and poses in both layouts give exactly the same instance and RSN
    maps. The SemanticKITTI twin gets the poses read from the HeLiPR GT (as repr floats, Tr =
    identity), so both readers hand the builder bit-identical poses; that the GT itself is read
    right is checked above and against the scans' true poses here."""
    stamp = AEVA_THRESHOLD - 3 * PERIOD_NS if sensor == "Aeva" else FIRST_STAMP  # 25 and 29 B
    stamps = [stamp + PERIOD_NS * i for i in range(6)]
    write_helipr_sequence(tmp_path / "h", scans, sensor, stamps=stamps)
    helipr = open_lidar_sequence(tmp_path / "h")
    if sensor == "Aeva":
        sizes = {(p.stat().st_size / len(scans.points[i])) for i, p in enumerate(helipr.bins)}
        assert sizes == {25.0, 29.0}
    np.testing.assert_allclose(helipr.T_map_scan, scans.T_map_scan, atol=1e-12)
    write_kitti_twin(tmp_path / "k", scans, helipr.T_map_scan)
    kitti = open_lidar_sequence(tmp_path / "k")
    assert kitti.layout == "semantickitti"
    np.testing.assert_array_equal(kitti.T_map_scan, helipr.T_map_scan)
    for index in range(6):
        a, b = read_sequence_scan(helipr, index), read_sequence_scan(kitti, index)
        for name in ("points", "labels", "instance_ids"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    config = MapBuildConfig(every=2)
    from_helipr, from_kitti = build_lidar_maps(helipr, config), build_lidar_maps(kitti, config)
    assert len(from_helipr.instances.points) >= 20
    for name in ("points", "labels", "sizes"):
        np.testing.assert_array_equal(
            getattr(from_helipr.instances, name), getattr(from_kitti.instances, name), name
        )
    for name in ("xy", "normals", "std_deg"):
        np.testing.assert_array_equal(
            getattr(from_helipr.road_normals, name), getattr(from_kitti.road_normals, name), name
        )


def test_gt_line_helper_is_tum_compatible():
    """The fixture's GT lines are what evo's TUM reader splits: single spaces, 8 fields."""
    line = tum_line("1", np.eye(4))
    assert "  " not in line and len(line.split(" ")) == 8
