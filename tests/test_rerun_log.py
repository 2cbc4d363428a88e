"""``jaxloc.io.rerun_log``: an SG2Loc run and an M2Loc drive written as Rerun recordings (``.rrd``)
and read back with Rerun's own reader (``rerun.chunk.RrdReader``): the entities logged, how many
rows each has on the ``frame`` timeline, and the particles and poses they hold; ``rerun rrd
verify`` (the viewer's loader) accepts the file.

The runs are built from arrays (no filter or query is compiled): a two-object scene graph, an
``SG2LocResult`` of 2 rounds x 3 frames x 6 particle slots, a 3-frame query, an M2Loc
``DriveResult`` of 3 scans."""

from __future__ import annotations

import builtins
import subprocess
import sys

import numpy as np
import pytest
import trimesh

from jaxloc.camera import Camera
from jaxloc.io.instance_maps import InstanceMap
from jaxloc.io.rerun_log import class_colors, write_drive_rerun, write_rerun
from jaxloc.m2loc import DriveResult, TrackStatus
from jaxloc.m2loc._drive import DriveStep, ScanInstances
from jaxloc.scene import SceneGraph
from jaxloc.sg2loc import FrameSequence, SG2LocResult
from jaxloc.sg2loc.online import Estimate

rerun_chunk = pytest.importorskip("rerun.chunk")

ROUNDS, FRAMES, SLOTS = 2, 3, 6


def _read(path) -> dict[str, list]:
    """entity path -> its chunks' record batches, from the file."""
    out: dict[str, list] = {}
    for chunk in rerun_chunk.RrdReader(path).stream().to_chunks():
        out.setdefault(chunk.entity_path, []).append(chunk.to_record_batch())
    return out


def _rows(batches, column: str) -> list:
    """The values of ``column`` over the entity's rows, in ``frame`` order (static rows first)."""
    rows = []
    for batch in batches:
        if column not in batch.schema.names:
            continue
        frames = batch.column("frame").to_pylist() if "frame" in batch.schema.names else None
        values = batch.column(column).to_pylist()
        rows += list(zip(frames or [-1] * len(values), values, strict=True))
    return [value for _, value in sorted(rows, key=lambda row: row[0])]


@pytest.fixture(scope="module")
def sg2loc_run():
    boxes = [trimesh.creation.box(extents=(1, 1, 1)), trimesh.creation.box(extents=(2, 1, 0.5))]
    boxes[1].apply_translation([3.0, 0.0, 0.0])
    scene = SceneGraph.from_meshes(boxes, [4, 7], np.eye(2))
    rng = np.random.default_rng(0)
    particles = rng.uniform(-2, 2, (ROUNDS, FRAMES, SLOTS, 4))
    weights = rng.uniform(0.1, 1.0, (ROUNDS, FRAMES, SLOTS))
    weights[:, :, 4:] = 0.0  # inactive slots
    weights[1, 2, 1:] = 0.0  # one particle left
    mle = particles[:, :, 0, :]
    result = SG2LocResult(
        poses=mle[-1], localized=np.array([False, True, True]), round_mle=mle,
        round_start=np.zeros((ROUNDS, 4)), num_particles=np.full((ROUNDS, FRAMES), 4),
        info=None, particles=particles, particle_weights=weights, used_depth=True,
        used_color=True,
    )  # fmt: skip
    camera = Camera(20.0, 20.0, 15.5, 11.5, 32, 24)
    sequence = FrameSequence(
        camera,
        np.zeros((FRAMES, 2, 2, 2)),
        np.zeros((FRAMES - 1, 4)),
        depth=rng.uniform(0.5, 3.0, (FRAMES, 24, 32)),
        rgb=rng.uniform(0, 1, (FRAMES, 24, 32, 3)),
    )
    poses_gt = mle[-1] + [0.1, 0.0, 0.0, 0.05]
    return scene, result, sequence, poses_gt


def test_an_sg2loc_run_reads_back_as_logged(sg2loc_run, tmp_path):
    scene, result, sequence, poses_gt = sg2loc_run
    path = write_rerun(tmp_path / "run.rrd", scene, result, sequence, poses_gt,
                       timestamps=1e9 + np.arange(FRAMES) * 0.1)  # fmt: skip
    assert path.is_file() and not list(tmp_path.glob("*.tmp"))
    verify = subprocess.run(  # the viewer's own loader (rerun-sdk ships the CLI)
        [sys.executable, "-m", "rerun", "rrd", "verify", str(path)], capture_output=True, text=True
    )
    assert verify.returncode == 0, verify.stderr
    found = _read(path)
    for entity in ("/world", "/world/map/objects/0", "/world/map/objects/1",
                   "/world/trajectory/estimate", "/world/trajectory/gt",
                   "/world/trajectory/estimate/current", "/world/trajectory/gt/current",
                   "/world/camera", "/world/camera/image", "/world/camera/image/rgb",
                   "/world/camera/image/depth", "/plots/localized",
                   "/plots/position_error_m"):  # fmt: skip
        assert entity in found, (entity, sorted(found))
    mesh = _rows(found["/world/map/objects/1"], "Mesh3D:vertex_positions")[0]
    assert len(mesh) == 3 * 12  # a box: 12 triangles, unshared corners
    colors = _rows(found["/world/map/objects/1"], "Mesh3D:vertex_colors")[0]
    expected = class_colors([7])[0]
    assert (
        colors[0]
        == (int(expected[0]) << 24) | (int(expected[1]) << 16) | (int(expected[2]) << 8) | 255
    )
    for r in range(ROUNDS):
        counts = [len(p) for p in _rows(found[f"/world/particles/round_{r}"], "Points3D:positions")]
        assert counts == [4, 4, 1] if r == 1 else [4] * FRAMES
        arrows = _rows(found[f"/world/particles/round_{r}/mle"], "Arrows3D:origins")
        np.testing.assert_allclose(np.asarray(arrows)[:, 0], result.round_mle[r, :, :3], atol=1e-6)
    first = np.asarray(_rows(found["/world/particles/round_0"], "Points3D:positions")[0])
    np.testing.assert_allclose(first, result.particles[0, 0, :4, :3], atol=1e-6)
    current = np.asarray(_rows(found["/world/trajectory/estimate/current"], "Arrows3D:origins"))
    np.testing.assert_allclose(current[:, 0], result.poses[:, :3], atol=1e-6)
    assert len(_rows(found["/world/trajectory/estimate"], "LineStrips3D:strips")[0]) == FRAMES - 1
    assert [v[0] for v in _rows(found["/plots/localized"], "Scalars:scalars")] == [0, 1, 1]
    errors = _rows(found["/plots/position_error_m"], "Scalars:scalars")  # localized frames only
    np.testing.assert_allclose(np.ravel(errors), [0.1, 0.1], atol=1e-6)
    assert len(_rows(found["/world/camera/image/depth"], "DepthImage:buffer")) == FRAMES
    assert len(_rows(found["/world/camera"], "Transform3D:translation")) == FRAMES


def test_a_streamed_run_has_poses_and_no_particles(sg2loc_run, tmp_path):
    """The stacked estimates of ``online.filter_sequence`` (``pose``, ``localized``)."""
    scene, result, sequence, _ = sg2loc_run
    estimates = Estimate(result.poses, result.localized, *([None] * 6))
    found = _read(write_rerun(tmp_path / "online.rrd", scene, estimates, sequence))
    assert not any(entity.startswith("/world/particles") for entity in found)
    current = _rows(found["/world/trajectory/estimate/current"], "Arrows3D:origins")
    np.testing.assert_allclose(np.asarray(current)[:, 0], result.poses[:, :3], atol=1e-6)
    assert len(_rows(found["/world/camera/image/rgb"], "EncodedImage:blob")) == FRAMES


def test_an_m2loc_drive_reads_back_as_logged(tmp_path):
    rng = np.random.default_rng(1)
    instance_map = InstanceMap(rng.uniform(-50, 50, (20, 3)), rng.choice([40, 50, 70], 20),
                               np.arange(20))  # fmt: skip
    poses = np.repeat(np.eye(4)[None], 3, 0)
    poses[:, 0, 3] = [0.0, 5.0, 10.0]
    status = [int(TrackStatus.RELOCALIZED), int(TrackStatus.LOST), int(TrackStatus.TRACKED)]
    steps = tuple(
        DriveStep(None, s, ScanInstances(rng.uniform(-10, 10, (5, 3)), np.full(5, 40)), None,
                  False, 0.0, 0.0)
        for s in status
    )  # fmt: skip
    valid = np.array([True, False, True])
    drive = DriveResult(poses, valid, np.array(status), np.ones(3), np.zeros(3), np.zeros(3),
                        np.zeros(3), steps)  # fmt: skip
    path = write_drive_rerun(tmp_path / "drive.rrd", instance_map, drive)
    found = _read(path)
    points = np.asarray(_rows(found["/world/map/instances"], "Points3D:positions")[0])
    np.testing.assert_allclose(points, instance_map.points, atol=1e-5)
    scans = _rows(found["/world/scan/instances"], "Points3D:positions")
    assert [len(s) for s in scans] == [5, 5]  # the lost scan has no pose to place it by
    np.testing.assert_allclose(
        np.asarray(scans[1]), steps[2].instances.points + [10.0, 0, 0], atol=1e-5
    )
    labels = _rows(found["/world/trajectory/estimate/current"], "Arrows3D:labels")
    assert [label[0] for label in labels if label] == ["relocalized", "tracked"]  # lost: cleared
    assert "/world/trajectory/gt" not in found
    assert not _rows(found.get("/world/trajectory/estimate", []), "LineStrips3D:strips")
    gt = poses + [[0, 0, 0, 0.5], [0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0]]
    path = write_drive_rerun(tmp_path / "gt.rrd", instance_map, drive, gt,
                             has_gt=[True, True, False])  # fmt: skip
    found = _read(path)
    strip = np.asarray(_rows(found["/world/trajectory/gt"], "LineStrips3D:strips")[0][0])
    np.testing.assert_allclose(strip, gt[:2, :3, 3], atol=1e-6)
    scans = _rows(found["/world/scan/instances"], "Points3D:positions")  # the lost one: by gt
    np.testing.assert_allclose(np.asarray(scans[1]), steps[1].instances.points + gt[1, :3, 3],
                               atol=1e-5)  # fmt: skip
    errors = _rows(found["/plots/position_error_m"], "Scalars:scalars")
    np.testing.assert_allclose(np.ravel(errors), [0.5], atol=1e-6)
    origins, eye = _layout(path)  # the map from above one side, its centre in view
    assert origins == ["plots/localized", "plots/position_error_m", "plots/rotation_error_deg",
                       "world"]  # fmt: skip
    assert eye["position"][2] > instance_map.points[:, 2].max() + 50


def _layout(path) -> tuple[list[str], dict[str, np.ndarray]]:
    """The views' origins and the 3D view's eye (``position``, ``look_target``) of the recording's
    default layout (its blueprint store)."""
    reader = rerun_chunk.RrdReader(path)
    (store,) = reader.blueprints()
    origins, eye = [], {}
    for chunk in reader.stream(store=store).to_chunks():
        batch = chunk.to_record_batch()
        if "ViewBlueprint:space_origin" in batch.schema.names:
            origins += [row[0] for row in batch.column("ViewBlueprint:space_origin").to_pylist()]
        for key in ("position", "look_target"):
            if f"EyeControls3D:{key}" in batch.schema.names:
                eye[key] = np.asarray(batch.column(f"EyeControls3D:{key}").to_pylist()[0][0])
    return sorted(origins), eye


def test_a_recording_opens_on_its_layout_and_reads_as_any_file(sg2loc_run, tmp_path):
    """The default layout: the world in 3D (seen from inside the map's and the trajectory's
    bounds, looking at the trajectory), the colour and depth images, the plots; the file's mode
    is the other writers'."""
    scene, result, sequence, poses_gt = sg2loc_run
    path = write_rerun(tmp_path / "run.rrd", scene, result, sequence, poses_gt)
    assert path.stat().st_mode & 0o777 == 0o644
    origins, eye = _layout(path)
    plots = ["plots/localized", "plots/position_error_m", "plots/rotation_error_deg"]
    assert origins == sorted([*plots, "world", "world/camera/image", "world/camera/image"])
    np.testing.assert_allclose(eye["look_target"], result.poses[:, :3].mean(0), atol=1e-5)
    vertices = np.asarray(scene.triangles)[np.asarray(scene.triangle_object) >= 0].reshape(-1, 3)
    corners = np.concatenate([vertices, result.poses[:, :3]])  # the map and the trajectory
    assert (corners.min(0) < eye["position"]).all() and (eye["position"] < corners.max(0)).all()
    origins, _ = _layout(write_rerun(tmp_path / "bare.rrd", scene, result))
    assert origins == ["plots/localized", "world"]  # no frames, no ground truth


def test_without_rerun_the_writer_says_how_to_install_it(sg2loc_run, tmp_path, monkeypatch):
    scene, result, _, _ = sg2loc_run
    real_import = builtins.__import__

    def no_rerun(name, *args, **kwargs):
        if name == "rerun" or name.startswith("rerun."):
            raise ModuleNotFoundError(f"No module named {name!r}")
        return real_import(name, *args, **kwargs)

    monkeypatch.delitem(sys.modules, "rerun", raising=False)
    monkeypatch.setattr(builtins, "__import__", no_rerun)
    with pytest.raises(ModuleNotFoundError, match=r'pip install "jaxloc\[viz\]"$'):
        write_rerun(tmp_path / "x.rrd", scene, result)
    assert not (tmp_path / "x.rrd").exists()
