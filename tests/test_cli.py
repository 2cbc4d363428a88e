"""The ``jaxloc`` command, called in-process through ``main(argv)``.

localize-lidar runs on a small synthetic instance map written to disk (always) and on the real
HeLiPR map + SemanticKITTI scan of ``../shared/data`` (skipped when absent). The synthetic map is
the world ``jaxloc bench triplet --blocks 1`` builds, and both use ``--scales 1 -k 10``, so the
bench test reuses the localization's compilation. Malformed and missing files must give exit
code 2 and one line on stderr, without a traceback.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
from _compilations import compilations

from jaxloc.cli import main
from jaxloc.io import read_semantickitti_scan
from jaxloc.m2loc import cluster_instances, localization_errors
from jaxloc.synthetic.outdoor import make_outdoor_world, make_query

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
REAL_MAP = DATA / "helipr_instance_maps" / "KAIST04"
REAL_SCAN = DATA / "semantickitti_scan" / "000000.bin"
CONFIG_ARGS = ["--scales", "1", "-k", "10"]
#: SemanticKITTI raw ids of trunk, pole, traffic sign (class ids 15, 17, 18).
RAW_IDS = {15: 71, 17: 80, 18: 81}


def run(argv, capsys):
    """Call main(argv); returns (exit code, stdout, stderr)."""
    code = main([str(a) for a in argv])
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.fixture(scope="module")
def world():
    # the world of `jaxloc bench triplet --world dense --blocks 1 --seed 0`
    return make_outdoor_world("dense", seed=0, blocks=1, bridge_length=0)


@pytest.fixture(scope="module")
def map_dir(world, tmp_path_factory) -> Path:
    """The world in the HeLiPR layout: instances/{15,17,18}.txt and RSN/road_normal.txt."""
    root = tmp_path_factory.mktemp("map")
    (root / "instances").mkdir()
    (root / "RSN").mkdir()
    for class_id in (15, 17, 18):
        points = world.points[world.labels == class_id]
        rows = np.column_stack([np.arange(len(points)), points])
        np.savetxt(root / "instances" / f"{class_id}.txt", rows, fmt="%d %.6f %.6f %.6f")
    rsn = world.road_normals
    np.savetxt(
        root / "RSN" / "road_normal.txt", np.column_stack([rsn.xy, rsn.normals, rsn.std_deg])
    )
    return root


@pytest.fixture(scope="module")
def queries(world):
    rng = np.random.default_rng(7)
    return [
        make_query(world.points, world.labels, world.road_normals, rng, max_kept=24)
        for _ in range(2)
    ]


def write_centroids(path: Path, query) -> Path:
    np.savetxt(path, np.column_stack([query.labels, query.points]), fmt="%d %.6f %.6f %.6f")
    return path


def write_poses(path: Path, poses) -> Path:
    np.savetxt(path, np.stack([T[:3].ravel() for T in poses]))  # KITTI 3x4 rows
    return path


def write_semantickitti(folder: Path, query) -> Path:
    """A .bin/.label pair (dataset layout velodyne/ + labels/) whose trunk/pole/sign points form
    one 4x4x2 block of 0.11 m spacing around each query centroid, plus road points."""
    offsets = np.stack(np.meshgrid(*[np.arange(4)] * 2, np.arange(2), indexing="ij"), -1)
    offsets = (offsets.reshape(-1, 3) - [1.5, 1.5, 0.5]) * 0.11
    points = [query.points[:, None, :] + offsets[None]]
    labels = [np.repeat([RAW_IDS[int(c)] for c in query.labels], len(offsets))]
    instance = np.repeat(np.arange(1, len(query.points) + 1), len(offsets))
    road = np.random.default_rng(0).uniform(-20, 20, (500, 3)) * [1, 1, 0.01]
    points = np.concatenate([points[0].reshape(-1, 3), road])
    words = np.concatenate([labels[0] | (instance << 16), np.full(len(road), 40)])
    (folder / "velodyne").mkdir()
    (folder / "labels").mkdir()
    scan = np.column_stack([points, np.zeros(len(points))]).astype("<f4")
    scan.tofile(folder / "velodyne" / "000001.bin")
    words.astype("<u4").tofile(folder / "labels" / "000001.label")
    return folder / "velodyne" / "000001.bin"


# ----------------------------------------------------------------------------- help


@pytest.mark.parametrize(
    "argv",
    [
        [],
        ["demo"],
        ["localize-lidar"],
        ["build-lidar-map"],
        ["build-scene-graph"],
        ["localize-camera"],
        ["bench"],
        ["bench", "raycast"],
        ["bench", "filter"],
        ["bench", "triplet"],
    ],
)
def test_help_of_every_command(argv, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main([*argv, "--help"])
    assert exit_info.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: jaxloc")
    if len(argv) < 2:  # the top level and the commands carry worked examples
        assert "examples:" in out


def test_help_explains_file_formats(capsys):
    with pytest.raises(SystemExit):
        main(["localize-lidar", "--help"])
    out = capsys.readouterr().out
    for needle in ("instances/15.txt", "road_normal.txt", ".label", "class_id x y z", "--gt"):
        assert needle in out
    with pytest.raises(SystemExit):
        main(["build-lidar-map", "--help"])
    out = capsys.readouterr().out
    for needle in ("velodyne/NNNNNN.bin", "labels/NNNNNN.label", "poses.txt", "calib.txt", "Tr"):
        assert needle in out


# ----------------------------------------------------------------------------- localize-lidar


def test_localize_lidar_synthetic_centroids_json(map_dir, queries, tmp_path, capsys):
    scans = [write_centroids(tmp_path / f"scan{i}.txt", q) for i, q in enumerate(queries)]
    gt = write_poses(tmp_path / "gt.txt", [q.T_map_scan for q in queries])
    code, out, err = run(
        ["localize-lidar", map_dir, *scans, "--gt", gt, "--json", *CONFIG_ARGS], capsys
    )
    assert code == 0, err
    document = json.loads(out)
    assert document["summary"]["map_instances"] == sum(
        len((map_dir / "instances" / f"{c}.txt").read_text().splitlines()) for c in (15, 17, 18)
    )
    assert document["summary"]["success_rate"] == 1.0
    for record, query in zip(document["scans"], queries, strict=True):
        assert record["instances"] == len(query.points)
        assert record["valid"] and record["clique_size"] >= 3
        rte, rre = localization_errors(np.array(record["T_map_scan"]), query.T_map_scan)
        assert rte < 1.0 and rre < 2.0
        assert record["rte_m"] == pytest.approx(rte, abs=1e-3)
    assert document["scans"][0]["compile_s"] >= 0.0


def test_localize_lidar_text_output(map_dir, queries, tmp_path, capsys):
    scan = write_centroids(tmp_path / "scan.txt", queries[0])
    gt = tmp_path / "gt.txt"
    np.savetxt(gt, queries[0].T_map_scan.reshape(1, 16))  # the 4x4 form
    code, out, _ = run(["localize-lidar", map_dir, scan, "--gt", gt, *CONFIG_ARGS], capsys)
    assert code == 0
    assert "with road normals" in out and "T_map_scan =" in out and "success" in out
    matrix = [
        [float(v) for v in line.split()]
        for line in out.splitlines()
        if re.fullmatch(r"\s+(-?\d+\.\d{4}\s*){4}", line)
    ]
    rte, rre = localization_errors(np.array(matrix), queries[0].T_map_scan)
    assert rte < 1.0 and rre < 2.0
    assert re.search(r"RTE \d+\.\d+ m, RRE \d+\.\d+ deg", out)


def test_localize_lidar_semantickitti_bin_matches_centroids(map_dir, queries, tmp_path, capsys):
    query = queries[1]
    bin_path = write_semantickitti(tmp_path, query)
    scan = read_semantickitti_scan(bin_path, tmp_path / "labels" / "000001.label")
    assert len(cluster_instances(scan.points, scan.labels).points) == len(query.points)
    code, out, err = run(["localize-lidar", map_dir, bin_path, "--json", *CONFIG_ARGS], capsys)
    assert code == 0, err
    record = json.loads(out)["scans"][0]
    assert record["instances"] == len(query.points) and record["valid"]
    rte, rre = localization_errors(np.array(record["T_map_scan"]), query.T_map_scan)
    assert rte < 1.0 and rre < 2.0


@pytest.mark.skipif(not (REAL_MAP.is_dir() and REAL_SCAN.is_file()), reason="no ../shared/data")
def test_localize_lidar_real_map_and_scan(capsys):
    code, out, err = run(["localize-lidar", REAL_MAP, REAL_SCAN, "--json", *CONFIG_ARGS], capsys)
    assert code == 0, err
    document = json.loads(out)
    scan = read_semantickitti_scan(REAL_SCAN, REAL_SCAN.with_suffix(".label"))
    record = document["scans"][0]
    assert record["instances"] == len(cluster_instances(scan.points, scan.labels).points)
    pose = np.array(record["T_map_scan"])
    np.testing.assert_allclose(pose[:3, :3] @ pose[:3, :3].T, np.eye(3), atol=1e-4)
    np.testing.assert_array_equal(pose[3], [0, 0, 0, 1])
    assert isinstance(record["valid"], bool) and record["clique_size"] >= 0
    assert record["descriptor_ms"] > 0 and record["match_ms"] > 0


# ----------------------------------------------------------------------------- errors


def _malformed(tmp_path: Path, map_dir: Path, queries) -> dict:
    """name -> (argv, expected message part) of one bad input each."""
    good_scan = write_centroids(tmp_path / "good.txt", queries[0])
    bad_map = tmp_path / "bad_map"
    (bad_map / "instances").mkdir(parents=True)
    for class_id in (15, 17, 18):
        (bad_map / "instances" / f"{class_id}.txt").write_text("0 1.0 2.0 3.0\n")
    (bad_map / "instances" / "17.txt").write_text("0 1.0 2.0 3.0\n1 1.0 abc 3.0\n")
    partial_map = tmp_path / "partial_map"
    (partial_map / "instances").mkdir(parents=True)
    (partial_map / "instances" / "15.txt").write_text("0 1.0 2.0 3.0\n")
    short = tmp_path / "short.txt"
    short.write_text("15 1.0 2.0\n")
    unknown = tmp_path / "unknown.txt"
    unknown.write_text("15 1 2 3\n12 4 5 6\n")
    nan = tmp_path / "nan.txt"
    nan.write_text("15 1 2 nan\n")
    truncated = tmp_path / "truncated.bin"
    np.zeros(5, "<f4").tofile(truncated)
    truncated.with_suffix(".label").write_bytes(b"\0" * 4)
    unlabelled = tmp_path / "velodyne" / "nolabel.bin"
    unlabelled.parent.mkdir()
    np.zeros(8, "<f4").tofile(unlabelled)
    ply = tmp_path / "scan.ply"
    ply.write_text("ply\n")
    gt = tmp_path / "gt_two.txt"
    np.savetxt(gt, np.tile(np.eye(4)[:3].ravel(), (2, 1)))
    scaled = tmp_path / "gt_scaled.txt"
    np.savetxt(scaled, (2 * np.eye(4))[:3].reshape(1, 12))
    return {
        "missing map": ([tmp_path / "nope", good_scan], "map folder not found"),
        "map without a class file": ([partial_map, good_scan], "missing instances/17.txt"),
        "malformed map line": (
            [bad_map, good_scan],
            "17.txt:2: line '1 1.0 abc 3.0' has a non-numeric value",
        ),
        "missing scan": ([map_dir, tmp_path / "absent.txt"], "missing scan"),
        "short scan line": ([map_dir, short], "short.txt:1: expected 4 numbers"),
        "unknown class": ([map_dir, unknown], "unknown class ids [12]"),
        "non-finite scan": ([map_dir, nan], "nan.txt:1: non-finite value"),
        "truncated bin": ([map_dir, truncated], "not a multiple of 4"),
        "bin without labels": ([map_dir, unlabelled], "no label file"),
        "unknown suffix": ([map_dir, ply], "unknown scan format"),
        "pose count": ([map_dir, good_scan, "--gt", gt], "2 poses for 1 scan(s)"),
        "pose not rigid": ([map_dir, good_scan, "--gt", scaled], "pose 1 is not rigid"),
        "missing gt": ([map_dir, good_scan, "--gt", tmp_path / "no_gt.txt"], "missing file"),
        "bad k": ([map_dir, good_scan, "-k", "0"], "argument -k: want an integer >= 1, got '0'"),
    }


def test_bad_inputs_exit_2_with_one_line(map_dir, queries, tmp_path, capsys):
    for name, (argv, expected) in _malformed(tmp_path, map_dir, queries).items():
        code, out, err = run(["localize-lidar", *argv, "--scales", "1"], capsys)
        assert code == 2, name
        assert err.startswith("jaxloc localize-lidar: error: "), (name, err)
        assert expected in err, (name, err)
        assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, name


def test_usage_errors_exit_2(capsys):
    for argv in (["localize-lidar", "map", "scan", "--scales", "4"], ["bench", "nothing"], []):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert len(err.splitlines()) == 1 and err.startswith("jaxloc") and "--help)" in err, err


# ----------------------------------------------------------------------------- bench and demo


def numbers_after(pattern: str, text: str) -> float:
    match = re.search(pattern, text)
    assert match, (pattern, text)
    return float(match.group(1))


def test_bench_triplet_tiny(capsys):
    code, out, err = run(
        ["bench", "triplet", "--queries", "2", "--blocks", "1", *CONFIG_ARGS], capsys
    )
    assert code == 0, err
    assert numbers_after(r"descriptors (\d+\.\d+) ms/query", out) > 0
    assert numbers_after(r"pose (\d+\.\d+) ms/query", out) > 0
    assert 0 <= numbers_after(r"success (\d+)%", out) <= 100


def test_bench_raycast_tiny(capsys):
    argv = ["bench", "raycast", "--poses", "2", "--width", "32", "--height", "18"]
    argv += ["--stride", "4", "--objects", "1", "--vertices", "100", "--repeats", "1"]
    code, out, err = run(argv, capsys)
    assert code == 0, err
    assert "2 poses x 32 rays" in out  # 8 x 4 pixels at stride 4
    from jaxloc.cli._bench import describe_engine

    assert f"engine: {describe_engine()}" in out  # e.g. "embree (native, 2 threads, ...)"
    assert numbers_after(r"(\d+\.\d+) M rays/s", out) > 0


def test_bench_rejects_bad_sizes(capsys):
    code, _, err = run(["bench", "raycast", "--poses", "0"], capsys)
    assert code == 2 and "argument --poses: want an integer >= 1, got '0'" in err


# The demo and `bench filter` share the room, camera, particle count and stride here, hence
# every compilation (the demo runs first).
TINY_SG2LOC = ["--frames", "2", "--particles", "32", "--width", "112", "--height", "63"]


def test_demo_tiny(tmp_path, capsys):
    """... and its warm-up (the filter's programs compiled from a placeholder of the query's
    sizes while the query is rendered) compiled the one program of the rounds its localize ran,
    none again for the real sequence."""
    figure = tmp_path / "demo.png"
    with compilations() as compiled:
        code, out, err = run(["demo", *TINY_SG2LOC, "--strides", "8,8", "--out", figure], capsys)
    assert code == 0, err
    rounds = [c for c in compiled if c.endswith(": jit(all_rounds)")]
    assert len(rounds) == 1 and rounds[0].startswith("jaxloc-warm-up_")
    assert re.search(r"frame 2: (not )?localized, position error \d+\.\d+ m", out)
    assert "round 2/2 (stride 8)" in err  # the progress bar, ticked from inside the scans
    assert figure.read_bytes().startswith(b"\x89PNG")


def test_demo_rerun_writes_a_recording_rerun_loads(tmp_path, capsys):
    """``demo --rerun F.rrd`` (the sizes of the tiny demo above, so its compilations) writes the
    run as a recording Rerun's own reader loads: the map, each round's particles, the camera."""
    rerun_chunk = pytest.importorskip("rerun.chunk")
    rrd = tmp_path / "demo.rrd"
    argv = ["demo", *TINY_SG2LOC, "--strides", "8,8", "--out", tmp_path / "d.png", "--rerun", rrd]
    code, out, err = run(argv, capsys)
    assert code == 0, err
    assert f"rerun: {rrd}" in out
    entities = {chunk.entity_path for chunk in rerun_chunk.RrdReader(rrd).stream().to_chunks()}
    for entity in ("/world/map/objects/0", "/world/particles/round_1", "/world/camera/image/rgb"):
        assert entity in entities, (entity, sorted(entities))


def test_rerun_without_rerun_sdk_is_one_line_before_any_work(tmp_path, capsys, monkeypatch):
    """Without rerun-sdk, ``--rerun`` is one line and exit status 2 while the options are
    checked: before the demo builds or compiles anything, before localize-lidar and
    localize-camera read their (here missing) inputs."""
    import sys

    monkeypatch.setitem(sys.modules, "rerun", None)  # `import rerun`: ModuleNotFoundError
    rrd = tmp_path / "x.rrd"
    for argv in (["demo"], ["localize-lidar", "map", "scan"], ["localize-camera", "m.npz", "s"]):
        code, out, err = run([*argv, "--rerun", rrd], capsys)
        assert code == 2 and out == "" and len(err.strip().splitlines()) == 1, err
        assert err.startswith(f"jaxloc {argv[0]}: error: --rerun {rrd}: writing a Rerun "
                              "recording (.rrd) needs the rerun-sdk package")  # fmt: skip
    assert not list(tmp_path.iterdir())


def test_demo_rejects_bad_strides(capsys):
    for bad in ("20,0", "20,x", ""):
        assert main(["demo", "--strides", bad]) == 2
        assert "want positive integers like 20,8,4" in capsys.readouterr().err


def test_bench_filter_tiny(capsys):
    code, out, err = run(["bench", "filter", *TINY_SG2LOC, "--stride", "8"], capsys)
    assert code == 0, err
    assert "32 particles x 112 rays" in out  # 14 x 8 pixels at stride 8
    assert numbers_after(r"(\d+\.\d+) s/frame wall", out) > 0


def test_the_first_scans_query_programs_are_prepared_for_plain_runs(map_dir, queries, tmp_path):
    """localize-lidar hands the first scan's capacity to open_triplet_map (its query programs
    then compile while the map is described) only where that scan is localized alone."""
    from jaxloc.cli import build_parser
    from jaxloc.cli._lidar import _first_query_capacity, triplet_config
    from jaxloc.io import open_lidar_recording

    scan = write_centroids(tmp_path / "scan.txt", queries[0])
    tiny = tmp_path / "tiny.txt"
    tiny.write_text("15 1 2 3\n17 4 5 6\n")
    poses = write_poses(tmp_path / "odometry.txt", [np.eye(4)])

    def capacity(*options, scans=(scan,)):
        argv = ["localize-lidar", str(map_dir), *map(str, scans), *options]
        args = build_parser().parse_args(argv)
        recording = open_lidar_recording(list(scans))
        return _first_query_capacity(recording, triplet_config(args), args)

    assert capacity() == (32,)  # 24 instances
    assert capacity("--track", "--odometry", str(poses)) == ()
    assert capacity("--accumulate", "2", "--odometry", str(poses)) == ()
    assert capacity(scans=(tiny,)) == ()  # too small to localize: no program runs
    broken = tmp_path / "broken.txt"
    broken.write_text("15 one two three\n")
    assert capacity(scans=(broken,)) == ()  # its error comes where it is localized
    twice = tmp_path / "twice.txt"
    twice.write_text(scan.read_text() + scan.read_text().splitlines()[0] + "\n")
    assert capacity(scans=(twice,)) == ()  # a duplicate point: localize_scan refuses it
