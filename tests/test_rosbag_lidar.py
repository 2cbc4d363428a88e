"""LiDAR recordings from bags (``jaxloc.io.open_lidar_recording`` on a ROS 1 ``.bag``, a ROS 2
folder of sqlite3 or MCAP storage and a bare ``.mcap``) and poses out as bags
(``write_pose_bag``, ``write_lidar_poses``).

The bags are written here with ``rosbags``' writers (``tests/_rosbag_fixtures.py``) from six
synthetic scans of a one-block world, beside the same scans as a SemanticKITTI folder with exact
poses: the bag reads as the folder (points, labels, instances), its odometry is the drive's
poses, and ``localize_drive`` gives the folder's flags and poses. Bad bags raise one line naming
the bag and the topic."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from _drive_records import cli_json
from _helipr_fixtures import tum_line, write_kitti_twin
from _rosbag_fixtures import KINDS, BagWriter, bag_path, packed_records, write_drive
from hypothesis import HealthCheck, given, settings, strategies as st
from scipy.spatial.transform import Rotation

from jaxloc.cli import main
from jaxloc.io.lidar_map import save_triplet_map
from jaxloc.io.lidar_recording import open_lidar_recording, write_lidar_poses
from jaxloc.io.poses import format_ns_as_seconds
from jaxloc.io.rosbag_poses import write_pose_bag
from jaxloc.m2loc import build_map, localize_drive, m2loc_config
from jaxloc.synthetic.lidar_scans import make_lidar_sequence
from jaxloc.synthetic.outdoor import make_outdoor_world

FIRST = 1_700_000_000_000_000_000
STAMPS = [FIRST + 100_000_000 * i for i in range(6)]


@pytest.fixture(scope="module")
def world():
    return make_outdoor_world("dense", seed=4, blocks=1, bridge_length=0)


@pytest.fixture(scope="module")
def scans(world):
    return make_lidar_sequence(
        world, (20.0, 0.0), (120.0, 0.0), 6, seed=5, max_range=30.0, road_points=3000,
        clutter_points=300,
    )  # fmt: skip


@pytest.fixture(scope="module")
def written(scans, tmp_path_factory) -> dict[str, Path]:
    """The drive as a folder ("folder") and as a bag of each kind, odometry on /odom."""
    root = tmp_path_factory.mktemp("bags")
    write_kitti_twin(root / "folder", scans, scans.T_map_scan)
    paths = {"folder": root / "folder"}
    for kind in KINDS:
        (root / kind).mkdir()
        paths[kind] = write_drive(bag_path(root / kind, kind), kind, scans, STAMPS)
    return paths


def one_line_error(call, *parts: str) -> str:
    with pytest.raises(ValueError) as caught:
        call()
    message = str(caught.value)
    assert "\n" not in message, message
    for part in parts:
        assert part in message, (part, message)
    return message


# ----------------------------------------------------------------------------- reading


@pytest.mark.parametrize("kind", KINDS)
def test_a_bag_reads_as_its_folder(scans, written, kind):
    """Every cloud as the folder's scan (points, class ids, instances, clustered centroids),
    stamped by its header; the odometry is the drive's poses; ``every`` keeps every k-th."""
    recording = open_lidar_recording(written[kind])
    folder = open_lidar_recording(written["folder"])
    assert len(recording) == 6 and recording.numbers == tuple(range(6))
    assert recording.stamps == tuple(STAMPS) and recording.poses is None
    assert not recording.has_pose.any() and recording.bag.odometry_topic == "/odom"
    np.testing.assert_allclose(recording.odometry, scans.T_map_scan, atol=1e-12)
    for index in range(6):
        mine, theirs = recording.scan(index), folder.scan(index)
        for name in ("points", "labels", "instance_ids"):
            np.testing.assert_array_equal(getattr(mine, name), getattr(theirs, name), name)
    np.testing.assert_array_equal(recording.instances(3).points, folder.instances(3).points)
    assert recording.name(2) == f"{written[kind]}:/points[2]"
    thinned = open_lidar_recording(written[kind], every=2)
    assert thinned.numbers == (0, 2, 4) and thinned.stamps == tuple(STAMPS[::2])
    np.testing.assert_array_equal(thinned.scan(1).points, folder.scan(2).points)
    recording.bag.close()


@pytest.fixture(scope="module")
def triplet_map(world):
    return build_map(world.points, world.labels, m2loc_config(1, hypotheses=0), world.road_normals)


@pytest.mark.parametrize("kind", ["ros1", "bare-mcap"])
def test_localize_drive_on_a_bag_gives_the_folder_s_flags_and_poses(
    triplet_map, scans, written, kind, tmp_path
):
    """Fused windows of 3 scans through the bag's odometry, or through a TUM ground truth
    (``gt=``, which the drive then uses as the folder's poses): the folder's flags and poses;
    the poses written as a bag hold one PoseStamped per valid scan, stamped as the scan."""
    from rosbags.highlevel import AnyReader

    folder = localize_drive(triplet_map, open_lidar_recording(written["folder"]), accumulate=3)
    recording = open_lidar_recording(written[kind])
    drive = localize_drive(triplet_map, recording, odometry=recording.odometry, accumulate=3)
    gt = tmp_path / "gt.tum"
    lines = [
        tum_line(format_ns_as_seconds(t), p) for t, p in zip(STAMPS, scans.T_map_scan, strict=True)
    ]
    gt.write_text("\n".join(lines) + "\n")
    judged = open_lidar_recording(written[kind], gt=gt)
    assert judged.has_pose.all()
    by_gt = localize_drive(triplet_map, judged, accumulate=3)
    assert folder.valid.sum() >= 4
    for result in (drive, by_gt):
        np.testing.assert_array_equal(result.valid, folder.valid)
        np.testing.assert_allclose(result.poses, folder.poses, atol=1e-6)
    valid = drive.valid.copy()
    valid[1] = False
    out = tmp_path / "est.mcap"
    assert write_lidar_poses(out, recording, drive.poses, valid) == 1
    with AnyReader([out]) as reader:
        found = [
            (connection.topic, time, reader.deserialize(raw, connection.msgtype))
            for connection, time, raw in reader.messages()
        ]
    poses = [(t, m) for topic, t, m in found if topic == "/jaxloc/pose"]
    flags = [m.data for topic, _, m in found if topic == "/jaxloc/valid"]
    assert flags == valid.tolist()
    assert [t for t, _ in poses] == [s for s, ok in zip(STAMPS, valid, strict=True) if ok]
    for (time, message), pose in zip(poses, drive.poses[valid], strict=True):
        stamp = message.header.stamp
        assert stamp.sec * 10**9 + stamp.nanosec == time and message.header.frame_id == "map"
        p, q = message.pose.position, message.pose.orientation
        np.testing.assert_allclose([p.x, p.y, p.z], pose[:3, 3], atol=1e-12)
        rotation = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
        np.testing.assert_allclose(rotation, pose[:3, :3], atol=1e-6)  # float32 estimates


def test_build_lidar_map_on_a_bag_is_the_folder_s_map(scans, written, tmp_path, capsys):
    """``jaxloc build-lidar-map BAG``: the folder's instance and road-normal files, the scans
    placed by the bag's odometry or by ``--gt`` (which also replaces a folder's poses); a bag
    option on a folder and a folder option on a bag are one line each."""
    gt = tmp_path / "gt.tum"
    poses = zip(STAMPS, scans.T_map_scan, strict=True)
    gt.write_text("".join(tum_line(format_ns_as_seconds(t), p) + "\n" for t, p in poses))
    common = ["--every", "2", "--no-progress"]
    runs = {"folder": [written["folder"]], "odometry": [written["mcap"]],
            "gt": [written["mcap"], "--gt", gt],
            "folder_gt": [written["folder"], "--gt", gt]}  # fmt: skip
    for name, source in runs.items():
        assert main([str(a) for a in ["build-lidar-map", *source, tmp_path / name, *common]]) == 0
    assert "placed by its odometry" in capsys.readouterr().out
    files = ["instances/15.txt", "instances/17.txt", "instances/18.txt", "RSN/road_normal.txt"]
    for name in ("odometry", "gt", "folder_gt"):
        for file in files:
            expected = np.loadtxt(tmp_path / "folder" / file, ndmin=2)
            np.testing.assert_allclose(np.loadtxt(tmp_path / name / file, ndmin=2), expected,
                                       atol=1e-6, err_msg=f"{name}: {file}")  # fmt: skip
    assert sum(len(np.loadtxt(tmp_path / "gt" / f, ndmin=2)) for f in files[:3]) >= 5
    for argv, expected in (
        (
            [written["folder"], tmp_path / "x", "--topic", "/points"],
            "topic='/points' applies to bags",
        ),
        (
            [written["mcap"], tmp_path / "y", "--sensor", "Ouster"],
            "applies to sequence folders, not",
        ),
    ):
        assert main([str(a) for a in ["build-lidar-map", *argv]]) == 2
        error = capsys.readouterr().err.strip()
        assert "\n" not in error and expected in error, error


def test_localize_lidar_on_a_bag_writes_its_poses_as_a_bag(triplet_map, scans, tmp_path, capsys):
    """``jaxloc localize-lidar`` on an MCAP bag of two cloud topics (``--topic`` names one), its
    windows fused through the bag's own odometry: the library's flags and poses, written with
    ``--poses-out x.mcap`` as a PoseStamped per valid scan and with ``--rerun`` as a recording
    Rerun's reader loads; without ``--topic``, one line."""
    from rosbags.highlevel import AnyReader

    bag = tmp_path / "drive.mcap"
    with BagWriter(bag, "bare-mcap") as writer:
        for stamp, points, raw, pose in zip(
            STAMPS, scans.points, scans.raw_labels, scans.T_map_scan, strict=True
        ):
            writer.cloud("/points", stamp, packed_records(points, raw))
            writer.cloud("/points_raw", stamp, packed_records(points, raw))
            writer.odometry("/odom", stamp, pose)
    save_triplet_map(triplet_map, tmp_path / "map.npz")
    out = tmp_path / "est.mcap"
    argv = ["localize-lidar", tmp_path / "map.npz", bag, "--accumulate", "3", "--json",
            "--no-progress", "--poses-out", out]  # fmt: skip
    assert main([str(a) for a in argv]) == 2
    error = capsys.readouterr().err.strip()
    assert "\n" not in error and "2 PointCloud2 topics" in error and "topic=" in error, error
    rrd = tmp_path / "drive.rrd"
    assert main([str(a) for a in [*argv, "--topic", "/points", "--rerun", rrd]]) == 0
    report = json.loads(capsys.readouterr().out)
    recording = open_lidar_recording(bag, topic="/points")
    expected = localize_drive(triplet_map, recording, odometry=recording.odometry, accumulate=3)
    assert [r["valid"] for r in report["scans"]] == expected.valid.tolist()
    assert expected.valid.sum() >= 4 and report["scans"][0]["scan"] == f"{bag}:/points[0]"
    with AnyReader([out]) as reader:
        found = [
            (connection.msgtype, time, reader.deserialize(raw, connection.msgtype))
            for connection, time, raw in reader.messages()
            if connection.topic == "/jaxloc/pose"
        ]
    assert [t for _, t, _ in found] == [
        s for s, ok in zip(STAMPS, expected.valid, strict=True) if ok
    ]
    for (msgtype, _, message), pose in zip(found, expected.poses[expected.valid], strict=True):
        assert msgtype == "geometry_msgs/msg/PoseStamped" and message.header.frame_id == "map"
        p = message.pose.position
        np.testing.assert_allclose([p.x, p.y, p.z], pose[:3, 3], atol=1e-9)
    rerun_chunk = pytest.importorskip("rerun.chunk")
    entities = {chunk.entity_path for chunk in rerun_chunk.RrdReader(rrd).stream().to_chunks()}
    assert {"/world/map/instances", "/world/trajectory/estimate"} <= entities, sorted(entities)


def test_odometry_from_tf_and_from_another_frame_through_tf_static(scans, tmp_path):
    """``/tf`` (odom -> base_link, base_link -> velodyne static) and an Odometry of base_link
    with ``/tf_static`` both give ``T_odom_velodyne``; between samples the pose is interpolated
    (exact for constant speed and yaw rate); ground truth from a pose topic, a scan outside it
    without a pose."""
    tf_bag = write_drive(tmp_path / "tf.mcap", "bare-mcap", scans, STAMPS, odometry="tf")
    for named in (None, "/tf"):
        found = open_lidar_recording(tf_bag, odometry_topic=named)
        assert found.bag.odometry_topic == "/tf"
        np.testing.assert_allclose(found.odometry, scans.T_map_scan, atol=1e-9)

    def motion(t):
        pose = np.eye(4)
        pose[:3, :3] = Rotation.from_euler("z", 0.3 * t).as_matrix()
        pose[:3, 3] = [5.0 * t, 1.0 * t, 0.1]
        return pose

    seconds = (np.asarray(STAMPS) - FIRST) * 1e-9
    lever = np.eye(4)
    lever[:3, 3] = [0.5, 0.0, 1.2]
    half = [FIRST - 50_000_000 + 100_000_000 * i for i in range(8)]  # between the scans
    with BagWriter(tmp_path / "odom.mcap", "bare-mcap") as bag:
        bag.tf("/tf_static", FIRST, [("base_link", "velodyne", lever)])
        for stamp, points, raw in zip(STAMPS, scans.points, scans.raw_labels, strict=True):
            bag.cloud("/points", stamp, packed_records(points, raw))
        for stamp in half:
            bag.odometry("/odom", stamp, motion((stamp - FIRST) * 1e-9), child="base_link")
        for stamp, t in zip(STAMPS[1:], seconds[1:], strict=True):
            bag.pose_stamped("/gt", stamp, motion(t) @ lever)
    recording = open_lidar_recording(tmp_path / "odom.mcap", gt_topic="/gt")
    expected = np.stack([motion(t) @ lever for t in seconds])
    np.testing.assert_allclose(recording.odometry, expected, atol=1e-9)
    np.testing.assert_array_equal(recording.has_pose, [False, True, True, True, True, True])
    np.testing.assert_allclose(recording.poses[1:], expected[1:], atol=1e-9)
    assert open_lidar_recording(tmp_path / "odom.mcap", odometry_topic="none").odometry is None


def test_label_fields_of_every_layout(scans, tmp_path):
    """uint16 ``label`` (ids only), named class and instance fields, an int32 packed label,
    float64 coordinates; a cloud not marked dense loses its NaN points."""
    points, raw = scans.points[0].astype(np.float64), scans.raw_labels[0]
    expected = open_lidar_recording(write_drive(tmp_path / "a.mcap", "bare-mcap", scans, STAMPS))
    reference = expected.scan(0)
    layouts = {
        "uint16": [("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("label", "<u2")],
        "named": [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("cls", "<u2"), ("obj", "<u4")],
        "int32": [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("label", "<i4")],
    }
    options = {"named": {"label_field": "cls", "instance_field": "obj"}}
    for name, fields in layouts.items():
        records = np.zeros(len(points) + 1, fields)
        for axis, coordinate in zip("xyz", points.T, strict=True):
            records[axis][:-1] = coordinate
        records["x"][-1] = np.nan  # no return
        ids, instances = raw & 0xFFFF, raw >> 16
        if name == "uint16":
            records["label"][:-1] = ids
        elif name == "named":
            records["cls"][:-1], records["obj"][:-1] = ids, instances
        else:
            records["label"][:-1] = raw.view(np.int32)
        with BagWriter(tmp_path / f"{name}.mcap", "bare-mcap") as bag:
            bag.cloud("/points", FIRST, records, dense=False)
        scan = open_lidar_recording(tmp_path / f"{name}.mcap", **options.get(name, {})).scan(0)
        np.testing.assert_array_equal(scan.points, reference.points, name)
        np.testing.assert_array_equal(scan.labels, reference.labels, name)
        want = np.zeros_like(instances) if name == "uint16" else instances
        np.testing.assert_array_equal(scan.instance_ids, want, name)


# ----------------------------------------------------------------------------- bad bags


def _cloud_bag(path: Path, clouds, kind: str = "bare-mcap", odometry=()) -> Path:
    """A bag of ``(topic, stamp, records[, options of BagWriter.cloud])`` clouds and
    ``(topic, stamp)`` identity odometry."""
    with BagWriter(path, kind) as bag:
        for topic, stamp, records, *options in clouds:
            bag.cloud(topic, stamp, records, **(options[0] if options else {}))
        for topic, stamp in odometry:
            bag.odometry(topic, stamp, np.eye(4))
    return path


def test_bad_bags_raise_one_line_naming_the_bag_and_topic(scans, tmp_path):
    good = packed_records(scans.points[0], scans.raw_labels[0])
    unlabelled = np.zeros(3, [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4")])
    unknown_id = good.copy()
    unknown_id["label"][5] = 300
    far = good.copy()
    far["x"][7] = 3.7e19
    cases = {
        "no cloud": ([], [("/odom", FIRST)], {}, ["no sensor_msgs/PointCloud2 topic", "/odom"]),
        "no label": (
            [("/points", FIRST, unlabelled)], [], {},
            ["/points[0]: no label field 'label'", "x, y, z, intensity", "label_field="],
        ),
        "two topics": (
            [("/a", FIRST, good), ("/b", FIRST, good)], [], {},
            ["2 PointCloud2 topics ['/a', '/b']", "topic="],
        ),
        "absent topic": ([("/a", FIRST, good)], [], {"topic": "/b"}, ["no topic '/b'", "['/a']"]),
        "repeated stamp": (
            [("/points", FIRST, good), ("/points", FIRST, good, {"log_time": FIRST + 1})], [], {},
            ["/points[1]: stamp", "is not after the previous cloud's"],
        ),
        "decreasing stamp": (
            [("/points", FIRST, good), ("/points", FIRST - 1, good, {"log_time": FIRST + 1})],
            [], {},
            ["/points[1]: stamp", "the stamps must increase"],
        ),
        "unknown encoding": (
            [("/points", FIRST, good, {"datatypes": {"label": 9}})], [], {},
            ["/points[0]: field 'label' has unknown datatype 9"],
        ),
        "odometry not covering": (
            [("/points", FIRST, good), ("/points", FIRST + 10**8, good)],
            [("/odom", FIRST + 5 * 10**7), ("/odom", FIRST + 2 * 10**8)], {},
            ["odometry /odom", "does not cover scan 0 of /points", "odometry_topic='none'"],
        ),
        "two odometry topics": (
            [("/points", FIRST, good)], [("/odom", FIRST), ("/odom2", FIRST)], {},
            ["2 odometry topics ['/odom', '/odom2']", "odometry_topic="],
        ),
        "gt and gt_topic": ([("/points", FIRST, good)], [], {"gt": "x", "gt_topic": "/g"},
                            ["give gt= or gt_topic="]),
        "layout with a bag": ([("/points", FIRST, good)], [], {"layout": "plain"},
                              ["layout='plain' applies to sequence folders"]),
    }  # fmt: skip
    for name, (clouds, odometry, options, parts) in cases.items():
        path = _cloud_bag(tmp_path / f"{name.replace(' ', '_')}.mcap", clouds, odometry=odometry)
        one_line_error(lambda p=path, o=options: open_lidar_recording(p, **o), str(path), *parts)
    # what only reading a cloud finds names the scan
    for name, records, part in (
        ("unknown id", unknown_id, "label id 300 is not in SemanticKITTI's learning map"),
        ("far", far, "beyond 1000 m of the sensor"),
    ):
        path = _cloud_bag(tmp_path / f"{name}.mcap", [("/points", FIRST, records)])
        recording = open_lidar_recording(path)
        one_line_error(lambda r=recording: r.instances(0), f"{path}:/points[0]: ", part)
    chosen = open_lidar_recording(tmp_path / "two_topics.mcap", topic="/b")
    assert chosen.bag.topic == "/b" and len(chosen) == 1
    with BagWriter(tmp_path / "frames.mcap", "bare-mcap") as bag:
        bag.cloud("/points", FIRST, good)
        bag.odometry("/odom", FIRST, np.eye(4), child="base_link")
    one_line_error(
        lambda: open_lidar_recording(tmp_path / "frames.mcap"),
        "frames.mcap: /odom: poses of frame 'base_link', clouds in 'velodyne'",
    )
    one_line_error(
        lambda: open_lidar_recording([tmp_path / "far.mcap", tmp_path / "far.mcap"]),
        "far.mcap: a bag is read alone",
    )


@pytest.mark.parametrize("kind", KINDS)
def test_a_truncated_bag_is_one_line_naming_it(scans, tmp_path, kind):
    path = write_drive(bag_path(tmp_path, kind), kind, scans, STAMPS)
    storage = next(path.glob("*.*3")) if kind == "sqlite3" else path
    if kind == "mcap":
        storage = path / "mcap.mcap"
    storage.write_bytes(storage.read_bytes()[: storage.stat().st_size // 2])
    one_line_error(lambda: open_lidar_recording(path), str(path), "not a readable bag")


@settings(max_examples=20, deadline=None, suppress_health_check=list(HealthCheck))
@given(
    kind=st.sampled_from(["ros1", "sqlite3", "bare-mcap"]),
    at=st.floats(0, 1),
    flips=st.lists(st.tuples(st.floats(0, 1), st.integers(1, 255)), min_size=1, max_size=4),
)
def test_damaged_bags_fail_with_a_value_error_naming_the_bag(scans, written, kind, at, flips):
    """Flipped bytes and a cut anywhere in a bag: opening it and reading every scan either works
    or raises ValueError naming the bag, never another exception."""
    source = written[kind]
    storage = source / "sqlite3.db3" if kind == "sqlite3" else source
    data = bytearray(storage.read_bytes())
    for where, mask in flips:
        data[int(where * (len(data) - 1))] ^= mask
    if at < 0.5:  # cut half of the examples
        del data[max(int(2 * at * len(data)), 1) :]
    root = source.parent.parent / f"fuzz-{kind}"
    shutil.rmtree(root, ignore_errors=True)
    shutil.copytree(source.parent, root)
    damaged = root / source.name
    (damaged / storage.name if kind == "sqlite3" else damaged).write_bytes(bytes(data))
    try:
        recording = open_lidar_recording(damaged)
        for index in range(len(recording)):
            recording.scan(index)
        recording.bag.close()
    except ValueError as error:
        assert str(damaged) in str(error), str(error)


# ----------------------------------------------------------------------------- poses out


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_pose_bag_folders_and_their_refusals(tmp_path, storage):
    """A ROS 2 bag folder of either storage reads back with rosbags; an existing folder, repeated
    stamps, a non-rigid valid pose and shapes that disagree write nothing."""
    from rosbags.highlevel import AnyReader

    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[:, 0, 3] = [1.0, 2.0, 3.0]
    stamps, valid = np.array(STAMPS[:3]), np.array([True, False, True])
    folder = tmp_path / "out"
    assert write_pose_bag(folder, stamps, poses, valid, storage=storage) == 2
    assert (folder / "metadata.yaml").is_file()
    with AnyReader([folder]) as reader:
        assert {t: i.msgtype for t, i in reader.topics.items()} == {
            "/jaxloc/pose": "geometry_msgs/msg/PoseStamped",
            "/jaxloc/valid": "std_msgs/msg/Bool",
        }
        xs = [
            reader.deserialize(raw, c.msgtype).pose.position.x
            for c, _, raw in reader.messages()
            if c.topic == "/jaxloc/pose"
        ]
    assert xs == [1.0, 3.0]
    sheared = poses.copy()
    sheared[0, 0, 1] = 0.5
    for args, part in (
        ((folder, stamps, poses, valid), "exists; a bag folder is written new"),
        ((tmp_path / "r.mcap", stamps[[0, 0, 1]], poses, valid), "two inputs share a stamp"),
        (
            (tmp_path / "s.mcap", stamps, sheared, valid),
            "the pose of input 0 is valid but not a finite rigid",
        ),
        ((tmp_path / "n.mcap", stamps[:2], poses, valid), "need (N,) integer stamps"),
    ):
        one_line_error(lambda a=args: write_pose_bag(*a), str(args[0]), part)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_write_lidar_poses_picks_the_format_by_the_path(written, tmp_path):
    recording = open_lidar_recording(written["folder"])
    poses, valid = np.tile(np.eye(4), (6, 1, 1)), np.ones(6, bool)
    write_lidar_poses(tmp_path / "a.mcap", recording, poses, valid)
    assert (tmp_path / "a.mcap").read_bytes()[:5] == b"\x89MCAP"
    write_lidar_poses(tmp_path / "bag", recording, poses, valid, "rosbag2")
    assert (tmp_path / "bag" / "metadata.yaml").is_file()
    write_lidar_poses(tmp_path / "c.mcap", recording, poses, valid, "tum")  # the default
    assert (tmp_path / "c.mcap").read_bytes() == (tmp_path / "a.mcap").read_bytes()
    for name, format in (("b.mcap", "kitti"), ("b.tum", "mcap"), ("b.mcap", "rosbag2")):
        one_line_error(
            lambda n=name, f=format: write_lidar_poses(tmp_path / n, recording, poses, valid, f),
            f"{name}: format {format!r} does not fit the name",
        )
    shutil.rmtree(tmp_path / "bag")


# ----------------------------------------------------------------------------- a real map

REAL_MAPS = Path(__file__).resolve().parents[2] / "shared" / "data" / "helipr_instance_maps"


def _clouds_of(scans) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Each scan's instance centroids as labelled clouds: a 2 m vertical stack of rings (radius
    0.1 m, every 5 cm) centred on each centroid, raw SemanticKITTI ids with instance k + 1 in the
    high 16 bits, so TripletLoc's clustering gives the centroids back."""
    from jaxloc.synthetic.lidar_scans import _RAW

    heights = np.arange(-1.0, 1.0 + 1e-9, 0.05)
    ring = 0.1 * np.stack([np.cos(a := np.linspace(0, 2 * np.pi, 6, endpoint=False)), np.sin(a)])
    offsets = np.array([[*ring[:, j], h] for h in heights for j in range(ring.shape[1])])
    clouds, raws = [], []
    for scan in scans:
        points = np.concatenate([c + offsets for c in scan.points]).astype(np.float32)
        raw = np.concatenate(
            [np.full(len(offsets), _RAW[int(c)] | ((k + 1) << 16), np.uint32)
             for k, c in enumerate(scan.labels)]
        )  # fmt: skip
        clouds.append(points)
        raws.append(raw)
    return clouds, raws


@pytest.mark.slow
@pytest.mark.skipif(not REAL_MAPS.exists(), reason="needs ../shared/data/helipr_instance_maps")
def test_a_drive_on_a_real_map_from_bags_is_the_folder_s_drive(tmp_path):
    """A drive simulated on KAIST04 (noisy odometry), written as a SemanticKITTI folder and as a
    ROS 2 MCAP bag and a ROS 1 bag (``PointCloud2`` with a uint32 ``label`` field,
    ``nav_msgs/Odometry``): ``localize-lidar MAP BAG --accumulate 3 --gt F`` gives the folder's
    flags and poses (within 1e-3 m), and ``--poses-out est.mcap`` holds one PoseStamped per valid
    estimate."""
    from types import SimpleNamespace

    from rosbags.highlevel import AnyReader

    from jaxloc.io import open_triplet_map, read_instance_map, read_road_normals
    from jaxloc.synthetic.outdoor import make_drive

    folder = REAL_MAPS / "KAIST04"
    instances, normals = read_instance_map(folder), read_road_normals(folder)
    rng = np.random.default_rng(7000)
    drive = make_drive(instances.points, instances.labels, normals, rng, 6, max_kept=11)
    truth = np.stack([s.T_map_scan for s in drive])
    noise = np.eye(4)
    noise[:3, 3] = [0.05, -0.04, 0.01]
    chain = [truth[0]]
    for a, b in zip(truth, truth[1:], strict=False):
        chain.append(chain[-1] @ np.linalg.inv(a) @ b @ noise)
    chain = np.stack(chain)
    clouds, raws = _clouds_of(drive)
    scans = SimpleNamespace(points=clouds, raw_labels=raws, T_map_scan=truth)
    saved = tmp_path / "kaist04.npz"
    save_triplet_map(open_triplet_map(folder), saved)
    write_kitti_twin(tmp_path / "folder", scans, truth)
    odometry = tmp_path / "odometry.txt"
    np.savetxt(odometry, chain[:, :3].reshape(-1, 12), fmt="%.17g")
    gt = tmp_path / "gt.tum"
    lines = [tum_line(format_ns_as_seconds(t), p) for t, p in zip(STAMPS, truth, strict=True)]
    gt.write_text("\n".join(lines) + "\n")
    common = ["--accumulate", "3", "--json", "--no-progress"]
    expected = cli_json(["localize-lidar", saved, tmp_path / "folder", "--odometry", odometry,
                         *common])  # fmt: skip
    assert sum(r["valid"] for r in expected) >= 3, expected
    for kind in ("mcap", "ros1"):
        (tmp_path / kind).mkdir()
        bag = write_drive(bag_path(tmp_path / kind, kind), kind, scans, STAMPS,
                          odometry_poses=chain)  # fmt: skip
        out = tmp_path / f"{kind}.mcap"
        got = cli_json(["localize-lidar", saved, bag, "--gt", gt, "--poses-out", out, *common])
        assert [r["valid"] for r in got] == [r["valid"] for r in expected]
        for mine, theirs in zip(got, expected, strict=True):
            if theirs["valid"]:
                np.testing.assert_allclose(
                    np.asarray(mine["T_map_scan"])[:3, 3],
                    np.asarray(theirs["T_map_scan"])[:3, 3],
                    atol=1e-3,
                )
                np.testing.assert_allclose(
                    np.asarray(mine["T_map_scan"])[:3, :3],
                    np.asarray(theirs["T_map_scan"])[:3, :3],
                    atol=1e-5,
                )
        with AnyReader([out]) as reader:
            poses = [c for c in reader.connections if c.topic == "/jaxloc/pose"]
            assert poses and poses[0].msgtype == "geometry_msgs/msg/PoseStamped"
            count = sum(1 for _ in reader.messages(connections=poses))
        assert count == sum(r["valid"] for r in got)
