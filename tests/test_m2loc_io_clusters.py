"""jaxloc.m2loc loaders and instance clustering."""

from pathlib import Path

import numpy as np
import pytest

from jaxloc.io import read_instance_map, read_road_normals, read_semantickitti_scan
from jaxloc.io.semantickitti import semantickitti_class_ids
from jaxloc.m2loc import cluster_instances
from jaxloc.m2loc._clusters import euclidean_clusters, voxel_downsample

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
SCAN = DATA / "semantickitti_scan"
MAPS = DATA / "helipr_instance_maps"


def test_learning_map_ids():
    raw = np.array([71, 80, 81, 70, 0, 40 | (7 << 16)], np.uint32)
    np.testing.assert_array_equal(semantickitti_class_ids(raw), [15, 17, 18, 14, -1, 8])


def test_voxel_downsample_matches_loop():
    rng = np.random.default_rng(0)
    points = rng.uniform(0, 1, (500, 3))
    out = voxel_downsample(points, 0.25)
    keys = {}
    for p in points:
        keys.setdefault(tuple(np.floor(p / 0.25).astype(int)), []).append(p)
    expected = np.array(sorted(np.mean(v, axis=0).tolist() for v in keys.values()))
    np.testing.assert_allclose(np.array(sorted(out.tolist())), expected, atol=1e-12)


def test_euclidean_clusters_vs_brute_force_components():
    rng = np.random.default_rng(1)
    points = np.concatenate(
        [rng.normal(c, 0.2, (30, 3)) for c in ([0, 0, 0], [5, 0, 0], [0, 9, 0])]
    )
    points = np.concatenate([points, [[20.0, 20, 20]]])
    clusters = euclidean_clusters(points, 0.5, min_points=2)
    # brute-force union-find on all pairs
    parent = list(range(len(points)))

    def find(i):
        while parent[i] != i:
            i = parent[i]
        return i

    d = np.linalg.norm(points[:, None] - points[None], axis=-1)
    for i, j in zip(*np.nonzero(np.triu(d <= 0.5, 1)), strict=True):
        parent[find(i)] = find(j)
    roots = np.array([find(i) for i in range(len(points))])
    expected = sorted(
        sorted(np.flatnonzero(roots == r).tolist())
        for r in np.unique(roots)
        if np.sum(roots == r) >= 2
    )
    assert sorted(sorted(c.tolist()) for c in clusters) == expected


def test_fusion_takes_label_of_largest_member():
    rng = np.random.default_rng(2)
    pole = rng.uniform([-0.1, -0.1, 0], [0.1, 0.1, 4], (2000, 3))  # ~ 320 voxels
    sign = rng.uniform(
        [0.2, -0.3, 1.9], [0.3, 0.3, 2.5], (500, 3)
    )  # centroid 0.25 m from the pole's
    trunk = rng.uniform([9.8, -0.2, 0], [10.2, 0.2, 2], (2000, 3))
    points = np.concatenate([pole, sign, trunk])
    labels = np.array([17] * 2000 + [18] * 500 + [15] * 2000)
    inst = cluster_instances(points, labels)
    assert len(inst.points) == 2
    assert sorted(inst.labels.tolist()) == [15, 17]


def test_cluster_rejects_nan():
    with pytest.raises(ValueError, match="NaN"):
        cluster_instances(np.array([[np.nan, 0, 0]]), np.array([15]))


@pytest.mark.skipif(not SCAN.exists(), reason="shared data absent")
def test_real_semantickitti_scan_plausible_instances():
    scan = read_semantickitti_scan(SCAN / "000000.bin", SCAN / "000000.label")
    assert scan.points.shape[0] > 100_000 and scan.points.dtype == np.float32
    inst = cluster_instances(scan.points, scan.labels)
    counts = {c: int(np.sum(inst.labels == c)) for c in (15, 17, 18)}
    assert 10 <= len(inst.points) <= 80, counts  # TripletLoc scans hold about 30 vertices
    assert all(v >= 1 for v in counts.values()), counts
    d = (
        np.linalg.norm(inst.points[:, None] - inst.points[None], axis=-1)
        + np.eye(len(inst.points)) * 9
    )
    assert d.min() > 0.5  # fused within 0.5 m


@pytest.mark.skipif(not MAPS.exists(), reason="shared data absent")
def test_real_instance_map_and_rsn_load():
    m = read_instance_map(MAPS / "KAIST04")
    assert m.points.shape == (3923, 3) and set(np.unique(m.labels)) == {15, 17, 18}
    r = read_road_normals(MAPS / "KAIST04")
    np.testing.assert_allclose(np.linalg.norm(r.normals, axis=1), 1.0, atol=1e-9)
    assert np.all(r.normals[:, 2] > 0.9)


def _write_map(root: Path, trunk_lines: str):
    (root / "instances").mkdir(parents=True)
    (root / "RSN").mkdir()
    (root / "instances" / "15.txt").write_text(trunk_lines)
    (root / "instances" / "17.txt").write_text("0 1 2 3\n")
    (root / "instances" / "18.txt").write_text("")
    (root / "RSN" / "road_normal.txt").write_text("0 0 0 0 1 0.5\n")


@pytest.mark.parametrize(
    "lines, message",
    [
        ("0 1 2\n", "expected 4 fields"),
        ("0 1 x 3\n", "non-numeric value"),
        ("0 1 nan 3\n", "NaN or inf"),
    ],
)
def test_malformed_map_line_is_a_clear_error(tmp_path, lines, message):
    _write_map(tmp_path, "0 1 2 3\n" + lines)
    with pytest.raises(ValueError, match=message) as info:
        read_instance_map(tmp_path)
    assert "15.txt:2" in str(info.value)


def test_small_map_and_rsn_parse(tmp_path):
    _write_map(tmp_path, "0 1 2 3\n\n5 4 5 6\n")
    m = read_instance_map(tmp_path)
    np.testing.assert_array_equal(m.labels, [15, 15, 17])
    np.testing.assert_array_equal(m.ids, [0, 5, 0])
    (tmp_path / "RSN" / "road_normal.txt").write_text("0 0 0 0 0 0.5\n")
    with pytest.raises(ValueError, match="zero-length"):
        read_road_normals(tmp_path)
