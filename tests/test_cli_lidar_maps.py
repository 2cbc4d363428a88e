"""``jaxloc build-lidar-map`` and ``localize-lidar`` on a sequence folder and a saved map, end to
end: a synthetic SemanticKITTI sequence of a known world is turned into a map, which then
localizes the sequence's own scans; bad sequences exit with status 2 and write nothing."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from jaxloc.cli import main
from jaxloc.synthetic.lidar_scans import make_lidar_sequence, write_semantickitti_sequence
from jaxloc.synthetic.outdoor import make_outdoor_world


def run(argv, capsys):
    code = main([str(a) for a in argv])
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.fixture(scope="module")
def sequence_dir(tmp_path_factory) -> Path:
    world = make_outdoor_world("dense", seed=2, blocks=1, bridge_length=0)
    scans = make_lidar_sequence(world, (10.0, 0.0), (190.0, 0.0), 16, seed=3, max_range=30.0)
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
        for key in ("T_map_scan", "valid", "clique_size", "rte_m", "rre_deg"):
            assert a[key] == b[key], key
    assert from_saved["summary"]["map_build_s"] < 5.0  # loaded, not described again
    code, out, err = run(["localize-lidar", built_saved, *argv], capsys)
    assert code == 0, err
    assert json.loads(out)["summary"]["success_rate"] >= 0.75


def test_saved_map_refuses_descriptor_options(built, sequence_dir, capsys):
    code, _, err = run(["localize-lidar", built[1], sequence_dir, "--scales", "1"], capsys)
    assert code == 2 and "a saved map keeps the descriptors" in err


def _bad_sequences(sequence_dir: Path, root: Path) -> dict[str, tuple[Path, str]]:
    """name -> (sequence folder, expected part of the message) of one bad input each."""

    def copy(name: str) -> Path:
        target = root / name
        shutil.copytree(sequence_dir, target)
        return target

    cases = {"missing folder": (root / "absent", "no such sequence folder")}
    no_poses = copy("no_poses")
    (no_poses / "poses.txt").unlink()
    cases["no poses"] = (no_poses, "poses.txt: missing poses")
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
    from jaxloc.m2loc import m2loc_config

    parser = build_parser()
    default = triplet_config(parser.parse_args(["localize-lidar", "map", "scan.bin"]))
    published = triplet_config(
        parser.parse_args(["localize-lidar", "map", "scan.bin", "--no-robust"])
    )
    assert default == m2loc_config(3)
    assert (default.one_to_one, default.hypotheses) == (True, 256)
    assert published == m2loc_config(3, robust=False)
