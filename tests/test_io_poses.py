"""Pose files in and out: KITTI (12 numbers a line), 4x4 rows (16) and TUM (8), read against
numpy / scipy references, written so that evo's own readers load them, timestamps exact to the
nanosecond; and sequences whose poses are matched to the scans by time."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jaxloc.io import read_pose_file, write_kitti, write_tum
from jaxloc.io.lidar_sequence import open_lidar_sequence
from jaxloc.io.poses import format_ns_as_seconds, match_timestamps, read_poses, seconds_to_ns


def random_poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = Rotation.random(n, random_state=seed).as_matrix()
    poses[:, :3, 3] = rng.uniform(-500, 500, (n, 3))
    return poses


def tum_text(stamps: list[str], poses: np.ndarray) -> str:
    """TUM lines formatted here with numpy/scipy only (x y z w quaternions, %.17g)."""
    quats = Rotation.from_matrix(poses[:, :3, :3]).as_quat()
    rows = [
        " ".join([stamp, *(f"{v:.17g}" for v in pose[:3, 3]), *(f"{v:.17g}" for v in q)])
        for stamp, pose, q in zip(stamps, poses, quats, strict=True)
    ]
    return "\n".join(rows) + "\n"


# ----------------------------------------------------------------------------- reading


def test_kitti_and_4x4_rows_against_numpy(tmp_path):
    poses = random_poses(5)
    np.savetxt(tmp_path / "kitti.txt", poses[:, :3].reshape(5, 12), fmt="%.17g")
    np.savetxt(tmp_path / "rows.txt", poses.reshape(5, 16), fmt="%.17g")
    for name, expected in (("kitti.txt", "kitti"), ("rows.txt", "4x4")):
        found = read_pose_file(tmp_path / name)
        assert found.format == expected and found.timestamps is None and found.time_unit is None
        np.testing.assert_array_equal(found.poses, poses)  # %.17g round-trips float64
    np.testing.assert_array_equal(read_poses(tmp_path / "kitti.txt"), poses)


def test_tum_quaternions_against_scipy_and_by_hand(tmp_path):
    poses = random_poses(6, seed=1)
    stamps = ["1691936557.946849179", "0.5", "1e-3", "12", "-0.25", "1317384506.40"]
    path = tmp_path / "traj.tum"
    path.write_text("# timestamp tx ty tz qx qy qz qw\n" + tum_text(stamps, poses))
    found = read_pose_file(path)
    assert found.format == "tum" and found.time_unit == "s"
    np.testing.assert_allclose(found.poses, poses, atol=1e-12)
    expected = [
        1691936557946849179,
        500000000,
        1000000,
        12 * 10**9,
        -250000000,
        1317384506400000000,
    ]
    np.testing.assert_array_equal(found.timestamps, expected)  # exact, not via float64
    # a yaw of +90 deg about z, by hand: q = (0, 0, sin 45, cos 45), x y z w
    half = float(np.sqrt(0.5))
    path.write_text(f"0 1 2 3 0 0 {half!r} {half!r}\n")
    yaw = read_pose_file(path).poses[0]
    np.testing.assert_allclose(yaw[:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-15)
    np.testing.assert_array_equal(yaw[:3, 3], [1, 2, 3])


def test_nanosecond_stamps_are_told_from_seconds(tmp_path):
    """HeLiPR's ns stamps (integers >= 1e15) are nanoseconds; small integers (scan numbers)
    are seconds; ``time_unit`` forces either."""
    path = tmp_path / "gt.txt"
    path.write_text("1691936557946849179 0 0 0 0 0 0 1\n1691936558046849179 1 0 0 0 0 0 1\n")
    found = read_pose_file(path)
    assert found.time_unit == "ns" and found.match_tolerance_ns() == 0
    np.testing.assert_array_equal(found.timestamps, [1691936557946849179, 1691936558046849179])
    path.write_text("0 0 0 0 0 0 0 1\n1 1 0 0 0 0 0 1\n")
    found = read_pose_file(path)
    assert found.time_unit == "s" and found.match_tolerance_ns() == 1_000_000
    np.testing.assert_array_equal(found.timestamps, [0, 10**9])
    np.testing.assert_array_equal(read_pose_file(path, time_unit="ns").timestamps, [0, 1])


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("1 2 3 4 5 6 7\n", r"p\.txt:1: expected 12 \(KITTI 3x4\), 16 \(4x4\) or 8 \(TUM"),
        (
            "0 0 0 0 0 0 0 1\n\n1 0 0 0 0 1 0 0 0 0 1 0\n",
            r"p\.txt:3: 12 numbers where the file's first pose line has 8 \(tum\)",
        ),
        ("1 0 0 0 0 1 0 0 0 0 1 nan\n", r"p\.txt:1: pose has NaN or inf"),
        ("1 0 0 0 0 1 0 0 0 0 1 inf\n", r"p\.txt:1: pose has NaN or inf"),
        ("1 0 0 0 0 1 0 0 0 0 1 x\n", r"p\.txt:1: pose has a non-numeric value"),
        ("nan 0 0 0 0 0 0 1\n", r"p\.txt:1: timestamp is NaN or inf"),
        ("1e30 0 0 0 0 0 0 1\n", r"p\.txt:1: timestamp '1e30' s is out of range"),
        ("0 0 0 0 0 0 0 2\n", r"p\.txt:1: quaternion \(qx qy qz qw\) has norm 2, not 1"),
        ("0 0 0 0 0 0 0 0\n", r"p\.txt:1: quaternion \(qx qy qz qw\) has norm 0, not 1"),
        ("2 0 0 0 0 1 0 0 0 0 1 0\n", r"p\.txt: pose 1 is not rigid"),
        ("# only a comment\n\n", r"p\.txt: no pose \(an empty file\)"),
    ],
)
def test_malformed_pose_files_name_file_and_line(tmp_path, text, message):
    path = tmp_path / "p.txt"
    path.write_text(text)
    with pytest.raises(ValueError, match=message):
        read_pose_file(path)


def test_binary_and_missing_files(tmp_path):
    path = tmp_path / "p.txt"
    path.write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(ValueError, match=r"p\.txt: not a UTF-8 text file"):
        read_pose_file(path)
    with pytest.raises(FileNotFoundError):
        read_pose_file(tmp_path / "absent.txt")


# ----------------------------------------------------------------------------- writing


def test_round_trips_are_exact(tmp_path):
    poses = random_poses(7, seed=2)
    stamps = np.array([1691936557946849179 + 100_000_007 * i for i in range(7)], np.int64)
    write_tum(tmp_path / "a.tum", poses, stamps)
    back = read_pose_file(tmp_path / "a.tum")
    np.testing.assert_array_equal(back.timestamps, stamps)
    np.testing.assert_array_equal(back.poses[:, :3, 3], poses[:, :3, 3])  # repr round-trips
    np.testing.assert_allclose(back.poses, poses, atol=1e-15)  # through the quaternion
    write_kitti(tmp_path / "a.kitti", poses)
    np.testing.assert_array_equal(read_pose_file(tmp_path / "a.kitti").poses, poses)
    seconds = np.array([0.1, 1e-7, 1317384506.4027], np.float64)
    write_tum(tmp_path / "b.tum", poses[:3], seconds)
    fields = [line.split(" ")[0] for line in (tmp_path / "b.tum").read_text().splitlines()]
    assert [float(f) for f in fields] == seconds.tolist()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.kitti", "a.tum", "b.tum"]


def test_written_files_are_what_evo_reads(tmp_path):
    """evo splits on exactly one space (csv.reader), so: single spaces, no trailing space; its
    TUM reader rolls x y z w to w x y z."""
    from evo.tools.file_interface import read_kitti_poses_file, read_tum_trajectory_file

    poses = random_poses(4, seed=3)
    stamps = np.array([1691936557946849179, 1691936558046849179, 3, 4 * 10**9], np.int64)
    write_tum(tmp_path / "t.tum", poses, stamps)
    write_kitti(tmp_path / "k.txt", poses)
    for name, fields in (("t.tum", 8), ("k.txt", 12)):
        text = (tmp_path / name).read_text()
        assert text.endswith("\n") and "  " not in text and " \n" not in text
        assert {len(line.split(" ")) for line in text.splitlines()} == {fields}
    trajectory = read_tum_trajectory_file(str(tmp_path / "t.tum"))
    np.testing.assert_array_equal(trajectory.positions_xyz, poses[:, :3, 3])
    np.testing.assert_allclose(trajectory.poses_se3, poses, atol=1e-15)
    np.testing.assert_allclose(trajectory.timestamps, stamps / 1e9, rtol=1e-15, atol=0)
    assert np.all(trajectory.orientations_quat_wxyz[:, 0] >= 0)  # qw >= 0 written
    lines = (tmp_path / "t.tum").read_text().splitlines()
    assert lines[0].startswith("1691936557.946849179 ") and lines[2].startswith("0.000000003 ")
    kitti = read_kitti_poses_file(str(tmp_path / "k.txt"))
    np.testing.assert_array_equal(np.asarray(kitti.poses_se3), poses)


def test_writers_refuse_bad_poses(tmp_path):
    scaled = 2 * np.eye(4)[None]
    scaled[0, 3, 3] = 1
    with pytest.raises(ValueError, match=r"x\.tum: pose 1 is not rigid"):
        write_tum(tmp_path / "x.tum", scaled, np.array([0], np.int64))
    with pytest.raises(ValueError, match="timestamps for 1 poses"):
        write_tum(tmp_path / "x.tum", np.eye(4)[None], np.array([0, 1], np.int64))
    with pytest.raises(ValueError, match="shape"):
        write_kitti(tmp_path / "x.txt", np.eye(4))
    with pytest.raises(ValueError, match="NaN or inf"):
        write_kitti(tmp_path / "x.txt", np.full((1, 4, 4), np.nan))
    assert not any(tmp_path.iterdir())


def test_nanoseconds_and_seconds_text():
    assert format_ns_as_seconds(1691936557946849179) == "1691936557.946849179"
    assert format_ns_as_seconds(-1) == "-0.000000001"
    assert format_ns_as_seconds(-1_500_000_000) == "-1.500000000"
    assert seconds_to_ns("-1.5", "x") == -1_500_000_000
    assert seconds_to_ns("1691936557.9468491795", "x") == 1691936557946849180  # half to even
    with pytest.raises(ValueError, match="x: timestamp 'abc' is not a number"):
        seconds_to_ns("abc", "x")


def test_match_timestamps():
    available = np.array([300, 100, 200], np.int64)
    np.testing.assert_array_equal(match_timestamps(np.array([100, 200, 250, 301]), available),
                                  [1, 2, -1, -1])  # fmt: skip
    np.testing.assert_array_equal(
        match_timestamps(np.array([150, 249, 301, 1000]), available, tolerance_ns=50),
        [1, 2, 0, -1],  # a tie (150) goes to the earlier stamp
    )
    extreme = np.array([np.iinfo(np.int64).min], np.int64)  # no int64 overflow
    np.testing.assert_array_equal(match_timestamps(extreme, np.array([2**62])), [-1])
    np.testing.assert_array_equal(match_timestamps(np.array([1]), np.array([], np.int64)), [-1])


# ----------------------------------------------------------------------------- sequences


def _plain_sequence(root, count: int) -> None:
    (root / "velodyne").mkdir(parents=True)
    (root / "labels").mkdir()
    for i in range(count):
        np.arange(8, dtype="<f4").tofile(root / "velodyne" / f"{i:06d}.bin")
        np.zeros(2, "<u4").tofile(root / "labels" / f"{i:06d}.label")


def test_times_txt_and_tum_poses_match_scans_by_time(tmp_path):
    """A plain sequence with KITTI's times.txt and a TUM poses.txt (seconds, 6 decimals): poses
    match within 1 ms; the scan without one is left out, the extra pose is ignored."""
    _plain_sequence(tmp_path, 4)
    (tmp_path / "times.txt").write_text("0.000000e+00\n1.037359e-01\n2.073880e-01\n3.110400e-01\n")
    poses = random_poses(4, seed=4)
    text = tum_text(["0.000000", "0.103736", "0.311040", "9.000000"], poses)
    (tmp_path / "poses.txt").write_text(text)
    sequence = open_lidar_sequence(tmp_path)
    assert sequence.layout == "plain"
    np.testing.assert_array_equal(sequence.timestamps, [0, 103735900, 311040000])
    np.testing.assert_allclose(sequence.T_map_scan, poses[:3], atol=1e-12)
    assert [p.name for p in sequence.skipped] == ["000002.bin"] and sequence.unused_poses == 1
    (tmp_path / "times.txt").write_text("0\n0.1\n")
    with pytest.raises(ValueError, match=r"times\.txt: 2 times for 4 scans"):
        open_lidar_sequence(tmp_path)
    (tmp_path / "times.txt").write_text("0\n0.1 2\n0.2\n0.3\n")
    with pytest.raises(ValueError, match=r"times\.txt:2: expected one time"):
        open_lidar_sequence(tmp_path)


def test_tum_poses_without_scan_times_go_by_order(tmp_path):
    _plain_sequence(tmp_path, 3)
    poses = random_poses(3, seed=5)
    (tmp_path / "poses.txt").write_text(tum_text(["5", "6", "7"], poses))
    sequence = open_lidar_sequence(tmp_path)
    assert sequence.timestamps is None
    np.testing.assert_allclose(sequence.T_map_scan, poses, atol=1e-12)
    (tmp_path / "poses.txt").write_text(tum_text(["5", "6"], poses[:2]))
    with pytest.raises(ValueError, match=r"poses\.txt: 2 poses for 3 scans"):
        open_lidar_sequence(tmp_path)
