"""``jaxloc.io.open_camera_recording``: a camera recording opened with its side files named as
files (the map file, ``3RScan.json`` or a transform file), against ``read_camera_sequence`` given
the same things as arrays; its errors; and ``write_camera_poses`` against the poses evo reads.

The recording is the minimal ScanNet export folder of tests/test_camera_sequence.py (4-d patch
embeddings) and the map a one-box scene graph with 4-d embeddings."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
from _camera_fixtures import write_matrix
from test_camera_sequence import write_folder

from jaxloc.geometry import yaw_pose_to_se3
from jaxloc.io import open_camera_recording, save_scene, write_camera_poses
from jaxloc.io.camera_recording import camera_pose_matrices
from jaxloc.io.camera_sequence import read_camera_sequence
from jaxloc.scene import SceneGraph

FRAMES = [0, 3, 7]


@pytest.fixture
def recording_and_map(tmp_path):
    folder = write_folder(tmp_path / "seq", FRAMES)
    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    scene = SceneGraph.from_meshes([box], [1], np.eye(4)[:1])
    save_scene(scene, tmp_path / "map.npz")
    return folder, tmp_path / "map.npz"


def _rigid(angle: float, shift) -> np.ndarray:
    T = np.eye(4)
    T[:2, :2] = [[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]]
    T[:3, 3] = shift
    return T


def test_the_opener_is_load_camera_sequence_with_the_files_read(recording_and_map, tmp_path):
    folder, map_file = recording_and_map
    opened = open_camera_recording(folder, map_file=map_file, width=40, step=2)
    direct = read_camera_sequence(folder, width=40, embedding_dim=4, step=2)
    assert opened.frame_ids == direct.frame_ids == (0, 7) and opened.format == "scannet-export"
    np.testing.assert_array_equal(
        opened.sequence.patch_embeddings, direct.sequence.patch_embeddings
    )
    np.testing.assert_array_equal(opened.sequence.ego_motion, direct.sequence.ego_motion)
    np.testing.assert_array_equal(opened.poses_gt, direct.poses_gt)
    transform = _rigid(0.3, [0.5, -1.0, 0.0])
    write_matrix(tmp_path / "transform.txt", transform)
    by_file = open_camera_recording(folder, transform=tmp_path / "transform.txt")
    by_array = read_camera_sequence(folder, transform=transform)
    np.testing.assert_allclose(by_file.poses_gt, by_array.poses_gt, atol=1e-5)  # the file's digits
    assert not np.allclose(by_file.poses_gt, read_camera_sequence(folder).poses_gt, atol=0.1)
    column_major = transform.T.ravel().tolist()  # as 3RScan.json stores it
    scenes = [{"reference": "ref", "scans": [{"reference": "seq", "transform": column_major}]}]
    (tmp_path / "3RScan.json").write_text(json.dumps(scenes))
    by_json = open_camera_recording(folder, rescan_json=tmp_path / "3RScan.json")  # id: folder
    np.testing.assert_allclose(by_json.poses_gt, by_array.poses_gt, atol=1e-12)


def test_the_opener_refuses_what_does_not_fit(recording_and_map, tmp_path):
    folder, map_file = recording_and_map
    other = tmp_path / "other.npz"
    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    save_scene(SceneGraph.from_meshes([box], [1], np.eye(3)[:1]), other)
    with pytest.raises(ValueError, match=r"0\.npy: embeddings have 4 dims, the map's have 3"):
        open_camera_recording(folder, map_file=other)
    with pytest.raises(ValueError, match="give rescan_json or transform, not both"):
        open_camera_recording(folder, rescan_json=tmp_path / "x.json", transform=np.eye(4))
    with pytest.raises(ValueError, match="patch_shape must be >= 1"):
        open_camera_recording(folder, patch_shape=(0, 4))
    (tmp_path / "broken.npz").write_bytes(b"not a map")
    with pytest.raises(ValueError, match="broken.npz: not a readable jaxloc map"):
        open_camera_recording(folder, map_file=tmp_path / "broken.npz")
    scaled = tmp_path / "scaled.txt"  # a transform file that is not rigid: named (was not)
    scaled.write_text("2 0 0 0\n0 2 0 0\n0 0 2 0\n0 0 0 1\n")
    with pytest.raises(ValueError, match=r"scaled\.txt: not a rigid transform"):
        open_camera_recording(folder, transform=scaled)


def test_poses_written_for_evo(recording_and_map, tmp_path):
    """TUM: the frames' numbers as stamps (an export folder has no times), one pose a frame;
    KITTI: one 3x4 a frame; both the yaw poses with the frames' tilt."""
    from evo.tools.file_interface import read_kitti_poses_file, read_tum_trajectory_file

    folder, map_file = recording_and_map
    recording = open_camera_recording(folder, map_file=map_file)
    poses = recording.poses_gt + [0.1, -0.2, 0.0, 0.05]
    matrices = camera_pose_matrices(poses, recording.sequence.tilt)
    for t in range(len(FRAMES)):
        one = yaw_pose_to_se3(poses[t].astype(np.float32), recording.sequence.tilt[t])
        np.testing.assert_allclose(matrices[t], np.asarray(one.as_matrix()), atol=1e-6)
    write_camera_poses(tmp_path / "est.tum", recording, poses)
    tum = read_tum_trajectory_file(str(tmp_path / "est.tum"))
    np.testing.assert_array_equal(tum.timestamps, FRAMES)
    np.testing.assert_allclose(tum.positions_xyz, matrices[:, :3, 3], atol=1e-9)
    write_camera_poses(tmp_path / "est.kitti", recording, poses, "kitti")
    kitti = read_kitti_poses_file(str(tmp_path / "est.kitti"))
    np.testing.assert_allclose(np.asarray(kitti.poses_se3), matrices, atol=1e-9)
    with pytest.raises(ValueError, match="format must be 'tum' or 'kitti'"):
        write_camera_poses(tmp_path / "x", recording, poses, "csv")
