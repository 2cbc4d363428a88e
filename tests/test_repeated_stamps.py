"""Repeated and out-of-order stamps, two files of one number, keys given twice in a user's
recording: each is a ``ValueError`` naming the file(s) at the reader, never one of two silently
kept.

Every recording is written here byte by byte in its real format (TUM / KITTI text, SemanticKITTI
and HeLiPR scans, a ScanNet export, a 3RScan sequence, a version-4 ``.sens``), a few tiny frames
each, so nothing is rendered or compiled.
"""

from __future__ import annotations

import io
import json
import re
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from jaxloc.io.camera_recording import write_camera_poses
from jaxloc.io.camera_sequence import read_camera_sequence, read_odometry
from jaxloc.io.lidar_recording import open_lidar_recording
from jaxloc.io.lidar_sequence import open_lidar_sequence, read_kitti_calibration
from jaxloc.io.poses import read_pose_file, seconds_to_ns, write_tum
from jaxloc.io.rscan_sequence import open_rscan_sequence, read_rescan_transform
from jaxloc.io.scannet_export import open_scannet_export
from jaxloc.io.scannet_sens import open_sens

#: TUM line tail of the identity pose: ``x y z qx qy qz qw``.
IDENTITY = "0 0 0 0 0 0 1"
#: A HeLiPR-like stamp (ns).
STAMP = 1_691_936_557_000_000_000
#: Size of the test images (W, H) and their pinhole intrinsics.
WIDTH, HEIGHT = 16, 12
K = np.array([[10.0, 0, 7.5, 0], [0, 10.0, 5.5, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
#: The camera-to-world rotation of a camera looking along +x with z up (OpenCV axes).
R_WORLD_CAM = np.array([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]])
#: ``read_camera_sequence`` without images in the query (the frames are still decoded).
NO_IMAGES = {"use_rgb": False, "use_depth": False}


def camera_pose(x: float) -> np.ndarray:
    """A camera-to-world pose at ``(x, 0, 0)``."""
    pose = np.eye(4)
    pose[:3, :3], pose[0, 3] = R_WORLD_CAM, x
    return pose


def matrix_text(matrix: np.ndarray) -> str:
    """A 4x4 matrix as four text rows (ScanNet's pose and intrinsic files)."""
    return "".join(" ".join(repr(float(v)) for v in row) + "\n" for row in np.asarray(matrix))


def jpeg_bytes(grey: int = 100) -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(np.full((HEIGHT, WIDTH, 3), grey, np.uint8)).save(buffer, "JPEG")
    return buffer.getvalue()


def write_embeddings(folder: Path, numbers) -> None:
    """One (rows, cols, d) patch-embedding file ``embeddings/N.npy`` per frame number."""
    (folder / "embeddings").mkdir(parents=True, exist_ok=True)
    for number in numbers:
        np.save(folder / "embeddings" / f"{number}.npy", np.eye(5)[np.zeros((3, 4), int)])


# ---------------------------------------------------------------------------- pose files, times


def test_seconds_to_ns_is_exact_beyond_28_digits():
    """33 significant digits: the default 28-digit Decimal context rounded the product to
    ...179.5 and then to ...180; the exact value is ...179.4999... ns."""
    text = "1691936557.94684917949999999999999"
    assert seconds_to_ns(text, "t") == 1691936557946849179
    assert seconds_to_ns("1691936557.9468491795", "t") == 1691936557946849180  # half to even
    assert seconds_to_ns("1691936557.9468491785", "t") == 1691936557946849178
    assert seconds_to_ns("-0." + "0" * 9 + "5" + "0" * 40 + "1", "t") == -1


def test_tum_pose_file_with_a_repeated_stamp_is_refused_naming_both_lines(tmp_path):
    path = tmp_path / "poses.txt"
    path.write_text(f"1.0 {IDENTITY}\n1.0 5 5 5 0 0 0 1\n2.0 {IDENTITY}\n")
    with pytest.raises(ValueError, match=r"poses\.txt:2: stamp 1\.0 appears more than once "):
        read_pose_file(path)
    # one time written two ways
    path.write_text(f"# t x y z qx qy qz qw\n1.5 {IDENTITY}\n\n1.500000000 {IDENTITY}\n")
    with pytest.raises(ValueError, match=r"poses\.txt:4: .*\(line 2 has the same time\)"):
        read_pose_file(path)
    # integer nanoseconds (HeLiPR's GT)
    path.write_text(f"{STAMP} {IDENTITY}\n{STAMP + 1} {IDENTITY}\n{STAMP} {IDENTITY}\n")
    with pytest.raises(ValueError, match=rf"poses\.txt:3: stamp {STAMP} appears more than once"):
        read_pose_file(path)
    path.write_text(f"2.0 {IDENTITY}\n1.0 {IDENTITY}\n")  # out of order but distinct: matched
    np.testing.assert_array_equal(read_pose_file(path).timestamps, [2 * 10**9, 10**9])


def write_plain_sequence(root: Path, names=("000000", "000001", "000002")) -> Path:
    """A SemanticKITTI-layout sequence without calib.txt: ``velodyne/N.bin`` (two float32
    x y z intensity points) and ``labels/N.label`` (uint32 raw ids, 40 = road)."""
    (root / "velodyne").mkdir(parents=True)
    (root / "labels").mkdir()
    for name in names:
        np.zeros((2, 4), "<f4").tofile(root / "velodyne" / f"{name}.bin")
        np.full(2, 40, "<u4").tofile(root / "labels" / f"{name}.label")
    return root


def test_repeated_tum_stamps_are_refused_by_lidar_sequences_and_recordings(tmp_path):
    """TUM poses matched to times.txt, and ``gt=`` of a recording: a stamp on two lines is an
    error naming the pose file (one of the two poses was silently used)."""
    root = write_plain_sequence(tmp_path / "seq")
    (root / "times.txt").write_text("0.0\n0.1\n0.2\n")
    poses = root / "poses.txt"
    poses.write_text(f"0.0 {IDENTITY}\n0.1 1 0 0 0 0 0 1\n0.1 9 0 0 0 0 0 1\n0.2 {IDENTITY}\n")
    with pytest.raises(ValueError, match=r"poses\.txt:3: stamp 0\.1 appears more than once"):
        open_lidar_sequence(root)
    poses.unlink()
    gt = tmp_path / "gt.txt"
    gt.write_text(f"0.0 {IDENTITY}\n0.0 7 0 0 0 0 0 1\n0.2 {IDENTITY}\n")
    with pytest.raises(ValueError, match=r"gt\.txt:2: stamp 0\.0 appears more than once"):
        open_lidar_recording(root, gt=gt)


@pytest.mark.parametrize(
    "times, line, message",
    [
        ("0.0\n0.0\n0.2\n", 2, r"time 0\.0 s is not after line 1's \(0\.0 s\)"),
        ("0.2\n0.1\n0.0\n", 2, r"time 0\.1 s is not after line 1's \(0\.2 s\)"),
        ("0.0\n0.1\n# a comment\n0.100000000\n", 4, r"time 0\.100000000 s is not after line 2"),
    ],
)
def test_times_txt_with_a_repeated_or_decreasing_time_is_refused(tmp_path, times, line, message):
    """Repeated times gave two scans one pose and dropped another; decreasing ones paired scans
    with the poses of other scans."""
    root = write_plain_sequence(tmp_path / "seq")
    (root / "times.txt").write_text(times)
    (root / "poses.txt").write_text(f"0.0 {IDENTITY}\n0.1 1 0 0 0 0 0 1\n0.2 2 0 0 0 0 0 1\n")
    with pytest.raises(ValueError, match=rf"times\.txt:{line}: {message}"):
        open_lidar_sequence(root)
    with pytest.raises(ValueError, match=rf"times\.txt:{line}: "):
        open_lidar_sequence(root, require_poses=False)


# --------------------------------------------------------------- two files of one scan number


def write_helipr_sequence(root: Path, names, gt_stamps) -> Path:
    """``LiDAR/Ouster/<name>.bin`` (two zero 26-byte Ouster records), ``labels/<name>.label``
    and ``LiDAR_GT/Ouster_gt.txt`` with an identity pose per stamp."""
    for folder in ("LiDAR/Ouster", "labels", "LiDAR_GT"):
        (root / folder).mkdir(parents=True)
    for name in names:
        (root / "LiDAR" / "Ouster" / f"{name}.bin").write_bytes(bytes(2 * 26))
        (root / "labels" / f"{name}.label").write_bytes(bytes(2 * 4))
    gt = "".join(f"{stamp} {IDENTITY}\n" for stamp in gt_stamps)
    (root / "LiDAR_GT" / "Ouster_gt.txt").write_text(gt)
    return root


def test_two_scans_named_by_one_number_or_stamp_are_refused(tmp_path):
    """``1.bin`` and ``01.bin`` (KITTI poses by order: which scan is scan 1?), and HeLiPR's
    ``0<stamp>.bin`` beside ``<stamp>.bin`` (both kept, with one stamp and one GT pose)."""
    root = write_plain_sequence(tmp_path / "plain", ("1", "01", "2"))
    (root / "poses.txt").write_text("".join(f"1 0 0 {i} 0 1 0 0 0 0 1 0\n" for i in range(3)))
    velodyne = root / "velodyne"
    message = (
        f"{velodyne / '01.bin'} and {velodyne / '1.bin'}: two scans named by the same number 1"
    )
    with pytest.raises(ValueError, match=re.escape(message)):
        open_lidar_sequence(root)
    root = write_helipr_sequence(tmp_path / "helipr", [STAMP, f"0{STAMP}", STAMP + 100], [STAMP])
    scans = root / "LiDAR" / "Ouster"
    message = f"{scans / f'0{STAMP}.bin'} and {scans / f'{STAMP}.bin'}: two scans named by the "
    message += f"same stamp {STAMP}"
    with pytest.raises(ValueError, match=re.escape(message)):
        open_lidar_sequence(root)
    with pytest.raises(ValueError, match="two scans named by the same stamp"):
        open_lidar_recording(root)


def write_export(folder: Path, names=("0", "1", "2")) -> Path:
    """A ScanNet export folder: ``color/<name>.jpg`` and ``intrinsic/intrinsic_color.txt``."""
    (folder / "color").mkdir(parents=True)
    (folder / "intrinsic").mkdir()
    (folder / "intrinsic" / "intrinsic_color.txt").write_text(matrix_text(K))
    for name in names:
        (folder / "color" / f"{name}.jpg").write_bytes(jpeg_bytes())
    return folder


def write_rscan(scan: Path, stems=("frame-000000", "frame-000001")) -> Path:
    """A 3RScan ``scan/sequence/``: ``_info.txt`` and ``<stem>.color.jpg`` per frame."""
    folder = scan / "sequence"
    folder.mkdir(parents=True)
    row = " ".join(repr(float(v)) for v in K.ravel())
    info = [
        f"m_colorWidth = {WIDTH}",
        f"m_colorHeight = {HEIGHT}",
        f"m_depthWidth = {WIDTH}",
        f"m_depthHeight = {HEIGHT}",
        "m_depthShift = 1000",
        f"m_calibrationColorIntrinsic = {row}",
        f"m_calibrationDepthIntrinsic = {row}",
    ]
    (folder / "_info.txt").write_text("\n".join(info) + "\n")
    for stem in stems:
        (folder / f"{stem}.color.jpg").write_bytes(jpeg_bytes())
    return scan


@pytest.mark.parametrize(
    "layout, extra, first, second",
    [
        ("export", "color/01.jpg", "color/01.jpg", "color/1.jpg"),
        ("export", "color/1.png", "color/1.jpg", "color/1.png"),
        (
            "3rscan",
            "sequence/frame-1.color.jpg",
            "sequence/frame-000001.color.jpg",
            "sequence/frame-1.color.jpg",
        ),
    ],
)
def test_two_camera_frame_files_of_one_number_are_refused(tmp_path, layout, extra, first, second):
    """A ScanNet export's ``1.jpg`` beside ``01.jpg`` or ``1.png``, a 3RScan ``frame-000001``
    beside ``frame-1``: one of the two was silently dropped (or both kept as frames 1 and 2)."""
    if layout == "export":
        folder, opener = write_export(tmp_path / "rec"), open_scannet_export
    else:
        folder, opener = write_rscan(tmp_path / "rec"), open_rscan_sequence
    assert opener(folder).numbers[:2] == (0, 1)
    Image.new("RGB", (WIDTH, HEIGHT)).save(folder / extra)  # JPEG or PNG, by the suffix
    message = f"{folder / first} and {folder / second}: two frame files with the same number 1"
    with pytest.raises(ValueError, match=re.escape(message)):
        opener(folder)


# ------------------------------------------------------------------------- camera odometry


def test_camera_odometry_with_repeated_tum_stamps_is_refused(tmp_path):
    path = tmp_path / "odometry.txt"
    path.write_text(f"0 {IDENTITY}\n1 1 0 0 0 0 0 1\n1 5 0 0 0 0 0 1\n2 {IDENTITY}\n")
    with pytest.raises(ValueError, match=r"odometry\.txt:3: stamp 1 appears more than once"):
        read_odometry(path, (0, 1, 2))


def test_camera_odometry_with_a_repeated_frame_number_is_refused(tmp_path):
    """``N m00 ... m33`` lines: the last of the lines of one frame number was kept."""

    def line(number: str, x: float) -> str:
        return number + " " + " ".join(repr(float(v)) for v in camera_pose(x).ravel()) + "\n"

    path = tmp_path / "odometry.txt"
    path.write_text(line("0", 0) + line("1", 1) + line("2", 2) + line("01", 7))
    with pytest.raises(ValueError, match=r"odometry\.txt:4: .*frame 1.*line 2"):
        read_odometry(path, (0, 1, 2))


def write_sens(path: Path, timestamps_us) -> Path:
    """A version-4 ``.sens`` (ScanNet's sensorData.h ``writeHeaderToFile`` /
    ``RGBDFrame::saveToFile``: little-endian, jpeg colour, zlib uint16 depth, no IMU frames) with
    one frame per timestamp, at x = 0, 1, 2 ...; embeddings beside it."""
    name = b"StructureSensor"
    parts = [struct.pack("<IQ", 4, len(name)), name]
    for matrix in (K, np.eye(4), K, np.eye(4)):
        parts.append(np.asarray(matrix, "<f4").tobytes())
    parts.append(
        struct.pack("<2i4IfQ", 2, 1, WIDTH, HEIGHT, WIDTH, HEIGHT, 1000.0, len(timestamps_us))
    )
    depth = zlib.compress(np.full((HEIGHT, WIDTH), 1500, "<u2").tobytes())
    for index, stamp in enumerate(timestamps_us):
        color = jpeg_bytes()
        parts.append(np.asarray(camera_pose(index), "<f4").tobytes())
        parts += [struct.pack("<4Q", stamp, stamp, len(color), len(depth)), color, depth]
    parts.append(struct.pack("<Q", 0))
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"".join(parts))
    write_embeddings(path.parent, range(len(timestamps_us)))
    return path


def test_sens_with_zero_timestamps_opens_without_odometry(tmp_path):
    """Real ``.sens`` files may carry zero timestamps: nothing is matched by time without an
    odometry file, so they are read as they are."""
    source = open_sens(write_sens(tmp_path / "scene.sens", [0, 0, 0]))
    assert source.numbers == (0, 1, 2)
    assert [source.load(n, False).timestamp for n in source.numbers] == [0.0, 0.0, 0.0]


@pytest.mark.parametrize("timestamps_us", [[0, 0, 0], [66_666, 33_333, 0]])
def test_sens_timestamps_must_increase_when_odometry_is_matched_by_time(tmp_path, timestamps_us):
    """All-zero timestamps gave every frame the t = 0 odometry pose (an ego-motion of zeros);
    decreasing ones the poses of other frames."""
    path = write_sens(tmp_path / "scene.sens", timestamps_us)
    (tmp_path / "odometry.txt").write_text(
        f"0 {IDENTITY}\n0.033333 1 0 0 0 0 0 1\n0.066666 2 0 0 0 0 0 1\n"
    )
    with pytest.raises(ValueError, match=r"scene\.sens.*frame 1.*timestamp"):
        read_camera_sequence(path, **NO_IMAGES)


def test_write_tum_refuses_two_poses_at_one_time(tmp_path):
    """What the reader would refuse is not written either."""
    path = tmp_path / "poses.txt"
    with pytest.raises(ValueError, match=r"poses\.txt: two poses share the timestamp 5\.0+ s"):
        write_tum(path, np.stack([np.eye(4)] * 3), np.array([4, 5, 5]) * 10**9)
    assert not path.exists()


def test_poses_of_frames_without_distinct_times_are_written_by_frame_number(tmp_path):
    """A ``.sens`` file with zero timestamps: ``--poses-out`` falls back to the frame numbers, as
    for formats without timestamps (it wrote three poses at t = 0)."""
    recording = read_camera_sequence(write_sens(tmp_path / "scene.sens", [0, 0, 0]), **NO_IMAGES)
    assert recording.timestamps.tolist() == [0.0, 0.0, 0.0]
    path = tmp_path / "poses.txt"
    write_camera_poses(path, recording, np.zeros((3, 4)))
    assert read_pose_file(path).timestamps.tolist() == [0, 10**9, 2 * 10**9]


# ------------------------------------------------------------------------- keys given twice


def test_a_key_given_twice_is_refused(tmp_path):
    """A second ``Tr:`` in ``calib.txt`` or ``m_depthShift`` in ``_info.txt`` overrode the
    first, and of a scan listed twice in ``3RScan.json`` the first entry was used."""
    calib = tmp_path / "calib.txt"
    rigid = "1 0 0 0 0 1 0 0 0 0 1 0"
    calib.write_text(f"Tr: {rigid}\nTr: 1 0 0 5 0 1 0 0 0 0 1 0\n")
    with pytest.raises(ValueError, match=r"calib\.txt:2: Tr is given twice"):
        read_kitti_calibration(calib)
    scan = write_rscan(tmp_path / "scan")
    info = scan / "sequence" / "_info.txt"
    info.write_text(info.read_text() + "m_depthShift = 4000\n")
    with pytest.raises(ValueError, match=r"_info\.txt:8: m_depthShift is given twice"):
        open_rscan_sequence(scan)
    entry = {"reference": "rescan", "transform": np.eye(4).ravel().tolist()}
    scenes = [{"reference": "a", "scans": [entry]}, {"reference": "b", "scans": [entry]}]
    (tmp_path / "3RScan.json").write_text(json.dumps(scenes))
    with pytest.raises(ValueError, match=r"3RScan\.json: scan 'rescan' is listed 2 times"):
        read_rescan_transform(tmp_path / "3RScan.json", "rescan")
    np.testing.assert_array_equal(read_rescan_transform(tmp_path / "3RScan.json", "a"), np.eye(4))
