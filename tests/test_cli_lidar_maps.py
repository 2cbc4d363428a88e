"""``jaxloc build-lidar-map`` and ``localize-lidar`` on a sequence folder and a saved map, end to
end: a synthetic SemanticKITTI sequence of a known world is turned into a map, which then
localizes the sequence's own scans; bad sequences exit with status 2 and write nothing.

The same scans in the HeLiPR / TripletLoc layout (``tests/_helipr_fixtures.py``) build the same
map and localize the same way (one run per pose format, reusing the compiled programs of the
SemanticKITTI run: the maps have the same sizes); the ``--poses-out`` files are read with evo's
own readers and its APE (no alignment, translation part) equals jaxloc's RTE."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from _drive_records import assert_same, cli_json
from _helipr_fixtures import FIRST_STAMP, PERIOD_NS, ns_to_seconds, tum_line, write_helipr_sequence

from jaxloc.cli import main
from jaxloc.io import open_lidar_recording, open_triplet_map
from jaxloc.io.lidar_sequence import open_lidar_sequence
from jaxloc.m2loc import localize_drive, m2loc_config
from jaxloc.m2loc._accumulation import WINDOW_MIN_CLIQUE, WINDOW_MIN_INSTANCES
from jaxloc.m2loc._evaluation import format_record as _format_record
from jaxloc.synthetic.lidar_scans import make_lidar_sequence, write_semantickitti_sequence
from jaxloc.synthetic.outdoor import make_outdoor_world


def run(argv, capsys):
    code = main([str(a) for a in argv])
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.fixture(scope="module")
def scans():
    world = make_outdoor_world("dense", seed=2, blocks=1, bridge_length=0)
    return make_lidar_sequence(world, (10.0, 0.0), (190.0, 0.0), 16, seed=3, max_range=30.0)


@pytest.fixture(scope="module")
def sequence_dir(scans, tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("sequence")
    write_semantickitti_sequence(root, scans)
    return root


@pytest.fixture(scope="module")
def built(sequence_dir, tmp_path_factory):
    """(map folder, saved map) written by one build-lidar-map run."""
    out = tmp_path_factory.mktemp("built")
    saved = out / "described.npz"
    code = main(
        [
            "build-lidar-map",
            str(sequence_dir),
            str(out / "map"),
            "--every",
            "2",
            "--save-map",
            str(saved),
            "--no-progress",
        ]
    )
    assert code == 0
    return out / "map", saved


def test_build_writes_the_map_files(built):
    folder, saved = built
    for name in ("instances/15.txt", "instances/17.txt", "instances/18.txt", "RSN/road_normal.txt"):
        assert (folder / name).stat().st_size > 0, name
    assert saved.stat().st_size > 0


def test_built_map_localizes_its_own_sequence(built, sequence_dir, tmp_path, capsys):
    """Ground truth comes from the sequence; a map saved by localize-lidar --save-map gives
    results identical to the folder it was described from; the map build-lidar-map saved (from
    the unrounded centroids) localizes as well."""
    folder, built_saved = built
    saved = tmp_path / "from_folder.npz"
    argv = [sequence_dir, "--every", "5", "--json", "--no-progress"]
    code, out, err = run(["localize-lidar", folder, *argv, "--save-map", saved], capsys)
    assert code == 0, err
    from_folder = json.loads(out)
    code, out, err = run(["localize-lidar", saved, *argv], capsys)
    assert code == 0, err
    from_saved = json.loads(out)
    assert len(from_folder["scans"]) == 4  # scans 0, 5, 10, 15
    assert from_folder["summary"]["success_rate"] >= 0.75, from_folder["scans"]
    for a, b in zip(from_folder["scans"], from_saved["scans"], strict=True):
        for key in ("T_map_scan", "valid", "ambiguous", "clique_size", "rte_m", "rre_deg"):
            assert a[key] == b[key], key
        assert not (a["valid"] and a["ambiguous"])  # an ambiguous pose is never reported valid
    assert from_saved["summary"]["map_build_s"] < 5.0  # loaded, not described again
    code, out, err = run(["localize-lidar", built_saved, *argv], capsys)
    assert code == 0, err
    assert json.loads(out)["summary"]["success_rate"] >= 0.75


def test_saved_map_refuses_descriptor_options(built, sequence_dir, capsys):
    code, _, err = run(["localize-lidar", built[1], sequence_dir, "--scales", "1"], capsys)
    assert code == 2 and "a saved map keeps the descriptors" in err


def test_no_robust_applies_to_a_saved_robust_map(built, sequence_dir, capsys):
    """--no-robust on a map saved with m2loc_config's robust settings (their uniqueness check
    needs clique hypotheses, which --no-robust turns off) runs M2Loc as published."""
    argv = [sequence_dir, "--every", "10", "--json", "--no-progress", "--no-robust"]
    code, out, err = run(["localize-lidar", built[1], *argv], capsys)
    assert code == 0, err
    assert len(json.loads(out)["scans"]) == 2


def _bad_sequences(sequence_dir: Path, root: Path) -> dict[str, tuple[Path, str]]:
    """name -> (sequence folder, expected part of the message) of one bad input each."""

    def copy(name: str) -> Path:
        target = root / name
        shutil.copytree(sequence_dir, target)
        return target

    cases = {"missing folder": (root / "absent", "no such sequence folder")}
    no_poses = copy("no_poses")
    (no_poses / "poses.txt").unlink()
    cases["no poses"] = (no_poses, "no poses to place the scans by (its pose file")
    few = copy("few_poses")
    lines = (few / "poses.txt").read_text().splitlines()
    (few / "poses.txt").write_text("\n".join(lines[:-1]) + "\n")
    cases["fewer poses than scans"] = (few, "poses.txt: 15 poses for 16 scans")
    calib = copy("bad_calib")
    (calib / "calib.txt").write_text("P0: 1 2 3\n")
    cases["malformed calib"] = (calib, "calib.txt:1: expected 'KEY: 12 numbers'")
    short = copy("short_labels")
    label = short / "labels" / "000004.label"
    label.write_bytes(label.read_bytes()[:-8])
    cases["label length"] = (short, "000004.label")
    no_label = copy("no_label")
    (no_label / "labels" / "000002.label").unlink()
    cases["missing label file"] = (no_label, "000002.label: missing label file")
    nan = copy("nan_points")
    scan = np.fromfile(nan / "velodyne" / "000000.bin", "<f4")
    scan[5] = np.nan
    scan.tofile(nan / "velodyne" / "000000.bin")
    cases["NaN point"] = (nan, "000000.bin: non-finite point coordinates")
    nonrigid = copy("nonrigid_pose")
    rows = (nonrigid / "poses.txt").read_text().splitlines()
    rows[3] = " ".join(["2"] + rows[3].split()[1:])
    (nonrigid / "poses.txt").write_text("\n".join(rows) + "\n")
    cases["non-rigid pose"] = (nonrigid, "poses.txt: pose 4 is not rigid")
    road_only = copy("road_only")
    for path in (road_only / "labels").glob("*.label"):
        words = np.fromfile(path, "<u4")
        np.where((words & 0xFFFF) == 40, words, np.uint32(50)).astype("<u4").tofile(path)
    cases["no graph-class points"] = (road_only, "no instance of the classes")
    return cases


def test_bad_sequences_exit_2_and_write_nothing(sequence_dir, tmp_path, capsys):
    for name, (folder, expected) in _bad_sequences(sequence_dir, tmp_path).items():
        out = tmp_path / "out" / name.replace(" ", "_")
        code, _, err = run(
            ["build-lidar-map", folder, out, "--every", "4", "--no-progress"], capsys
        )
        assert code == 2, (name, err)
        assert err.startswith("jaxloc build-lidar-map: error: "), (name, err)
        assert expected in err, (name, err)
        assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, name
        assert not out.exists(), name


def test_save_map_path_is_checked_before_any_work(sequence_dir, built, tmp_path, capsys):
    out = tmp_path / "map"
    argv = ["build-lidar-map", sequence_dir, out, "--save-map", tmp_path / "map.txt"]
    code, _, err = run(argv, capsys)
    assert code == 2 and "must end in .npz" in err and not out.exists()
    argv = ["localize-lidar", built[0], sequence_dir, "--save-map", tmp_path / "map.txt"]
    code, _, err = run(argv, capsys)
    assert code == 2 and "must end in .npz" in err


def test_no_robust_is_m2loc_as_published():
    from jaxloc.cli import build_parser
    from jaxloc.cli._lidar import triplet_config

    parser = build_parser()
    default = triplet_config(parser.parse_args(["localize-lidar", "map", "scan.bin"]))
    published = triplet_config(
        parser.parse_args(["localize-lidar", "map", "scan.bin", "--no-robust"])
    )
    assert default == m2loc_config(3)
    assert (default.one_to_one, default.hypotheses) == (True, 256)
    assert published == m2loc_config(3, robust=False)


@pytest.mark.parametrize(
    ("accumulate", "track"), [(1, False), (3, True)], ids=["single", "accumulate_and_track"]
)
def test_localize_lidar_is_localize_drive(built, sequence_dir, accumulate, track):
    """The command passes --accumulate and --track to ``localize_drive`` as they are: the same
    flags, poses, cliques, windows and tracking states as the library on the same recording (each
    mode alone is checked against its building blocks in tests/test_m2loc_drive.py). The scans
    (--every 5), maps and settings are those of the tests above, so their programs are reused:
    the saved map for single scans, the folder with one scale and M2Loc as published for
    tracking."""
    folder, saved = built
    argv = [sequence_dir, "--every", "5", "--json", "--no-progress"]
    if track:
        argv += ["--scales", "1", "--no-robust", "--accumulate", str(accumulate), "--track"]
        triplet_map = open_triplet_map(folder, m2loc_config(1, robust=False))
    else:
        triplet_map = open_triplet_map(saved)
    records = cli_json(["localize-lidar", folder if track else saved, *argv])
    recording = open_lidar_recording(sequence_dir, every=5)
    result = localize_drive(triplet_map, recording, accumulate=accumulate, track=track)
    assert_same(records, result, track)
    assert sum(r["valid"] for r in records) >= 3, records


# ----------------------------------------------------------------------------- HeLiPR layout


@pytest.fixture(scope="module")
def helipr_dir(scans, tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("helipr") / "Town01"
    write_helipr_sequence(root, scans)
    return root


def _stamps(count: int) -> list[int]:
    return [FIRST_STAMP + PERIOD_NS * i for i in range(count)]


def _evo_ape(reference, estimate) -> np.ndarray:
    """evo_ape's default: the translation part, no alignment (evo.core.metrics.APE)."""
    from evo.core import metrics

    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((reference, estimate))
    return np.asarray(ape.error)


def test_helipr_sequence_end_to_end_with_evo(scans, built, helipr_dir, tmp_path, capsys):
    from evo.core import sync
    from evo.core.trajectory import PosePath3D
    from evo.tools.file_interface import read_kitti_poses_file, read_tum_trajectory_file

    out = tmp_path / "map"
    code, stdout, err = run(
        ["build-lidar-map", helipr_dir, out, "--every", "2", "--no-progress"], capsys
    )
    assert code == 0, err
    assert "(helipr, Ouster): 8 of 16 scans used" in stdout
    for name in ("instances/15.txt", "instances/17.txt", "instances/18.txt", "RSN/road_normal.txt"):
        ours, theirs = np.loadtxt(out / name, ndmin=2), np.loadtxt(built[0] / name, ndmin=2)
        np.testing.assert_allclose(ours, theirs, atol=2e-6, err_msg=name)  # KITTI's %.9e poses

    tum = tmp_path / "estimate.tum"
    argv = ["localize-lidar", out, helipr_dir, "--every", "5", "--json", "--no-progress"]
    code, stdout, err = run([*argv, "--poses-out", tum], capsys)
    assert code == 0, err
    records = json.loads(stdout)["scans"]
    stamps = _stamps(16)[::5]
    assert [r["timestamp_ns"] for r in records] == stamps
    assert json.loads(stdout)["summary"]["success_rate"] >= 0.75

    # the reference, written here in TUM seconds from the true poses
    reference_path = tmp_path / "reference.tum"
    lines = [
        tum_line(ns_to_seconds(t), p) for t, p in zip(_stamps(16), scans.T_map_scan, strict=True)
    ]
    reference_path.write_text("\n".join(lines) + "\n")
    reference = read_tum_trajectory_file(str(reference_path))
    estimate = read_tum_trajectory_file(str(tum))
    valid = [r for r in records if r["valid"]]
    assert len(estimate.timestamps) == len(valid)  # TUM: the valid scans only
    reference, estimate = sync.associate_trajectories(reference, estimate, max_diff=0.01)
    np.testing.assert_allclose(_evo_ape(reference, estimate), [r["rte_m"] for r in valid],
                               atol=1e-9)  # fmt: skip

    # KITTI out, ground truth from a TUM file in seconds matched by time: the same errors
    kitti = tmp_path / "estimate.kitti"
    code, stdout, err = run(
        [*argv, "--poses-out", kitti, "--pose-format", "kitti", "--gt", reference_path], capsys
    )
    assert code == 0, err
    again = json.loads(stdout)["scans"]
    for a, b in zip(records, again, strict=True):
        assert a["valid"] == b["valid"] and abs(a["rte_m"] - b["rte_m"]) < 1e-6, (a, b)
    single = helipr_dir / "LiDAR" / "Ouster" / f"{stamps[1]}.bin"  # one scan, its stamp kept
    code, stdout, err = run(
        ["localize-lidar", out, single, "--gt", reference_path, "--json", "--no-progress"], capsys
    )
    assert code == 0, err
    alone = json.loads(stdout)["scans"][0]
    assert alone["timestamp_ns"] == stamps[1] and abs(alone["rte_m"] - records[1]["rte_m"]) < 1e-6
    estimate = read_kitti_poses_file(str(kitti))
    assert estimate.num_poses == len(again)  # KITTI: every scan, in order
    truth = PosePath3D(poses_se3=list(scans.T_map_scan[::5]))
    np.testing.assert_allclose(_evo_ape(truth, estimate), [r["rte_m"] for r in again],
                               atol=1e-6)  # fmt: skip


def test_helipr_notes_and_bad_inputs(scans, helipr_dir, tmp_path, capsys):
    """A scan without a GT line is left out with a note; malformed HeLiPR files exit 2 with one
    line naming the file."""

    def copy(name: str) -> Path:
        target = tmp_path / name
        shutil.copytree(helipr_dir, target)
        return target

    gt_name = "LiDAR_GT/Ouster_gt.txt"
    partial = copy("partial")
    lines = (partial / gt_name).read_text().splitlines()
    (partial / gt_name).write_text("\n".join(lines[1:]) + "\n")
    code, _, err = run(["build-lidar-map", partial, tmp_path / "p", "--no-progress"], capsys)
    assert code == 0, err
    assert "note: " in err and "1 scan(s) without a pose at their time left out" in err

    cases = {}
    truncated = copy("truncated")
    scan = truncated / "LiDAR" / "Ouster" / f"{FIRST_STAMP}.bin"
    scan.write_bytes(scan.read_bytes()[:-3])
    cases["truncated scan"] = ([truncated], f"{FIRST_STAMP}.bin: ")
    nan = copy("nan_gt")
    rows = (nan / gt_name).read_text().splitlines()
    rows[2] = " ".join([*rows[2].split()[:3], "nan", *rows[2].split()[4:]])
    (nan / gt_name).write_text("\n".join(rows) + "\n")
    cases["NaN in the GT"] = ([nan], "Ouster_gt.txt:3: pose has NaN or inf")
    units = copy("units")
    rows = (units / gt_name).read_text().splitlines()
    seconds = [" ".join([ns_to_seconds(int(r.split()[0])), *r.split()[1:]]) for r in rows]
    (units / gt_name).write_text("\n".join(seconds) + "\n")
    cases["GT stamps in seconds"] = ([units], "is not an integer (ns)")
    label = copy("short_label")
    path = label / "labels" / f"{FIRST_STAMP + 3 * PERIOD_NS}.label"
    path.write_bytes(path.read_bytes()[:-4])
    cases["short label file"] = ([label, "--every", "3"], "labels for")
    cases["absent sensor"] = ([helipr_dir, "--sensor", "Avia"], "no scans in LiDAR/Avia/")
    cases["forced layout"] = ([helipr_dir, "--format", "semantickitti"], "calib.txt: missing")
    for name, (argv, expected) in cases.items():
        command = ["build-lidar-map", argv[0], tmp_path / "x", *argv[1:], "--no-progress"]
        code, _, err = run(command, capsys)
        assert code == 2, (name, err)
        assert err.startswith("jaxloc build-lidar-map: error: ") and expected in err, (name, err)
        assert len(err.strip().splitlines()) == 1, (name, err)
        assert not (tmp_path / "x").exists(), name


def test_accumulate_fuses_the_last_scans_through_odometry(built, sequence_dir, tmp_path, capsys):
    """--accumulate 3 localizes each scan with the two before it (odometry: the sequence's poses,
    or the same poses from --odometry, with the same results), and with older ones while the
    window holds fewer than --window-instances (up to --accumulate-max); bad values exit 2."""
    saved = built[1]
    argv = [sequence_dir, "--every", "5", "--json", "--no-progress", "--accumulate", "3"]
    fused_scans = {}
    for instances in (0, 1000, None):
        grow = [] if instances is None else ["--window-instances", str(instances)]
        code, out, err = run(["localize-lidar", saved, *argv, *grow], capsys)
        assert code == 0, err
        fused_scans[instances] = [s.get("fused_scans", 1) for s in json.loads(out)["scans"]]
    assert fused_scans[0] == [1, 2, 3, 3]  # a fixed window of 3
    assert fused_scans[1000] == [1, 2, 3, 4]  # grown to every scan so far (the bound is 6)
    fused = json.loads(out)  # the default, WINDOW_MIN_INSTANCES
    scans = fused["scans"]
    for i, record in enumerate(scans[1:], start=1):
        scans_so_far = i + 1
        assert min(3, scans_so_far) <= fused_scans[None][i] <= scans_so_far
        if fused_scans[None][i] > min(3, scans_so_far):  # grown: to enough, or to every scan
            assert record["fused_scans"] == scans_so_far or (
                record["fused_instances"] >= WINDOW_MIN_INSTANCES
            )
    for record in scans[1:]:
        assert record["instances"] < record["fused_instances"]
        # a window's pose rests on more than the minimal set, or is refused and says so
        assert not record["valid"] or record["clique_size"] >= WINDOW_MIN_CLIQUE
        if record["small_clique"]:
            assert not record["valid"] and record["clique_size"] < WINDOW_MIN_CLIQUE
        assert (" needs a clique of" in _format_record(record)) == record["small_clique"]
    assert "small_clique" not in scans[0]
    assert fused["summary"]["success_rate"] >= 0.75, scans
    # --odometry: LiDAR-frame poses (poses.txt holds KITTI's cam0 poses), one per scan localized
    poses = open_lidar_sequence(sequence_dir).T_map_scan[::5]
    odometry = tmp_path / "odometry.txt"
    np.savetxt(odometry, poses[:, :3].reshape(len(poses), 12))
    code, out, err = run(["localize-lidar", saved, *argv, "--odometry", odometry], capsys)
    assert code == 0, err
    again = json.loads(out)["scans"]
    for a, b in zip(scans, again, strict=True):
        assert a["T_map_scan"] == b["T_map_scan"] and a["valid"] == b["valid"]
    for bad, message in (
        (["--accumulate", "0"], "argument --accumulate: want an integer >= 1, got '0'"),
        (["--odometry", odometry], "only used with --accumulate"),
        (["--window-instances", "5"], "--window-instances is only used with --accumulate K > 1"),
        (
            ["--accumulate", "3", "--accumulate-max", "2"],
            "--accumulate-max must be >= --accumulate",
        ),
        (
            ["--accumulate", "2", "--window-instances", "-1"],
            "argument --window-instances: want an integer >= 0, got '-1'",
        ),
    ):
        code, _, err = run(["localize-lidar", saved, sequence_dir, *bad], capsys)
        assert code == 2 and message in err, err


def test_track_follows_the_sequence_after_the_first_fix(built, sequence_dir, capsys):
    """--track: the first scan's global pose is confirmed by the second's, the next ones are
    localized near the odometry prediction (the sequence's poses), each record saying how; the
    poses agree with one-shot localization."""
    folder = built[0]
    argv = [sequence_dir, "--every", "5", "--no-progress", "--scales", "1", "--no-robust"]
    code, out, err = run(["localize-lidar", folder, *argv, "--json"], capsys)
    assert code == 0, err
    alone = json.loads(out)["scans"]
    code, out, err = run(["localize-lidar", folder, *argv, "--json", "--track"], capsys)
    assert code == 0, err
    tracked = json.loads(out)
    modes = [s["track"] for s in tracked["scans"]]
    assert modes == ["pending", "relocalized", "tracked", "tracked"]
    assert tracked["summary"]["success_rate"] == 0.75  # the first pose waits for confirmation
    for a, b in zip(alone, tracked["scans"], strict=True):
        if a["valid"] and b["valid"]:
            assert abs(a["rte_m"] - b["rte_m"]) < 0.3 and abs(a["rre_deg"] - b["rre_deg"]) < 1.0
    code, out, _ = run(["localize-lidar", folder, *argv, "--track"], capsys)
    assert code == 0
    for words in ("pending, ", "relocalized, ", "tracked, ", "local associations"):
        assert words in out
