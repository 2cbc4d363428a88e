"""Every LiDAR reader refuses what no sensor records, as one line naming the file or option:
records of another type whose lengths happen to agree (a float64 scan with a uint64 label file),
points beyond ``MAX_RANGE_M``, SemanticKITTI ids outside the learning map, and options of
``open_lidar_recording`` that do not apply to the input (``sensor`` with a scan file, ``layout``
and ``every`` without a sequence folder, bag options without a bag). Bags refuse the same points
and ids (``tests/test_rosbag_lidar.py``)."""

from __future__ import annotations

import warnings
from types import SimpleNamespace

import numpy as np
import pytest
from _helipr_fixtures import FIRST_STAMP, pack_labels, pack_records

from jaxloc.io.helipr import read_helipr_scan
from jaxloc.io.lidar_recording import open_lidar_recording, read_centroid_scan
from jaxloc.io.semantickitti import MAX_RANGE_M, read_semantickitti_scan


def _scan(n: int = 64):
    rng = np.random.default_rng(0)
    points = rng.uniform(-20, 20, (n, 3))
    raw = rng.choice([71, 80, 81, 40, 50], n).astype(np.uint32) | (np.arange(n) % 5 << 16)
    return points, raw.astype(np.uint32)


def _one_line(call, *parts: str) -> None:
    with pytest.raises(ValueError) as caught, warnings.catch_warnings():
        warnings.simplefilter("error")  # and no RuntimeWarning on the way
        call()
    message = str(caught.value)
    assert "\n" not in message, message
    for part in parts:
        assert part in message, (part, message)


def test_a_float64_scan_with_a_uint64_label_file_is_refused(tmp_path):
    """The counts agree (each float64 is two float32, each uint64 two uint32 words), the
    coordinates do not: the words of the doubles read as float32 reach 1e20 m and more."""
    points, raw = _scan()
    np.column_stack([points, np.zeros(len(points))]).astype("<f8").tofile(tmp_path / "a.bin")
    raw.astype("<u8").tofile(tmp_path / "a.label")
    recording = open_lidar_recording(tmp_path / "a.bin")
    _one_line(lambda: recording.instances(0), "a.bin: ", f"beyond {MAX_RANGE_M:g} m of the sensor")


def test_points_beyond_range_and_unknown_ids_in_every_reader(tmp_path):
    points, raw = _scan()
    far = points.copy()
    far[3] = [1500.0, 0.0, 0.0]
    xyzi = np.column_stack([far, np.zeros(len(far))]).astype("<f4")
    xyzi.tofile(tmp_path / "far.bin")
    raw.astype("<u4").tofile(tmp_path / "far.label")
    _one_line(
        lambda: read_semantickitti_scan(tmp_path / "far.bin", tmp_path / "far.label"),
        "far.bin: 1 point(s) beyond 1000 m of the sensor (point 3 at 1.5e+03 m)",
    )
    np.column_stack([points, np.zeros(len(points))]).astype("<f4").tofile(tmp_path / "id.bin")
    unknown = raw.copy()
    unknown[[4, 9]] = [300 | (1 << 16), 2]
    unknown.astype("<u4").tofile(tmp_path / "id.label")
    _one_line(
        lambda: read_semantickitti_scan(tmp_path / "id.bin", tmp_path / "id.label"),
        "id.label: label id 2 (and 1 other id(s)) is not in SemanticKITTI's learning map",
    )
    bin_path = tmp_path / "LiDAR" / "Ouster" / f"{FIRST_STAMP}.bin"
    bin_path.parent.mkdir(parents=True)
    bin_path.write_bytes(pack_records(far.astype(np.float32), "Ouster", FIRST_STAMP))
    (tmp_path / "x.label").write_bytes(pack_labels(raw))
    _one_line(
        lambda: read_helipr_scan(bin_path, tmp_path / "x.label", "ouster"),
        f"{FIRST_STAMP}.bin: 1 point(s) beyond 1000 m",
    )
    (tmp_path / "c.txt").write_text("15 1 2 3\n17 4000 5 6\n")
    _one_line(lambda: read_centroid_scan(tmp_path / "c.txt"), "c.txt: 1 point(s) beyond 1000 m")


def test_options_that_do_not_apply_to_the_input_are_refused(tmp_path):
    """``sensor`` with a scan file or a SemanticKITTI folder, ``layout`` / ``every`` with scan
    files only, bag options without a bag: each names the input and the option."""
    from _helipr_fixtures import write_kitti_twin

    points, raw = _scan()
    scans = SimpleNamespace(points=[points.astype(np.float32)] * 2, raw_labels=[raw] * 2)
    write_kitti_twin(tmp_path / "kitti", scans, np.tile(np.eye(4), (2, 1, 1)))
    scan = tmp_path / "kitti" / "velodyne" / "000000.bin"
    cases = [
        ([scan], {"sensor": "Foo"}, "000000.bin: sensor='Foo' applies to sequence folders"),
        ([scan], {"layout": "plain"}, "000000.bin: layout='plain' applies to sequence folders"),
        ([scan], {"every": 2}, "000000.bin: every=2 applies to sequence folders"),
        (
            [tmp_path / "kitti"], {"sensor": "Ouster"},
            "kitti: sensor='Ouster' applies to HeLiPR sequence folders",
        ),
        ([tmp_path / "kitti"], {"topic": "/points"}, "kitti: topic='/points' applies to bags"),
        ([scan, scan], {"label_field": "cls"}, "000000.bin ...: label_field='cls' applies to bags"),
    ]  # fmt: skip
    for paths, options, part in cases:
        _one_line(lambda p=paths, o=options: open_lidar_recording(p, **o), part)
    assert len(open_lidar_recording(tmp_path / "kitti", every=2)) == 1
