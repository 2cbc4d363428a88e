"""Property-based fuzzing of every LiDAR-side reader: valid files of each format are mutated
(truncated, bytes flipped, NaN / inf / garbage text inserted) and read again; the only exceptions
allowed out are ``ValueError`` (or a subclass, such as ``MapFormatError``) and
``FileNotFoundError``, and a ``ValueError`` must name the file it is about.

Formats: SemanticKITTI scans (``.bin`` + ``.label``) and sequences (``poses.txt``, ``calib.txt``,
``times.txt``), HeLiPR scans of every sensor, SPVNAS labels and GT files (and a HeLiPR sequence
read scan by scan), pose files (KITTI, 4x4, TUM), instance maps and road normals, centroid scan
files (:func:`jaxloc.io.read_centroid_scan`), and the described map's ``.npz``. Few examples each,
no deadline: a few seconds in all.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from _helipr_fixtures import FIRST_STAMP, pack_labels, pack_records, tum_line
from hypothesis import HealthCheck, given, settings, strategies as st

from jaxloc.io import (
    load_triplet_map,
    read_centroid_scan,
    read_instance_map,
    read_pose_file,
    read_road_normals,
    read_semantickitti_scan,
    save_triplet_map,
)
from jaxloc.io.helipr import read_helipr_gt, read_helipr_scan
from jaxloc.io.lidar_sequence import open_lidar_sequence, read_sequence_scan
from jaxloc.m2loc import build_map, tripletloc_config

#: Text a fuzzer inserts: non-finite numbers, overflowing ones, separators, comments, garbage,
#: a NUL byte, a lone UTF-8 continuation byte, a non-ASCII digit.
TOKENS = [b"nan", b"inf", b"-inf", b"1e999", b"-", b" ", b"\n", b"#", b"abc", b"\x00", b"\x80",
          "\u0663".encode(), b"0x1p3", b"1_0"]  # fmt: skip

mutation = st.one_of(
    st.tuples(st.just("truncate"), st.floats(0, 1)),
    st.tuples(st.just("flip"), st.floats(0, 1), st.integers(1, 255)),
    st.tuples(st.just("insert"), st.floats(0, 1), st.sampled_from(TOKENS)),
)
mutations = st.lists(mutation, min_size=1, max_size=3)
FUZZ = settings(
    max_examples=30,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)


def mutate(data: bytes, steps) -> bytes:
    out = bytearray(data)
    for step in steps:
        at = int(step[1] * len(out))
        if step[0] == "truncate":
            del out[at:]
        elif step[0] == "flip" and out:
            out[min(at, len(out) - 1)] ^= step[2]
        elif step[0] == "insert":
            out[at:at] = step[2]
    return bytes(out)


def expect_clean_failure(read, path: Path) -> None:
    """``read()`` succeeds or raises ValueError naming ``path`` (or FileNotFoundError)."""
    try:
        read()
    except FileNotFoundError:
        pass
    except ValueError as error:
        assert path.name in str(error), (type(error), str(error))


# ----------------------------------------------------------------------------- valid files


def _scan_arrays(n: int = 64):
    rng = np.random.default_rng(0)
    points = rng.uniform(-20, 20, (n, 3)).astype(np.float32)
    raw = rng.choice([71, 80, 81, 40, 50], n).astype(np.uint32) | (np.arange(n) % 5 << 16)
    return points, raw.astype(np.uint32)


class Scans:
    """The scans of the synthetic fixture in the shape ``write_*`` helpers expect."""

    def __init__(self, count: int):
        points, raw = _scan_arrays()
        self.points = [points + i for i in range(count)]
        self.raw_labels = [raw] * count
        poses = np.tile(np.eye(4), (count, 1, 1))
        poses[:, 0, 3] = np.arange(count) * 2.0
        self.T_map_scan = poses


@pytest.fixture(scope="module")
def pristine(tmp_path_factory) -> Path:
    """One valid file (or folder) of every format."""
    from _helipr_fixtures import write_helipr_sequence, write_kitti_twin

    root = tmp_path_factory.mktemp("pristine")
    scans = Scans(3)
    write_kitti_twin(root / "kitti", scans, scans.T_map_scan)
    (root / "kitti" / "times.txt").write_text("0.0\n0.1\n0.2\n")
    write_helipr_sequence(root / "helipr", scans)
    poses = scans.T_map_scan
    (root / "poses").mkdir()
    (root / "poses" / "kitti.txt").write_text(
        "".join(" ".join(f"{v:.9g}" for v in p[:3].ravel()) + "\n" for p in poses)
    )
    (root / "poses" / "rows.txt").write_text(
        "".join(" ".join(f"{v:.9g}" for v in p.ravel()) + "\n" for p in poses)
    )
    (root / "poses" / "tum.txt").write_text(
        "".join(tum_line(f"{i}.5", p) + "\n" for i, p in enumerate(poses))
    )
    (root / "map" / "instances").mkdir(parents=True)
    (root / "map" / "RSN").mkdir()
    rng = np.random.default_rng(1)
    points = {c: rng.uniform(-30, 30, (4, 3)) for c in (15, 17, 18)}
    for c, rows in points.items():
        (root / "map" / "instances" / f"{c}.txt").write_text(
            "".join(f"{i} {x:.6f} {y:.6f} {z:.6f}\n" for i, (x, y, z) in enumerate(rows))
        )
    (root / "map" / "RSN" / "road_normal.txt").write_text(
        "1.0 2.0 0.01 0.02 0.9997 0.5\n-3.0 4.0 0 0 1 1.5\n"
    )
    (root / "centroids.txt").write_text("# class x y z\n15 1 2 3\n17 4 5 6\n18 -1 -2 0.5\n")
    all_points = np.concatenate(list(points.values()))
    labels = np.repeat([15, 17, 18], 4)
    save_triplet_map(build_map(all_points, labels, tripletloc_config(top_k=4)), root / "map.npz")
    return root


def _copy(pristine: Path, name: str, tmp_path: Path) -> Path:
    target = tmp_path / name
    if target.exists():
        shutil.rmtree(target) if target.is_dir() else target.unlink()
    source = pristine / name
    shutil.copytree(source, target) if source.is_dir() else shutil.copy(source, target)
    return target


# ----------------------------------------------------------------------------- the readers


@FUZZ
@given(steps=mutations, which=st.sampled_from(["bin", "label"]))
def test_semantickitti_scan(pristine, tmp_path, steps, which):
    folder = _copy(pristine, "kitti", tmp_path)
    bin_path, label_path = folder / "velodyne" / "000001.bin", folder / "labels" / "000001.label"
    target = bin_path if which == "bin" else label_path
    target.write_bytes(mutate(target.read_bytes(), steps))
    try:
        read_semantickitti_scan(bin_path, label_path)
    except ValueError as error:
        assert "000001." in str(error)


@FUZZ
@given(steps=mutations, which=st.sampled_from(["poses.txt", "calib.txt", "times.txt"]))
def test_semantickitti_sequence(pristine, tmp_path, steps, which):
    folder = _copy(pristine, "kitti", tmp_path)
    (folder / which).write_bytes(mutate((folder / which).read_bytes(), steps))
    try:
        open_lidar_sequence(folder)
    except FileNotFoundError:
        pass
    except ValueError as error:
        assert "poses.txt" in str(error) or which in str(error), str(error)


@FUZZ
@given(
    steps=mutations,
    sensor=st.sampled_from(["Ouster", "Velodyne", "Avia", "Aeva", "Aeva29"]),
    which=st.sampled_from(["bin", "label"]),
)
def test_helipr_scan(tmp_path, steps, sensor, which):
    stamp = 1691936557946849180 if sensor == "Aeva29" else FIRST_STAMP
    folder_name = "Aeva" if sensor.startswith("Aeva") else sensor
    points, raw = _scan_arrays()
    bin_path = tmp_path / "LiDAR" / folder_name / f"{stamp}.bin"
    label_path = tmp_path / "labels" / f"{stamp}.label"
    bin_path.parent.mkdir(parents=True, exist_ok=True)
    label_path.parent.mkdir(exist_ok=True)
    bin_path.write_bytes(pack_records(points, folder_name, stamp))
    label_path.write_bytes(pack_labels(raw))
    target = bin_path if which == "bin" else label_path
    target.write_bytes(mutate(target.read_bytes(), steps))
    try:
        read_helipr_scan(bin_path, label_path, folder_name.lower())
    except ValueError as error:
        assert str(stamp) in str(error), str(error)


@FUZZ
@given(steps=mutations, which=st.sampled_from(["gt", "bin", "label"]))
def test_helipr_sequence_and_gt(pristine, tmp_path, steps, which):
    folder = _copy(pristine, "helipr", tmp_path)
    target = {
        "gt": folder / "LiDAR_GT" / "Ouster_gt.txt",
        "bin": sorted((folder / "LiDAR" / "Ouster").iterdir())[1],
        "label": sorted((folder / "labels").iterdir())[1],
    }[which]
    target.write_bytes(mutate(target.read_bytes(), steps))
    if which == "gt":
        expect_clean_failure(lambda: read_helipr_gt(target), target)

    def read_all():
        sequence = open_lidar_sequence(folder)
        for index in range(len(sequence.bins)):
            read_sequence_scan(sequence, index)

    try:
        read_all()
    except FileNotFoundError:
        pass
    except ValueError as error:
        assert target.stem in str(error) or "Ouster_gt.txt" in str(error), str(error)


@FUZZ
@given(steps=mutations, name=st.sampled_from(["kitti.txt", "rows.txt", "tum.txt"]))
def test_pose_files(pristine, tmp_path, steps, name):
    path = tmp_path / name
    path.write_bytes(mutate((pristine / "poses" / name).read_bytes(), steps))
    expect_clean_failure(lambda: read_pose_file(path), path)


@FUZZ
@given(steps=mutations, name=st.sampled_from(["15.txt", "17.txt", "18.txt", "road_normal.txt"]))
def test_instance_maps_and_road_normals(pristine, tmp_path, steps, name):
    folder = _copy(pristine, "map", tmp_path)
    path = folder / ("RSN" if name == "road_normal.txt" else "instances") / name
    path.write_bytes(mutate(path.read_bytes(), steps))
    expect_clean_failure(lambda: read_instance_map(folder), path)
    expect_clean_failure(lambda: read_road_normals(folder), path)


@FUZZ
@given(steps=mutations)
def test_centroid_scan_files(pristine, tmp_path, steps):
    path = tmp_path / "centroids.txt"
    path.write_bytes(mutate((pristine / "centroids.txt").read_bytes(), steps))
    expect_clean_failure(lambda: read_centroid_scan(path, (15, 17, 18)), path)


@FUZZ
@given(steps=mutations)
def test_described_map_file(pristine, tmp_path, steps):
    path = tmp_path / "map.npz"
    path.write_bytes(mutate((pristine / "map.npz").read_bytes(), steps))
    expect_clean_failure(lambda: load_triplet_map(path), path)


@pytest.mark.parametrize(
    "header",
    [
        b"{'descr': '<f4', 'fortran_order': False, 'shape': (3,",  # tokenize.TokenError
        b"{'descr': '<f4', 'fortran_order': False, 'shape': (99999999999999,), }",  # 364 TiB
        b"{'descr': x}",  # not a literal
    ],
)
def test_map_file_whose_npy_header_does_not_parse(tmp_path, header):
    """What byte flips reach only rarely: a zip member (valid CRC) whose ``.npy`` header no longer
    parses, or promises an array that cannot be allocated, is a MapFormatError too."""
    import zipfile

    from jaxloc.io import MapFormatError

    padded = header + b" " * ((64 - 10 - len(header) - 1) % 64) + b"\n"
    blob = b"\x93NUMPY\x01\x00" + len(padded).to_bytes(2, "little") + padded + b"\0" * 8
    with zipfile.ZipFile(tmp_path / "m.npz", "w") as archive:
        archive.writestr("format.npy", blob)
    with pytest.raises(MapFormatError, match=r"m\.npz: not a readable jaxloc map"):
        load_triplet_map(tmp_path / "m.npz")
