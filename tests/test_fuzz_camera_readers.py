"""Property-based fuzzing of every camera-side reader: valid fixtures of each format, damaged by
hypothesis (truncated, bytes flipped, NaN / inf / garbage in text), must load or fail with a
``ValueError`` (or ``FileNotFoundError``) naming the file, never with another exception.

Formats: ScanNet export folders (colour JPEG, depth PNG, pose and intrinsic text, embedding
``.npy``), ScanNet ``.sens``, 3RScan sequences (``_info.txt``, PGM depth, poses) and
``3RScan.json``, label images, scene map ``.npz`` files (their compressed streams included),
labelled reconstructions (ScanNet, 3RScan, generic PLY and objects files, the label table),
embedding tables, mesh files and their object lists. The LiDAR readers:
tests/test_fuzz_lidar_readers.py.
"""

from __future__ import annotations

import json
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest
from _camera_fixtures import (
    NYU40,
    Recording,
    room_objects,
    write_3rscan_scan,
    write_binary_ply,
    write_scannet_scan,
)
from hypothesis import HealthCheck, given, settings, strategies as st

from jaxloc import SceneGraph
from jaxloc.camera import Camera
from jaxloc.io import (
    ClassEmbeddings,
    load_class_embeddings,
    load_scene,
    read_3rscan,
    read_embedding_table,
    read_label_image,
    read_labelled_ply,
    read_meshes,
    read_objects_file,
    read_scannet,
    save_scene,
)
from jaxloc.io.camera_sequence import read_camera_sequence
from jaxloc.io.rscan_sequence import read_rescan_transform

SETTINGS = settings(
    max_examples=12,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
TEXT_POISON = ["nan", "inf", "-inf", "1e999", "x", "", "\x00", "ü", "1 2", "--"]


@pytest.fixture(scope="module")
def fixtures(tmp_path_factory):
    """One valid fixture per format, in one folder."""
    root = tmp_path_factory.mktemp("fuzz_camera")
    objects = room_objects()[:6]
    classes = np.array(sorted({NYU40[label] for label, _, _ in objects}))
    labels = [NYU40[label] for label, _, _ in objects]
    onehot = (np.asarray(labels)[:, None] == classes[None, :]).astype(float)
    scene = SceneGraph.from_meshes([m for _, _, m in objects], labels, onehot)
    save_scene(scene, root / "map.npz", ClassEmbeddings.onehot(classes))
    poses = np.array([[1.5, 1.0, 1.3, 0.2], [1.6, 1.1, 1.3, 0.4]])
    rec = Recording(
        scene, poses, np.zeros((2, 2)), Camera(20.5, 20.5, 15.5, 11.5, 32, 24),
        Camera(10.25, 10.25, 7.75, 5.75, 16, 12), (2, 3), classes,
    )  # fmt: skip
    rec.write_export(root / "export", [0, 1])
    rec.write_sens(root / "sens" / "scene.sens", [1, 2])
    rec.write_3rscan(root / "rscan" / "scan", [0, 1])
    rec.write_labels(root / "labels", [0, 1], {c: c for c in classes})
    json_scenes = [
        {"reference": "a", "scans": [{"reference": "b", "transform": np.eye(4).ravel().tolist()}]}
    ]
    (root / "3RScan.json").write_text(json.dumps(json_scenes))
    write_scannet_scan(root / "scannet", objects)
    write_3rscan_scan(root / "rscan_recon", objects)
    box = objects[5][2]
    write_binary_ply(
        root / "cloud.ply", box.vertices, np.full((len(box.vertices), 3), 9, np.uint8), None,
        extra={"objectId": np.full(len(box.vertices), 4)},
    )  # fmt: skip
    (root / "objects.txt").write_text("4 5 chair\n")
    (root / "table.txt").write_text("chair 1 0 0\ntable 0 1 0\n")
    np.save(root / "table.npy", np.eye(4))
    (root / "mesh_objects.txt").write_text("a 1 1 0 0\nb 2 0 1 0\n")
    box.export(root / "mesh.ply")
    return root


def damage(data: bytes, kind: str, position: float, value: int, token: str) -> bytes:
    """One damage of a file's bytes: truncate, flip a byte, or put a poison token in text."""
    if not data:
        return data
    at = min(int(position * len(data)), len(data) - 1)
    if kind == "truncate":
        return data[:at]
    if kind == "flip":
        return data[:at] + bytes([data[at] ^ (value or 1)]) + data[at + 1 :]
    text = data.decode("utf-8", "replace")
    words = text.split(" ")
    words[min(int(position * len(words)), len(words) - 1)] = token
    return " ".join(words).encode()


DAMAGE = st.tuples(
    st.sampled_from(["truncate", "flip", "text"]),
    st.floats(0.0, 1.0),
    st.integers(0, 255),
    st.sampled_from(TEXT_POISON),
)


def check(root: Path, relative: str, damage_args, read) -> None:
    """Copy the fixtures, damage ``relative``, run ``read(copy_root)``: only ValueError or
    FileNotFoundError may come out."""
    with tempfile.TemporaryDirectory() as scratch:
        copy = Path(scratch) / "f"
        shutil.copytree(root, copy, symlinks=True)
        target = copy / relative
        target.write_bytes(damage(target.read_bytes(), *damage_args))
        try:
            read(copy)
        except (ValueError, FileNotFoundError):
            pass


CASES = {
    "export colour": ("export/color/1.jpg", lambda r: read_camera_sequence(r / "export")),
    "export depth": ("export/depth/0.png", lambda r: read_camera_sequence(r / "export")),
    "export pose": ("export/pose/1.txt", lambda r: read_camera_sequence(r / "export")),
    "export intrinsics": (
        "export/intrinsic/intrinsic_depth.txt",
        lambda r: read_camera_sequence(r / "export"),
    ),
    "export embeddings": ("export/embeddings/1.npy", lambda r: read_camera_sequence(r / "export")),
    "sens": ("sens/scene.sens", lambda r: read_camera_sequence(r / "sens" / "scene.sens")),
    "3rscan info": (
        "rscan/scan/sequence/_info.txt",
        lambda r: read_camera_sequence(r / "rscan/scan"),
    ),
    "3rscan depth": (
        "rscan/scan/sequence/frame-000001.depth.pgm",
        lambda r: read_camera_sequence(r / "rscan/scan"),
    ),
    "3rscan pose": (
        "rscan/scan/sequence/frame-000000.pose.txt",
        lambda r: read_camera_sequence(r / "rscan/scan"),
    ),
    "3RScan.json": ("3RScan.json", lambda r: read_rescan_transform(r / "3RScan.json", "b")),
    "label image": ("labels/1.png", lambda r: read_label_image(r / "labels" / "1.png")),
    "scene map": (
        "map.npz",
        lambda r: (load_scene(r / "map.npz"), load_class_embeddings(r / "map.npz")),
    ),
    "scannet mesh": (
        "scannet/scene0000_00/scene0000_00_vh_clean_2.ply",
        lambda r: read_scannet(r / "scannet" / "scene0000_00"),
    ),
    "scannet segments": (
        "scannet/scene0000_00/scene0000_00_vh_clean_2.0.010000.segs.json",
        lambda r: read_scannet(r / "scannet" / "scene0000_00"),
    ),
    "scannet aggregation": (
        "scannet/scene0000_00/scene0000_00.aggregation.json",
        lambda r: read_scannet(r / "scannet" / "scene0000_00"),
    ),
    "label table": (
        "scannet/scannetv2-labels.combined.tsv",
        lambda r: read_scannet(r / "scannet" / "scene0000_00"),
    ),
    "3rscan mesh": (
        "rscan_recon/labels.instances.annotated.v2.ply",
        lambda r: read_3rscan(r / "rscan_recon"),
    ),
    "3rscan semseg": ("rscan_recon/semseg.v2.json", lambda r: read_3rscan(r / "rscan_recon")),
    "generic ply": ("cloud.ply", lambda r: read_labelled_ply(r / "cloud.ply", r / "objects.txt")),
    "objects file": (
        "objects.txt",
        lambda r: read_labelled_ply(r / "cloud.ply", r / "objects.txt"),
    ),
    "embedding table": ("table.txt", lambda r: read_embedding_table(r / "table.txt")),
    "embedding npy": ("table.npy", lambda r: read_embedding_table(r / "table.npy")),
    "mesh object list": ("mesh_objects.txt", lambda r: read_objects_file(r / "mesh_objects.txt")),
    "mesh file": ("mesh.ply", lambda r: read_meshes(r / "mesh.ply")),
}


def test_the_fixtures_are_valid(fixtures):
    """Undamaged, every case reads (so the fuzzing damages something that worked)."""
    for relative, read in CASES.values():
        assert (fixtures / relative).is_file(), relative
        read(fixtures)


@pytest.mark.parametrize("case", sorted(CASES))
@SETTINGS
@given(damage_args=DAMAGE)
def test_damaged_files_fail_cleanly(fixtures, case, damage_args):
    relative, read = CASES[case]
    check(fixtures, relative, damage_args, read)
