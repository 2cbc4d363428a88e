"""Query sequences from camera recordings (the ScanNet-export folder here; the ``.sens`` and 3RScan
layouts in tests/test_camera_formats.py): pose and tilt conventions, intrinsics under resizing,
depth through its own intrinsics, numeric frame order, odometry, and every bad input.

The layout and file formats follow ScanNet's ``SensReader/python/SensorData.py`` (4x4 text
matrices written row by row, uint16 depth PNGs with depth shift 1000, ``color/N.jpg``); see
tests/_camera_fixtures.py.
"""

from __future__ import annotations

import numpy as np
import pytest
from _camera_fixtures import camera_to_world, write_matrix
from PIL import Image

from jaxloc.camera import Camera
from jaxloc.io.camera_frames import yaw_pose_and_tilt
from jaxloc.io.camera_sequence import read_camera_sequence

#: A ScanNet-like colour intrinsic matrix (ScanNet's 1296x968 colour camera, scaled by 1/8).
K_COLOR = np.array(
    [[146.27, 0.0, 80.97, 0.0], [0.0, 146.27, 60.47, 0.0], [0.0, 0.0, 1.0, 0.0], [0, 0, 0, 1.0]]
)
NATIVE = (162, 121)
EMBEDDING = (2, 3, 4)


def _rx(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _rz(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _looking_along_y(position, pitch_down=0.0, roll=0.0) -> np.ndarray:
    """T_world_cam of a camera at ``position`` whose level optical axis is world +y (yaw pi/2),
    built from camera axes: x right = world +x, y down = world -z, z forward = world +y; then
    pitched down about its own x axis and rolled about its optical axis (left side up)."""
    R = np.column_stack([[1, 0, 0], [0, 0, -1], [0, 1, 0]]).astype(float)
    R = R @ _rx(-pitch_down) @ _rz(roll)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, position
    return T


def write_folder(root, frame_ids, poses=None, size=NATIVE, emb_shape=EMBEDDING):
    """A minimal ScanNet-export folder: grey JPEGs, identity-ish poses, intrinsics, embeddings
    whose first value is the frame number (to check the order)."""
    for sub in ("color", "pose", "embeddings"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    write_matrix(root / "intrinsic" / "intrinsic_color.txt", K_COLOR)
    for t, number in enumerate(frame_ids):
        Image.new("RGB", size, (128, 64, 32)).save(root / "color" / f"{number}.jpg")
        pose = _looking_along_y([1.0, 2.0 + 0.1 * t, 1.3]) if poses is None else poses[t]
        write_matrix(root / "pose" / f"{number}.txt", pose)
        emb = np.ones(emb_shape)
        emb[0, 0, 0] = number + 1
        np.save(root / "embeddings" / f"{number}.npy", emb)
    return root


def test_known_scannet_pose_gives_known_yaw_pose_and_tilt():
    """A camera looking along world +y is yaw pi/2; pitched down by 0.2 rad it has pitch +0.2;
    rolled left side up by 0.1 rad it has roll +0.1 (DESIGN.md conventions)."""
    pose, tilt = yaw_pose_and_tilt(_looking_along_y([1.0, 2.0, 1.3]))
    np.testing.assert_allclose(pose, [1.0, 2.0, 1.3, np.pi / 2], atol=1e-12)
    np.testing.assert_allclose(tilt, [0.0, 0.0], atol=1e-12)
    pose, tilt = yaw_pose_and_tilt(_looking_along_y([0, 0, 1], pitch_down=0.2))
    np.testing.assert_allclose(pose[3], np.pi / 2, atol=1e-12)
    np.testing.assert_allclose(tilt, [0.2, 0.0], atol=1e-12)
    T = _looking_along_y([0, 0, 1], roll=0.1)
    left = -T[:3, 0]  # the camera's left side, in the world
    assert left[2] > 0  # raised
    np.testing.assert_allclose(yaw_pose_and_tilt(T)[1], [0.0, 0.1], atol=1e-12)
    # and the library's own pose maker gives back what it was given
    rng = np.random.default_rng(0)
    for _ in range(5):
        p = np.append(rng.uniform(-3, 3, 3), rng.uniform(-np.pi, np.pi))
        tilt = rng.uniform(-0.4, 0.4, 2)
        got_pose, got_tilt = yaw_pose_and_tilt(camera_to_world(p, tilt))
        np.testing.assert_allclose(got_pose, p, atol=1e-5)
        np.testing.assert_allclose(got_tilt, tilt, atol=1e-5)


def test_folder_poses_ego_motion_and_numeric_frame_order(tmp_path):
    """Frames 0, 2, 11, 102 sort as numbers; each frame keeps its own files; a camera stepping
    0.1 m along world +y while turning 0.05 rad per frame from yaw pi/2 has the known ego-motion
    in its own body frame; the ground truth is the poses' yaw pose."""
    poses = [_looking_along_y([1.0, 2.0 + 0.1 * t, 1.3]) for t in range(4)]
    for t in range(4):  # turn by 0.05 rad per frame about world z
        poses[t][:3, :3] = _rz(0.05 * t) @ poses[t][:3, :3]
    write_folder(tmp_path, [0, 2, 11, 102], poses)
    folder = read_camera_sequence(tmp_path)
    assert folder.frame_ids == (0, 2, 11, 102)
    np.testing.assert_array_equal(folder.sequence.patch_embeddings[:, 0, 0, 0], [1, 3, 12, 103])
    # frame t looks at yaw pi/2 + 0.05 t: the step along world +y is (cos, -sin)(0.05 t) forward
    turn = 0.05 * np.arange(3)
    expected = np.column_stack([0.1 * np.cos(turn), -0.1 * np.sin(turn), 0 * turn, 0.05 + 0 * turn])
    np.testing.assert_allclose(folder.sequence.ego_motion, expected, atol=1e-6)
    np.testing.assert_allclose(folder.poses_gt[:, 3], np.pi / 2 + 0.05 * np.arange(4), atol=1e-6)
    np.testing.assert_allclose(folder.poses_gt[:, :3], [p[:3, 3] for p in poses], atol=1e-6)


def test_intrinsics_and_resize_give_the_known_rays(tmp_path):
    """Resizing 162x121 to 81 wide (aspect kept: 60 high) scales the focal lengths and keeps
    pixel centres at integers: working pixel u sees the native ray through (u + 0.5)/s - 0.5;
    and the image content moves with it (a dark/bright edge at native x = 80 lands between
    working pixels 39 and 40)."""
    write_folder(tmp_path, [0])
    image = np.zeros((NATIVE[1], NATIVE[0], 3), np.uint8)
    image[:, 80:] = 255  # the edge at continuous x = 79.5 (between native pixels 79 and 80)
    Image.fromarray(image).save(tmp_path / "color" / "0.png")
    (tmp_path / "color" / "0.jpg").unlink()
    folder = read_camera_sequence(tmp_path, width=81)
    camera = folder.sequence.camera
    assert (camera.width, camera.height) == (81, 60)
    native = Camera(K_COLOR[0, 0], K_COLOR[1, 1], K_COLOR[0, 2], K_COLOR[1, 2], *NATIVE)
    sx, sy = 81 / NATIVE[0], 60 / NATIVE[1]
    uv = np.array([[0.0, 0.0], [40.0, 30.0], [80.0, 59.0], [12.0, 47.0]])
    native_uv = np.column_stack([(uv[:, 0] + 0.5) / sx - 0.5, (uv[:, 1] + 0.5) / sy - 0.5])
    np.testing.assert_allclose(
        np.asarray(camera.directions(uv)), np.asarray(native.directions(native_uv)), atol=1e-6
    )
    row = folder.sequence.rgb[0, 30, :, 0]
    assert row[38] < 0.1 and row[41] > 0.9 and row[39] < 0.5 < row[40]


@pytest.mark.parametrize("size", [{"width": 0}, {"height": -3}, {"width": 40.5}])
def test_a_working_size_that_is_not_a_positive_integer_is_refused(tmp_path, size):
    """Not "Camera.fx must be positive" from deep inside (width 0), nor PIL's error."""
    write_folder(tmp_path, [0])
    with pytest.raises(ValueError, match=r"(width|height) must be an integer >= 1 \(pixels\)"):
        read_camera_sequence(tmp_path, **size)


def test_depth_with_its_own_intrinsics_lands_on_the_right_pixels(tmp_path):
    """A half-size depth image whose principal point is also shifted by 3 px: every working pixel
    gets the depth pixel its ray passes through (depth values encode their pixel)."""
    write_folder(tmp_path, [0])
    K_depth = K_COLOR.copy()
    K_depth[0, 0] /= 2
    K_depth[1, 1] /= 2
    K_depth[0, 2] = K_COLOR[0, 2] / 2 + 3
    K_depth[1, 2] = K_COLOR[1, 2] / 2 - 2
    width, height = 81, 60
    vd, ud = np.mgrid[0:height, 0:width]
    millimetres = (1000 + ud + 100 * vd).astype(np.uint16)
    (tmp_path / "depth").mkdir()
    Image.fromarray(millimetres).save(tmp_path / "depth" / "0.png")
    with pytest.raises(ValueError, match=r"0\.png: depth is 81x60, the colour images 162x121, "
                       r"and there is no .*intrinsic_depth\.txt"):  # fmt: skip
        read_camera_sequence(tmp_path)
    write_matrix(tmp_path / "intrinsic" / "intrinsic_depth.txt", K_depth)
    depth = read_camera_sequence(tmp_path).sequence.depth[0]
    for u, v in [(0, 0), (80, 60), (161, 120), (37, 99)]:
        x = (u - K_COLOR[0, 2]) / K_COLOR[0, 0]
        y = (v - K_COLOR[1, 2]) / K_COLOR[1, 1]
        du, dv = round(K_depth[0, 0] * x + K_depth[0, 2]), round(K_depth[1, 1] * y + K_depth[1, 2])
        inside = 0 <= du < width and 0 <= dv < height
        expected = (1000 + du + 100 * dv) / 1000 if inside else 0.0
        assert depth[v, u] == pytest.approx(expected, abs=1e-6), (u, v)
    assert depth[0, 0] == 0.0  # outside the shifted depth image: invalid
    assert np.mean(depth > 0) > 0.9


def test_invalid_poses_are_skipped_and_odometry_gives_the_motion(tmp_path):
    """ScanNet marks frames without a pose with -inf: they are skipped. odometry.txt, when
    present, gives the ego-motion and tilt; pose/ stays the ground truth."""
    write_folder(tmp_path, [0, 1, 2])
    (tmp_path / "pose" / "1.txt").write_text("-inf -inf -inf -inf\n" * 4)
    folder = read_camera_sequence(tmp_path)
    assert folder.frame_ids == (0, 2) and folder.skipped == (1,)
    odometry = _looking_along_y([0, 0, 0], pitch_down=0.3)
    rows = [f"{n} " + " ".join(f"{v:.9f}" for v in odometry.ravel()) for n in (0, 1, 2)]
    (tmp_path / "odometry.txt").write_text("\n".join(rows) + "\n")
    folder = read_camera_sequence(tmp_path)
    np.testing.assert_allclose(folder.sequence.ego_motion, np.zeros((1, 4)), atol=1e-6)
    np.testing.assert_allclose(folder.sequence.tilt[:, 0], 0.3, atol=1e-6)
    np.testing.assert_allclose(folder.tilt_gt, 0.0, atol=1e-6)
    assert folder.poses_gt[1, 1] == pytest.approx(2.2)


def test_odometry_in_tum_and_kitti_files_gives_the_same_motion(tmp_path):
    """The odometry file may also be TUM (matched by time: a frame without a timestamp is at its
    number, as --poses-out writes it) or KITTI (one line per frame of the recording, in order)."""
    from jaxloc.io.poses import write_kitti, write_tum

    write_folder(tmp_path, [0, 1, 2])
    odometry = [_looking_along_y([0.1 * t, 0.05 * t, 1.2], pitch_down=0.1 * t) for t in range(3)]
    rows = [f"{n} " + " ".join(repr(float(v)) for v in odometry[n].ravel()) for n in (0, 1, 2)]
    (tmp_path / "odometry.txt").write_text("\n".join(rows) + "\n")
    numbered = read_camera_sequence(tmp_path).sequence
    write_tum(tmp_path / "odometry.tum", np.stack(odometry), np.array([0.0, 1.0, 2.0]))
    write_kitti(tmp_path / "odometry.kitti", np.stack(odometry))
    for name in ("odometry.tum", "odometry.kitti"):
        other = read_camera_sequence(tmp_path, odometry=tmp_path / name).sequence
        np.testing.assert_allclose(other.ego_motion, numbered.ego_motion, atol=1e-9)
        np.testing.assert_allclose(other.tilt, numbered.tilt, atol=1e-9)
    write_kitti(tmp_path / "short.kitti", np.stack(odometry[:2]))
    with pytest.raises(ValueError, match=r"short\.kitti: 2 kitti poses for the recording's 3"):
        read_camera_sequence(tmp_path, odometry=tmp_path / "short.kitti")
    write_tum(tmp_path / "late.tum", np.stack(odometry), np.array([10.0, 11.0, 12.0]))
    with pytest.raises(ValueError, match=r"late\.tum: no pose at the time of frame 0"):
        read_camera_sequence(tmp_path, odometry=tmp_path / "late.tum")


# ----------------------------------------------------------------------------- bad inputs


def test_missing_files_and_folders_are_named(tmp_path):
    with pytest.raises(ValueError, match="not a camera recording"):
        read_camera_sequence(tmp_path)
    with pytest.raises(FileNotFoundError) as info:
        read_camera_sequence(tmp_path, "scannet-export")
    assert info.value.filename.endswith("color")
    write_folder(tmp_path, [0, 5])
    (tmp_path / "embeddings" / "5.npy").unlink()
    with pytest.raises(FileNotFoundError) as info:
        read_camera_sequence(tmp_path)
    assert info.value.filename.endswith("embeddings/5.npy")
    (tmp_path / "intrinsic" / "intrinsic_color.txt").unlink()
    with pytest.raises(FileNotFoundError) as info:
        read_camera_sequence(tmp_path, "scannet-export")
    assert info.value.filename.endswith("intrinsic_color.txt")


@pytest.mark.parametrize(
    "content, message",
    [
        ("nan 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n", r"3\.txt: matrix has NaN or inf values"),
        ("2 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n", r"3\.txt: not a rigid transform"),
        ("1 0 0 0\n0 1 0 0\n0 0 -1 0\n0 0 0 1\n", r"3\.txt: not a rigid transform"),
        ("1 0 0\n0 1 0\n0 0 1\n", r"3\.txt: expected a 4x4 matrix"),
    ],
)
def test_bad_pose_files_name_the_file(tmp_path, content, message):
    write_folder(tmp_path, [0, 3])
    (tmp_path / "pose" / "3.txt").write_text(content)
    with pytest.raises(ValueError, match=message):
        read_camera_sequence(tmp_path)


def test_embeddings_of_the_wrong_dimension_or_shape(tmp_path):
    write_folder(tmp_path, [0, 1])
    with pytest.raises(ValueError, match=r"0\.npy: embeddings have 4 dims, the map's have 8"):
        read_camera_sequence(tmp_path, embedding_dim=8)
    np.save(tmp_path / "embeddings" / "1.npy", np.ones((3, 3, 4)))
    with pytest.raises(ValueError, match=r"1\.npy: shape \(3, 3, 4\) differs"):
        read_camera_sequence(tmp_path)
    zeros = np.zeros((2, 3, 4))
    zeros[0, 0, 0] = 1.0
    np.save(tmp_path / "embeddings" / "1.npy", zeros)  # zero vectors: patches without evidence
    loaded = read_camera_sequence(tmp_path).sequence.patch_embeddings
    assert np.count_nonzero(np.linalg.norm(loaded[1], axis=-1)) == 1


def test_non_numeric_frame_names_and_an_eight_bit_depth(tmp_path):
    write_folder(tmp_path, [0])
    (tmp_path / "depth").mkdir()
    Image.new("L", NATIVE).save(tmp_path / "depth" / "0.png")
    with pytest.raises(ValueError, match=r"0\.png: expected a 16-bit one-channel depth image"):
        read_camera_sequence(tmp_path)
    Image.new("RGB", NATIVE).save(tmp_path / "color" / "frame.jpg")
    with pytest.raises(ValueError, match=r"frame\.jpg: frame files must be named by their number"):
        read_camera_sequence(tmp_path)
