"""``jaxloc build-scene-graph`` and ``jaxloc localize-camera`` end to end on fixtures written in
ScanNet's formats: a scan folder becomes a map, a rendered RGB-D export folder is localized in it.
Bad inputs end with exit status 2, one line naming the file, and nothing written."""

from __future__ import annotations

import contextlib
import io
import json
import os
import re
import shutil
import subprocess
import sys

import numpy as np
import pytest
from _camera_fixtures import (
    Recording,
    room_objects,
    write_3rscan_scan,
    write_binary_ply,
    write_matrix,
    write_scannet_scan,
)

from jaxloc.camera import Camera
from jaxloc.cli import main
from jaxloc.io.scene_map import load_scene
from jaxloc.mapping import onehot_classes

FRAMES = [0, 2, 11, 30, 102, 1000]
NAMES = ["floor", "wall", "bed", "cabinet", "table", "chair"]
#: A walk of 6 frames at 1.3 m through the fixture room, turning 1.8 rad, slightly tilted.
_S = np.linspace(0.0, 1.0, len(FRAMES))
POSES = np.stack([2.6 - 0.6 * _S, 1.0 + 0.5 * _S, np.full_like(_S, 1.3), -0.3 + 1.8 * _S], 1)
TILTS = np.stack([0.1 + 0.03 * np.sin(5 * _S), 0.02 * np.cos(4 * _S)], 1)
#: Small settings: 64x48 working images, two rounds, 1000 particles, heights around 1.3 m.
LOCALIZE = ["--width", "64", "--particles", "1000", "--strides", "6", "3", "--boxes", "0.8"]
LOCALIZE += ["--heights", "1.2", "1.3", "1.4", "--no-progress"]


def run(argv, capsys):
    code = main([str(a) for a in argv])
    out = capsys.readouterr()
    return code, out.out, out.err


def assert_input_error(code, out, err, *fragments):
    assert code == 2
    assert out == ""
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    for fragment in fragments:
        assert fragment in lines[0], lines[0]


#: Raw ScanNet label ids of the fixture's classes (the label table's ``id``; table 6 is NYU40 7).
RAW_IDS = {1: 1, 2: 2, 3: 3, 4: 4, 5: 5, 7: 6}


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """(map path, sequence folder, scan folder): the fixture room as a ScanNet scan, built with
    the CLI, and a recording rendered from the built map (colour 96x72, depth 48x36 with its own
    intrinsics, one-hot patch embeddings on a 6x8 grid) written as a ScanNet export folder
    (``seq/``), a ``.sens`` (``sens/scene.sens``, frames renumbered 0..5), a 3RScan scan
    (``3rscan/scan_id``), and 16-bit label images of raw ScanNet ids (``labels/``)."""
    root = tmp_path_factory.mktemp("camera_cli")
    scan = write_scannet_scan(root, room_objects())
    out_map = root / "map.npz"
    code = main(["build-scene-graph", str(scan), str(out_map), "--format", "scannet",
                 "--target-vertices", "60"])  # fmt: skip
    assert code == 0
    scene = load_scene(out_map)
    color = Camera.from_fov(96, 72, 70.0)
    depth = Camera.from_fov(48, 36, 70.0)
    classes = onehot_classes(np.asarray(scene.labels))
    recording = Recording(scene, POSES, TILTS, color, depth, (6, 8), classes)
    recording.write_export(root / "seq", FRAMES)
    recording.write_sens(root / "sens" / "scene.sens", [10**6 * (t + 1) for t in range(6)])
    recording.write_3rscan(root / "3rscan" / "scan_id", FRAMES)
    recording.write_labels(root / "labels", FRAMES, RAW_IDS)
    return out_map, root / "seq", scan


def test_build_scene_graph_prints_objects_and_size(built, tmp_path, capsys):
    _, _, scan = built
    out_map = tmp_path / "again.npz"
    code, out, err = run(
        ["build-scene-graph", scan, out_map, "--format", "scannet", "--target-vertices", "60"],
        capsys,
    )
    assert code == 0, err
    scene = load_scene(out_map)
    first = out.splitlines()[0]
    match = re.match(r"9 objects \(6 classes\), (\d+) triangles, ([\d.]+) MB -> ", first)
    assert match, first
    assert int(match.group(1)) == scene.num_triangles
    assert float(match.group(2)) == pytest.approx(scene.storage_mb(), abs=1e-3)
    assert "one-hot per class, dimension i = class id 1 2 3 4 5 7" in out


def test_build_scene_graph_from_3rscan_and_generic(tmp_path, capsys):
    """The other two formats, with an embedding table by label (text) and by object (.npy)."""
    objects = room_objects()
    scan = write_3rscan_scan(tmp_path / "3rscan", objects)
    table = tmp_path / "labels.txt"
    table.write_text("".join(f"{label} 1 {k} 0.5\n" for k, label in enumerate(NAMES)))
    out_map = tmp_path / "3rscan.npz"
    code, out, err = run(
        ["build-scene-graph", scan, out_map, "--format", "3rscan", "--embeddings", table], capsys
    )
    assert code == 0, err
    assert out.startswith("9 objects (6 classes), ") and "embeddings: 3-d from" in out
    assert load_scene(out_map).num_objects == 9
    box = room_objects()[5][2]
    ply = tmp_path / "cloud.ply"
    instance = np.full(len(box.vertices), 4)
    colors = np.full((len(box.vertices), 3), 200, np.uint8)
    write_binary_ply(ply, box.vertices, colors, None, extra={"objectId": instance})
    (tmp_path / "objects.txt").write_text("4 5 chair\n")
    np.save(tmp_path / "by_object.npy", np.eye(5))
    out_map = tmp_path / "generic.npz"
    code, out, err = run(
        ["build-scene-graph", ply, out_map, "--format", "generic", "--objects",
         tmp_path / "objects.txt", "--embeddings", tmp_path / "by_object.npy",
         "--embeddings-by", "object"],
        capsys,
    )  # fmt: skip
    assert code == 0, err
    scene = load_scene(out_map)
    assert scene.num_objects == 1 and int(scene.labels[0]) == 5
    np.testing.assert_allclose(np.asarray(scene.embeddings[0]), np.eye(5)[4])


@pytest.fixture(scope="module")
def export_run(built, tmp_path_factory):
    """(report, figure, TUM file) of localize-camera on the export folder, with --refine, --plot
    and --poses-out: the run the layout tests compare with."""
    map_path, seq, _ = built
    out = tmp_path_factory.mktemp("export_run")
    figure, tum = out / "run.png", out / "poses.tum"
    argv = ["localize-camera", map_path, seq, *LOCALIZE, "--json", "--refine", "--plot", figure]
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        code = main([str(a) for a in argv + ["--poses-out", tum]])
    assert code == 0
    return json.loads(printed.getvalue()), figure, tum


@pytest.mark.slow
def test_localize_camera_end_to_end(built, export_run, capsys):
    """The map built from the scan localizes the rendered sequence: the JSON's poses are in the
    frames' numeric order and the last frame is within 0.15 m and 5 degrees (measured: 0.07 m,
    0.3 deg; six seeds of the same setting all ended below 0.09 m, 2.5 deg); --refine and --plot
    report; the text output prints one line per frame with its error."""
    map_path, seq, _ = built
    report, figure, _ = export_run
    assert report["frames"] == FRAMES and report["format"] == "scannet-export"
    poses = np.asarray(report["poses"])
    assert poses.shape == (len(FRAMES), 4)
    assert report["position_error_m"][-1] < 0.15
    assert report["rotation_error_deg"][-1] < 5.0
    position = np.linalg.norm(poses[-1, :3] - POSES[-1, :3])
    assert position == pytest.approx(report["position_error_m"][-1], abs=1e-4)
    assert set(report["refined"]) >= {"ok", "status", "T_world_cam", "position_error_m"}
    assert figure.stat().st_size > 10_000
    code, out, err = run(["localize-camera", map_path, seq, *LOCALIZE, "--refine"], capsys)
    assert code == 0, err
    lines = [line for line in out.splitlines() if line.startswith("frame ")]
    assert [int(line.split()[1].rstrip(":")) for line in lines] == FRAMES
    assert re.search(r"\| error [\d.]+ m, [\d.]+ deg$", lines[-1])
    # the verdict per frame, the same in the text and the JSON
    flags = [line.split(": ", 1)[1].startswith("localized") for line in lines]
    assert flags == report["localized"] and report["mode"] == "offline"
    assert f"localized: {sum(flags)} of {len(FRAMES)} frames" in out
    confidences = [float(re.search(r"confidence ([\d.]+)", line)[1]) for line in lines]
    np.testing.assert_allclose(confidences, report["confidence"], atol=0.006)
    assert "last frame: " in out and "R@0.25m,10deg" in out
    assert "refined last frame: ok" in out and "T_world_cam =" in out


def command_line_process(argv: list) -> str:
    """stdout of ``python -m jaxloc.cli ARGV`` in a fresh process, which sets itself up as a
    user's would (XLA's legacy fusion emitters, ``prefer_fast_compilation``; no cache): the
    in-process tests run on the library's default emitters."""
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "TF_CPP_MIN_LOG_LEVEL")}
    env["JAXLOC_NO_CACHE"] = "1"
    done = subprocess.run(
        [sys.executable, "-m", "jaxloc.cli", *map(str, argv)],
        capture_output=True, text=True, env=env, timeout=300,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    return done.stdout


@pytest.mark.slow
def test_the_command_lines_fast_compilation_gives_the_same_poses(built, export_run):
    """localize-camera in a process of its own (XLA's legacy fusion emitters, as a user's run)
    gives the poses and verdicts of the run in this process (the library's default emitters)."""
    map_path, seq, _ = built
    report, _, _ = export_run
    there = json.loads(
        command_line_process(["localize-camera", map_path, seq, *LOCALIZE, "--json"])
    )
    assert there["localized"] == report["localized"]
    np.testing.assert_allclose(there["poses"], report["poses"], atol=1e-5)


@pytest.mark.slow
def test_every_layout_gives_the_same_poses_and_labels_give_nearly_them(built, export_run, capsys):
    """The same frames as a ScanNet export folder, a .sens file and a 3RScan scan give the same
    poses with the same seed; label images of raw ScanNet ids (mapped to the map's NYU40 classes by
    the label table, made into embeddings with the map's stored one-hot class embeddings) give
    the same last-frame accuracy within the noise of this small setting."""
    map_path, seq, _ = built
    root = seq.parent
    reports = {"export": export_run[0]}
    for name, path in (
        ("sens", root / "sens" / "scene.sens"),
        ("3rscan", root / "3rscan" / "scan_id"),
    ):
        code, out, err = run(["localize-camera", map_path, path, *LOCALIZE, "--json"], capsys)
        assert code == 0, err
        reports[name] = json.loads(out)
    for name in ("sens", "3rscan"):
        np.testing.assert_array_equal(reports[name]["poses"], reports["export"]["poses"])
    assert reports["sens"]["frames"] == list(range(len(FRAMES)))
    labelled = root / "labelled"
    shutil.copytree(seq, labelled, ignore=shutil.ignore_patterns("embeddings"))
    code, out, err = run(
        ["localize-camera", map_path, labelled, *LOCALIZE, "--json", "--labels", root / "labels",
         "--label-table", root / "scannetv2-labels.combined.tsv", "--patches", "6", "8"],
        capsys,
    )  # fmt: skip
    assert code == 0, err
    labels = json.loads(out)
    onehot = reports["export"]
    assert labels["position_error_m"][-1] < 0.15 and labels["rotation_error_deg"][-1] < 5.0
    assert abs(labels["position_error_m"][-1] - onehot["position_error_m"][-1]) < 0.05


def test_poses_out_loads_in_evo_and_gives_jaxlocs_errors(built, export_run):
    """The TUM file of --poses-out loads with evo's own reader (timestamps = frame numbers for an
    export folder), and evo's translation APE (no alignment) against the ground truth equals
    jaxloc's per-frame position errors."""
    from evo.core import metrics, sync
    from evo.core.trajectory import PoseTrajectory3D
    from evo.tools import file_interface

    from jaxloc.io.camera_sequence import read_camera_sequence

    report, _, tum = export_run
    estimate = file_interface.read_tum_trajectory_file(str(tum))
    np.testing.assert_array_equal(estimate.timestamps, FRAMES)
    truth = read_camera_sequence(built[1])
    reference = PoseTrajectory3D(
        positions_xyz=truth.poses_gt[:, :3],
        orientations_quat_wxyz=np.tile([1.0, 0, 0, 0], (len(FRAMES), 1)),
        timestamps=np.asarray(FRAMES, np.float64),
    )
    reference, estimate = sync.associate_trajectories(reference, estimate)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((reference, estimate))
    np.testing.assert_allclose(ape.error, report["position_error_m"], atol=1e-6)
    assert ape.error[-1] < 0.15


# ----------------------------------------------------------------------------- bad inputs


def test_build_scene_graph_bad_inputs_write_nothing(built, tmp_path, capsys):
    _, _, scan = built
    bad = tmp_path / "scan" / scan.name
    shutil.copytree(scan, bad)
    shutil.copy(scan.parent / "scannetv2-labels.combined.tsv", bad.parent)
    aggregation = bad / f"{scan.name}.aggregation.json"
    data = json.loads(aggregation.read_text())
    data["segGroups"][1]["segments"] = [12345]
    aggregation.write_text(json.dumps(data))
    out_map = tmp_path / "out.npz"
    result = run(["build-scene-graph", bad, out_map, "--format", "scannet"], capsys)
    assert_input_error(*result, "aggregation.json", "names segments the mesh lacks: [12345]")
    assert not out_map.exists() and list(tmp_path.glob("out.npz*")) == []
    result = run(["build-scene-graph", tmp_path / "none", out_map, "--format", "3rscan"], capsys)
    assert_input_error(*result, "missing file", "labels.instances.annotated.v2.ply")
    result = run(["build-scene-graph", tmp_path / "x.ply", out_map, "--format", "generic"], capsys)
    assert_input_error(*result, "--format generic needs --objects FILE")
    assert not out_map.exists()


@pytest.fixture
def seq_copy(built, tmp_path):
    _, seq, _ = built
    return shutil.copytree(seq, tmp_path / "seq")


def test_localize_camera_bad_sequences(built, seq_copy, tmp_path, capsys):
    map_path = built[0]
    (seq_copy / "embeddings" / "11.npy").unlink()
    result = run(["localize-camera", map_path, seq_copy, *LOCALIZE], capsys)
    assert_input_error(*result, "missing file", "embeddings/11.npy")
    np.save(seq_copy / "embeddings" / "11.npy", np.ones((6, 8, 3)))
    result = run(["localize-camera", map_path, seq_copy, *LOCALIZE], capsys)
    assert_input_error(*result, "11.npy: embeddings have 3 dims, the map's have 6")
    shutil.copy(seq_copy / "embeddings" / "0.npy", seq_copy / "embeddings" / "11.npy")
    write_matrix(seq_copy / "pose" / "30.txt", np.diag([1.0, 1.0, 1.0, 1.0]) * 1.5)
    result = run(["localize-camera", map_path, seq_copy, *LOCALIZE], capsys)
    assert_input_error(*result, "pose/30.txt: not a rigid transform")
    (seq_copy / "pose" / "30.txt").write_text("nan 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    result = run(["localize-camera", map_path, seq_copy, *LOCALIZE], capsys)
    assert_input_error(*result, "pose/30.txt: matrix has NaN or inf values")
    shutil.copy(seq_copy / "pose" / "0.txt", seq_copy / "pose" / "30.txt")
    (seq_copy / "intrinsic" / "intrinsic_depth.txt").unlink()
    result = run(["localize-camera", map_path, seq_copy, *LOCALIZE], capsys)
    assert_input_error(*result, "depth/0.png: depth is 48x36, the colour images 96x72")


def test_localize_camera_bad_map_and_options(built, tmp_path, capsys):
    _, seq, _ = built
    broken = tmp_path / "broken.npz"
    broken.write_bytes(b"not a map")
    result = run(["localize-camera", broken, seq, *LOCALIZE], capsys)
    assert_input_error(*result, "broken.npz: not a readable jaxloc map")
    result = run(["localize-camera", built[0], seq, *LOCALIZE, "--strides", "20"], capsys)
    assert_input_error(*result, "--strides: stride 20 gives a 2 x 3 ray grid at 64 x 48", "7 x 7")
    assert_input_error(*result, "use strides of at most 7, or a larger --width, or --no-rgb")
    result = run(
        ["localize-camera", built[0], seq, *LOCALIZE, "--online", "--plot", "x.png"], capsys
    )
    assert_input_error(*result, "--plot draws the coarse-to-fine rounds")
    result = run(["localize-camera", built[0], seq, *LOCALIZE, "--refine", "--no-depth"], capsys)
    assert_input_error(*result, "--refine needs depth images", "depth")
    result = run(["localize-camera", built[0], seq, *LOCALIZE, "--heights", "nan"], capsys)
    assert_input_error(*result, "argument --heights: want finite numbers >= 0 like 1.2,1.3,1.4")


@pytest.mark.slow
def test_localize_camera_online_is_the_library_stream(built, capsys):
    """``--online`` prints what :func:`jaxloc.sg2loc.online.filter_sequence` returns for the
    recording :func:`jaxloc.io.open_camera_recording` opens: the same poses and verdicts."""
    import jax

    from jaxloc.io import open_camera_recording
    from jaxloc.sg2loc import SG2LocConfig, online
    from jaxloc.sg2loc._particles import PAPER_HEIGHTS
    from jaxloc.sg2loc._resampling import KLDConfig

    map_path, seq, _ = built
    argv = ["localize-camera", map_path, seq, *LOCALIZE, "--online", "--json"]
    code, out, err = run(argv, capsys)
    assert code == 0, err
    report = json.loads(out)
    assert report["mode"] == "online" and len(report["localized"]) == len(FRAMES)
    recording = open_camera_recording(seq, map_file=map_path, width=64)
    config = SG2LocConfig(
        capacity=1000,
        strides=(6,),
        heights=(1.2, 1.3, 1.4),
        kld=KLDConfig(min_particles=500, max_particles=1000),
    )
    assert config.heights.shape != np.shape(PAPER_HEIGHTS)
    expected = online.filter_sequence(
        jax.random.key(0), load_scene(map_path), recording.sequence, config
    )
    np.testing.assert_allclose(report["poses"], expected.pose, atol=1e-6)
    assert report["localized"] == expected.localized.tolist()
    np.testing.assert_allclose(report["confidence"], expected.verdict.confidence, atol=1e-4)


@pytest.mark.slow
def test_depth_check_is_the_library_check_and_is_printed_per_frame(built, capsys):
    """``--depth-check`` adds :func:`jaxloc.sg2loc.depth_blind_check`'s ``passed`` for the
    recording and settings of the run, per frame in the JSON and in the text; without depth or
    with ``--online`` it is a one-line error."""
    import jax

    from jaxloc.io import open_camera_recording
    from jaxloc.sg2loc import SG2LocConfig, depth_blind_check, kld_for_capacity

    map_path, seq, _ = built
    argv = ["localize-camera", map_path, seq, *LOCALIZE, "--depth-check"]
    code, out, err = run([*argv, "--json"], capsys)
    assert code == 0, err
    report = json.loads(out)
    recording = open_camera_recording(seq, map_file=map_path, width=64)
    config = SG2LocConfig(
        capacity=1000,
        strides=(6, 3),
        box_half_widths=(0.8,),
        heights=(1.2, 1.3, 1.4),
        kld=kld_for_capacity(1000),
    )
    expected = depth_blind_check(
        jax.random.key(0), load_scene(map_path), recording.sequence, config
    )
    assert report["depth_check"] == np.asarray(expected.passed).tolist()
    assert any(report["depth_check"]), "the fixture's walk passes the check on some frame"
    code, out, err = run(argv, capsys)
    lines = [line for line in out.splitlines() if line.startswith("frame ")]
    checked = [re.search(r"depth check (passed|failed)", line)[1] == "passed" for line in lines]
    assert code == 0 and checked == report["depth_check"]
    assert f"depth check passed: {sum(checked)} frames" in out
    result = run([*argv, "--online"], capsys)
    assert_input_error(*result, "--depth-check checks the coarse-to-fine rounds")
    result = run([*argv, "--no-depth"], capsys)
    assert_input_error(*result, "--depth-check needs depth images", "--no-depth")
