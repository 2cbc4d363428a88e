"""The camera recordings as their datasets ship them: ScanNet ``.sens``, 3RScan sequences (with the
rescan-to-reference transform of ``3RScan.json``) and label images, against the ScanNet export
folder the project already reads.

The fixtures (tests/_camera_fixtures.py ``Recording``) write one rendered recording in every
layout from the layouts' own specifications: ``SensReader/c++/src/sensorData.h``
(``writeHeaderToFile``, ``RGBDFrame::saveToFile``), ``SensReader/python/SensorData.py``
(``load``), 3RScan's ``README.md`` / ``FAQ.md`` and ``rio_lib`` (``sequence.cc``: ``_info.txt``
keys, ``frame-NNNNNN.{color.jpg,depth.pgm,pose.txt}``; ``data.cc`` ``ReadMatrix``: the JSON
transform filled column-major), ScanNet's ``saveToImages`` / ``saveAsPGM`` (16-bit big-endian
PGM with a comment line) and ScanNet's ``README.md`` (``label-filt/N.png``: 16-bit raw label ids).
"""

from __future__ import annotations

import json
import shutil
import struct

import numpy as np
import pytest
from _camera_fixtures import NYU40, Recording, room_objects

from jaxloc.camera import Camera
from jaxloc.io import ClassEmbeddings, patch_embeddings_from_labels
from jaxloc.io.camera_sequence import read_camera_sequence
from jaxloc.io.label_images import patch_class_histograms
from jaxloc.io.rscan_sequence import open_rscan_sequence, read_rescan_transform
from jaxloc.io.scannet_sens import read_sens_header
from jaxloc.scene import SceneGraph

NUMBERS = [0, 1, 2, 3]
POSES = np.array([[1.5, 1.0, 1.3, 0.2], [1.6, 1.1, 1.3, 0.4], [1.7, 1.3, 1.35, 0.6],
                  [1.8, 1.5, 1.3, 0.8]])  # fmt: skip
TILTS = np.array([[0.1, 0.0], [0.12, 0.02], [0.08, -0.01], [0.1, 0.01]])
STAMPS_US = [1_000_000, 1_033_333, 1_066_667, 1_100_000]
#: 3RScan's sensor sizes are 960x540 colour, 224x172 depth; here a scaled-down pair.
COLOR = Camera(68.5, 68.5, 47.5, 35.5, 96, 72)
DEPTH = Camera(34.25, 34.25, 23.75, 17.75, 48, 36)
CLASSES = np.array(sorted(set(NYU40.values())))
#: Byte offset of the compression types in the fixture's header: version, name length, the
#: 15-byte name, four 4x4 float32 matrices.
COMPRESSION_OFFSET = 4 + 8 + 15 + 4 * 64


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """(root, Recording) with the room written as an export folder, a .sens and a 3RScan scan."""
    objects = room_objects()
    labels = [NYU40[label] for label, _, _ in objects]
    onehot = (np.asarray(labels)[:, None] == CLASSES[None, :]).astype(float)
    colors = [rgb for _, rgb, _ in objects]
    scene = SceneGraph.from_meshes([m for _, _, m in objects], labels, onehot, colors)
    rec = Recording(scene, POSES, TILTS, COLOR, DEPTH, (6, 8), CLASSES)
    root = tmp_path_factory.mktemp("formats")
    rec.write_export(root / "export", NUMBERS)
    rec.write_sens(root / "sens" / "scene.sens", STAMPS_US)
    rec.write_3rscan(root / "3rscan" / "ref_scan", NUMBERS)
    return root, rec


def test_sens_header_and_frames_read_as_written(recording):
    root, rec = recording
    header = read_sens_header(root / "sens" / "scene.sens")
    assert header.sensor_name == "StructureSensor" and header.num_frames == len(NUMBERS)
    assert (header.color_compression, header.depth_compression) == ("jpeg", "zlib_ushort")
    assert header.color_size == (96, 72) and header.depth_size == (48, 36)
    np.testing.assert_array_equal(header.K_color, rec.K(COLOR))
    assert header.depth_shift == 1000.0
    loaded = read_camera_sequence(root / "sens" / "scene.sens")
    assert loaded.format == "sens" and loaded.frame_ids == tuple(NUMBERS)
    np.testing.assert_allclose(loaded.timestamps, np.asarray(STAMPS_US) * 1e-6, rtol=0, atol=1e-12)


@pytest.mark.parametrize("layout", ["sens", "3rscan"])
def test_every_layout_loads_the_same_query(recording, layout):
    """The same frames as an export folder, a .sens file and a 3RScan sequence load into the same
    query (embeddings, ego-motion, tilt, depth, colour) and the same ground truth."""
    root, _ = recording
    reference = read_camera_sequence(root / "export", width=64)
    path = root / "sens" / "scene.sens" if layout == "sens" else root / "3rscan" / "ref_scan"
    other = read_camera_sequence(path, width=64)
    assert other.format == layout and other.frame_ids == reference.frame_ids
    for name in ("patch_embeddings", "ego_motion", "tilt", "depth", "rgb"):
        np.testing.assert_array_equal(
            np.asarray(getattr(other.sequence, name)),
            np.asarray(getattr(reference.sequence, name)),
            err_msg=name,
        )
    np.testing.assert_array_equal(other.poses_gt, reference.poses_gt)
    np.testing.assert_allclose(reference.poses_gt, POSES, atol=2e-5)


def test_3rscan_depth_pgm_is_big_endian_millimetres(recording):
    """The PGM's 16-bit pixels are big-endian (Netpbm; ScanNet's saveAsPGM swaps bytes): read
    back, every pixel is the fixture's millimetres / m_depthShift."""
    root, rec = recording
    source = open_rscan_sequence(root / "3rscan" / "ref_scan")
    for t, number in enumerate(NUMBERS):
        np.testing.assert_array_equal(source.load(number, True).depth, rec.depth_mm[t] / 1000.0)


def test_a_rescan_is_expressed_in_its_reference_frame(recording, tmp_path):
    """3RScan.json's 16 numbers are column-major (rio_lib's ReadMatrix fills Eigen linearly): a
    rescan whose frames live in their own frame localizes against the reference's ground truth
    once its transform is applied; the reference scan itself maps to the identity."""
    root, rec = recording
    angle = 0.7
    rescan_to_ref = np.eye(4)
    rescan_to_ref[:3, :3] = [[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0],
                             [0, 0, 1]]  # fmt: skip
    rescan_to_ref[:3, 3] = [0.4, -1.2, 0.05]
    rec.write_3rscan(tmp_path / "rescan_id", NUMBERS, T_scan_world=np.linalg.inv(rescan_to_ref))
    scenes = [{"reference": "ref_scan", "type": "train",
               "scans": [{"reference": "rescan_id",
                          "transform": rescan_to_ref.T.ravel().tolist()}]}]  # fmt: skip
    (tmp_path / "3RScan.json").write_text(json.dumps(scenes))
    transform = read_rescan_transform(tmp_path / "3RScan.json", "rescan_id")
    np.testing.assert_allclose(transform, rescan_to_ref, atol=1e-15)
    np.testing.assert_array_equal(read_rescan_transform(tmp_path / "3RScan.json", "ref_scan"),
                                  np.eye(4))  # fmt: skip
    own_frame = read_camera_sequence(tmp_path / "rescan_id")
    moved = read_camera_sequence(tmp_path / "rescan_id", transform=transform)
    reference = read_camera_sequence(root / "export")
    assert np.abs(own_frame.poses_gt[:, :2] - reference.poses_gt[:, :2]).max() > 0.3
    np.testing.assert_allclose(moved.poses_gt[:, :3], reference.poses_gt[:, :3], atol=1e-5)
    yaw = np.angle(np.exp(1j * (moved.poses_gt[:, 3] - reference.poses_gt[:, 3])))
    np.testing.assert_allclose(yaw, 0.0, atol=1e-5)
    np.testing.assert_allclose(moved.tilt_gt, reference.tilt_gt, atol=1e-5)
    np.testing.assert_allclose(moved.sequence.ego_motion, reference.sequence.ego_motion, atol=1e-5)
    with pytest.raises(ValueError, match="no scan 'other'"):
        read_rescan_transform(tmp_path / "3RScan.json", "other")
    scenes[0]["scans"] = 5  # not a TypeError from iterating it
    (tmp_path / "3RScan.json").write_text(json.dumps(scenes))
    with pytest.raises(ValueError, match=r"3RScan\.json: scene 'ref_scan': 'scans' is not a list"):
        read_rescan_transform(tmp_path / "3RScan.json", "rescan_id")


@pytest.mark.parametrize(
    "entry, value", [((0, 1), 3.0), ((2, 2), 0.0), ((3, 0), 9.0), ((1, 3), 0.5)]
)
def test_intrinsics_not_of_the_pinhole_form_are_refused_naming_the_file(
    recording, tmp_path, entry, value
):
    """ScanNet's ``intrinsic_color.txt`` holds ``[fx 0 cx 0; 0 fy cy 0; 0 0 1 0; 0 0 0 1]``; a
    skew or another changed fixed entry was read as if it were not there (only fx, fy were
    checked), and the error for fx = 0 named "K_color", not the file."""
    root, _ = recording
    export = tmp_path / "export"
    shutil.copytree(root / "export", export)
    path = export / "intrinsic" / "intrinsic_color.txt"
    K = np.loadtxt(path)
    K[entry] = value
    np.savetxt(path, K)
    with pytest.raises(ValueError, match=r"intrinsic_color\.txt: not a pinhole intrinsic matrix"):
        read_camera_sequence(export)
    K[entry] = np.eye(4)[entry]
    K[0, 0] = 0.0
    np.savetxt(path, K)
    with pytest.raises(ValueError, match=r"intrinsic_color\.txt: not a pinhole .*fx, fy must be"):
        read_camera_sequence(export)


def test_patch_histograms_equal_a_pixel_loop():
    """Each pixel counted in its patch (the grid of jaxloc.stride_grid) and class; other ids not."""
    rng = np.random.default_rng(0)
    labels = rng.integers(0, 9, size=(37, 53))
    class_ids = np.array([1, 3, 4, 8])
    rows, cols = 4, 5
    expected = np.zeros((rows, cols, 4))
    for v in range(37):
        for u in range(53):
            if labels[v, u] in class_ids:
                r = min(int((v + 0.5) * rows / 37), rows - 1)
                c = min(int((u + 0.5) * cols / 53), cols - 1)
                expected[r, c, list(class_ids).index(labels[v, u])] += 1
    np.testing.assert_array_equal(patch_class_histograms(labels, rows, cols, class_ids), expected)


def test_label_embeddings_are_the_histogram_in_the_map_class_space():
    classes = ClassEmbeddings.onehot([2, 5, 9])
    labels = np.zeros((4, 6), np.int64)
    labels[:2, :3] = 5  # patch (0, 0): all class 5
    labels[2:, :3] = 0  # patch (1, 0): unknown only
    labels[:2, 3:] = [[2, 2, 9], [2, 9, 7]]  # patch (0, 1): 3x class 2, 2x class 9, 1x unknown 7
    labels[2:, 3:] = 12  # raw id 12 -> class 9 through the id map
    out = patch_embeddings_from_labels(labels, 2, 2, classes, id_map={12: 9, 5: 5, 2: 2, 9: 9})
    assert out.shape == (1, 2, 2, 3) and out.dtype == np.float32
    np.testing.assert_allclose(out[0, 0, 0], [0, 1, 0])
    np.testing.assert_array_equal(out[0, 1, 0], [0, 0, 0])
    np.testing.assert_allclose(out[0, 0, 1], np.array([3, 0, 2]) / np.sqrt(13), rtol=1e-6)
    np.testing.assert_allclose(out[0, 1, 1], [0, 0, 1])
    with pytest.raises(ValueError, match="must be >= 0"):
        patch_embeddings_from_labels(-labels - 1, 2, 2, classes)


def test_label_images_load_as_embeddings_of_the_map_classes(recording, tmp_path):
    """16-bit label PNGs of raw ScanNet ids (table 6 -> NYU40 7) become the one-hot class
    histograms of each patch; where a patch holds one class they equal the fixture's one-hot
    majority embeddings exactly."""
    root, rec = recording
    raw_of_class = {1: 1, 2: 2, 3: 3, 4: 4, 5: 5, 7: 6}
    rec.write_labels(tmp_path / "labels", NUMBERS, raw_of_class)
    id_map = {raw: cls for cls, raw in raw_of_class.items()}
    export = tmp_path / "export"
    rec.write_export(export, NUMBERS)
    for path in (export / "embeddings").iterdir():
        path.unlink()
    (export / "embeddings").rmdir()
    classes = ClassEmbeddings.onehot(CLASSES)
    loaded = read_camera_sequence(
        export, labels_dir=tmp_path / "labels", classes=classes, label_map=id_map,
        patch_shape=(6, 8),
    )  # fmt: skip
    emb = np.asarray(loaded.sequence.patch_embeddings)
    onehot = np.stack(rec.embeddings)
    pure = np.isclose(emb.max(axis=-1), 1.0)
    assert pure.mean() > 0.5
    np.testing.assert_allclose(emb[pure], onehot[pure], atol=1e-6)
    assert np.all(np.argmax(emb, -1)[pure] == np.argmax(onehot, -1)[pure])
    with pytest.raises(ValueError, match="class embeddings"):
        read_camera_sequence(export, labels_dir=tmp_path / "labels")


@pytest.mark.parametrize(
    "corrupt, message",
    [
        (lambda b: b[:-10], "truncated"),
        (lambda b: struct.pack("<I", 3) + b[4:], "not a version-4"),
        (
            lambda b: (
                b[:COMPRESSION_OFFSET] + struct.pack("<2i", 7, 1) + b[COMPRESSION_OFFSET + 8 :]
            ),
            "unsupported compression",
        ),
    ],
)
def test_corrupt_sens_files_name_the_file(recording, tmp_path, corrupt, message):
    root, _ = recording
    bad = tmp_path / "bad.sens"
    bad.write_bytes(corrupt((root / "sens" / "scene.sens").read_bytes()))
    (tmp_path / "embeddings").symlink_to(root / "sens" / "embeddings")
    with pytest.raises(ValueError, match=message) as info:
        read_camera_sequence(bad)
    assert "bad.sens" in str(info.value)
