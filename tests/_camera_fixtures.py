"""Small fixtures in the real on-disk formats of ScanNet and 3RScan, written by the tests.

The formats follow the datasets' own documentation and reader code:

* ScanNet scan folder (ScanNet/ScanNet ``README.md`` and
  ``BenchmarkScripts/3d_helpers/export_train_mesh_for_evaluation.py``): ``<scene>_vh_clean_2.ply``
  (binary little-endian; float x y z, uchar red green blue alpha; faces ``list uchar int``),
  ``<scene>_vh_clean_2.0.010000.segs.json`` (``segIndices``), ``<scene>.aggregation.json``
  (``segGroups`` of ``id``/``objectId``/``label``/``segments``) and a tab-separated
  ``scannetv2-labels.combined.tsv`` with the columns ``id raw_category ... nyu40id ...``.
* ScanNet RGB-D export (``SensReader/python/SensorData.py``): ``color/N.jpg``, ``depth/N.png``
  (uint16 millimetres), ``pose/N.txt`` (4x4 camera-to-world written row by row with ``%f``),
  ``intrinsic/intrinsic_color.txt`` / ``intrinsic_depth.txt`` (4x4).
* 3RScan (WaldJohannaU/3RScan ``README.md``; the PLY header as 3RScan ships it):
  ``labels.instances.annotated.v2.ply`` (ascii; x y z, red green blue, ushort objectId globalId,
  uchar NYU40 Eigen13 RIO27; faces ``list uchar uint``) and ``semseg.v2.json``.
"""

from __future__ import annotations

import io
import json
import struct
import zlib
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import trimesh
from PIL import Image

from jaxloc import render_batch, stride_grid
from jaxloc.camera import Camera
from jaxloc.geometry import yaw_pose_to_se3

ROOM = (4.0, 3.0, 2.5)
#: (label, nyu40 class id, colour, mesh maker) of the fixture room's objects.
NYU40 = {"wall": 1, "floor": 2, "cabinet": 3, "bed": 4, "chair": 5, "table": 7}


def _plane(corner, u, v, nu, nv) -> trimesh.Trimesh:
    """A rectangle corner + [0,1]u + [0,1]v as an (nu+1) x (nv+1) vertex grid."""
    a, b = np.meshgrid(np.linspace(0, 1, nu + 1), np.linspace(0, 1, nv + 1), indexing="ij")
    vertices = np.asarray(corner) + a.reshape(-1, 1) * u + b.reshape(-1, 1) * v
    index = np.arange((nu + 1) * (nv + 1)).reshape(nu + 1, nv + 1)
    q = np.stack([index[:-1, :-1], index[1:, :-1], index[1:, 1:], index[:-1, 1:]], -1).reshape(
        -1, 4
    )
    faces = np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]])
    return trimesh.Trimesh(vertices, faces, process=False)


def _box(lo, hi, subdivisions: int = 2) -> trimesh.Trimesh:
    box = trimesh.creation.box(bounds=np.array([lo, hi], float))
    for _ in range(subdivisions):
        box = box.subdivide()
    return box


def room_objects() -> list[tuple[str, np.ndarray, trimesh.Trimesh]]:
    """(label, RGB in [0, 1], mesh) of a 4 x 3 x 2.5 m room: floor, four walls, four furniture
    boxes of distinct classes and colours. Floor and walls are fine grids (hundreds of vertices)."""
    x, y, z = ROOM
    e = np.eye(3)
    return [
        ("floor", np.array([0.6, 0.5, 0.4]), _plane([0, 0, 0], x * e[0], y * e[1], 24, 18)),
        ("wall", np.array([0.9, 0.9, 0.8]), _plane([0, 0, 0], x * e[0], z * e[2], 16, 10)),
        ("wall", np.array([0.8, 0.9, 0.9]), _plane([0, y, 0], x * e[0], z * e[2], 16, 10)),
        ("wall", np.array([0.9, 0.8, 0.9]), _plane([0, 0, 0], y * e[1], z * e[2], 12, 10)),
        ("wall", np.array([0.8, 0.8, 0.9]), _plane([x, 0, 0], y * e[1], z * e[2], 12, 10)),
        ("bed", np.array([0.8, 0.1, 0.1]), _box([0.2, 0.2, 0.0], [1.6, 1.2, 0.6])),
        ("cabinet", np.array([0.1, 0.6, 0.1]), _box([3.3, 0.2, 0.0], [3.8, 1.4, 1.8])),
        ("table", np.array([0.1, 0.2, 0.8]), _box([2.2, 2.0, 0.0], [3.4, 2.8, 0.8])),
        ("chair", np.array([0.9, 0.7, 0.1]), _box([0.3, 2.2, 0.0], [0.8, 2.7, 1.0])),
    ]


def merged(objects):
    """(vertices (V, 3), faces (F, 3), colours (V, 3) uint8, object index (V,)) of the room."""
    vertices, faces, colors, owner, offset = [], [], [], [], 0
    for index, (_, rgb, mesh) in enumerate(objects):
        vertices.append(mesh.vertices)
        faces.append(mesh.faces + offset)
        colors.append(np.tile(np.round(rgb * 255).astype(np.uint8), (len(mesh.vertices), 1)))
        owner.append(np.full(len(mesh.vertices), index))
        offset += len(mesh.vertices)
    return (
        np.concatenate(vertices),
        np.concatenate(faces),
        np.concatenate(colors),
        np.concatenate(owner),
    )


def write_binary_ply(path: Path, vertices, colors, faces, extra: dict | None = None) -> None:
    """A binary little-endian PLY as ScanNet's ``_vh_clean_2.ply`` (float xyz, uchar rgba; faces
    ``list uchar int``; no face element for ``faces=None``: a point cloud), with optional extra
    int32 vertex properties."""
    extra = extra or {}
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    fields += [(c, "u1") for c in ("red", "green", "blue", "alpha")]
    fields += [(name, "<i4") for name in extra]
    vertex = np.zeros(len(vertices), fields)
    for i, c in enumerate("xyz"):
        vertex[c] = vertices[:, i]
    for i, c in enumerate(("red", "green", "blue")):
        vertex[c] = colors[:, i]
    vertex["alpha"] = 255
    for name, values in extra.items():
        vertex[name] = values
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(vertices)}"]
    header += [f"property {'float' if t == '<f4' else 'uchar'} {n}" for n, t in fields[:7]]
    header += [f"property int {name}" for name in extra]
    face = np.zeros(0, [("n", "u1"), ("i", "<i4", (3,))])
    if faces is not None:
        face = np.zeros(len(faces), face.dtype)
        face["n"], face["i"] = 3, faces
        header += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
    header += ["end_header"]
    path.write_bytes(("\n".join(header) + "\n").encode() + vertex.tobytes() + face.tobytes())


def write_scannet_scan(root: Path, objects, name: str = "scene0000_00") -> Path:
    """A ScanNet scan folder of ``objects`` (each object split over two segments), and the label
    table beside it (in ``root``). Returns the scan folder."""
    scan = root / name
    scan.mkdir(parents=True)
    vertices, faces, colors, owner = merged(objects)
    write_binary_ply(scan / f"{name}_vh_clean_2.ply", vertices, colors, faces)
    segment = 10 * owner + 3 + np.arange(len(owner)) % 2  # two segments per object
    (scan / f"{name}_vh_clean_2.0.010000.segs.json").write_text(
        json.dumps({"params": {}, "sceneId": name, "segIndices": segment.tolist()})
    )
    groups = [
        {"id": i, "objectId": i, "segments": [10 * i + 3, 10 * i + 4], "label": label}
        for i, (label, _, _) in enumerate(objects)
    ]
    (scan / f"{name}.aggregation.json").write_text(
        json.dumps({"sceneId": f"scannet.{name}", "appId": "Aggregator.v2", "segGroups": groups})
    )
    header = "id\traw_category\tcategory\tcount\tnyu40id\teigen13id\tnyuClass\tnyu40class"
    rows = [
        f"{k + 1}\t{label}\t{label}\t10\t{nyu}\t1\t{label}\t{label}"
        for k, (label, nyu) in enumerate(NYU40.items())
    ]
    (root / "scannetv2-labels.combined.tsv").write_text("\n".join([header, *rows]) + "\n")
    return scan


def write_3rscan_scan(scan: Path, objects) -> Path:
    """A 3RScan scan folder: ascii PLY with per-vertex objectId (1-based; one unannotated
    triangle with objectId 0) and NYU40, and ``semseg.v2.json``."""
    scan.mkdir(parents=True)
    vertices, faces, colors, owner = merged(objects)
    vertices = np.concatenate([vertices, [[9, 9, 0], [9.1, 9, 0], [9, 9.1, 0]]])
    colors = np.concatenate([colors, np.zeros((3, 3), np.uint8)])
    faces = np.concatenate([faces, [[len(owner), len(owner) + 1, len(owner) + 2]]])
    object_id = np.concatenate([owner + 1, [0, 0, 0]])
    nyu = np.asarray([NYU40[objects[i][0]] for i in owner] + [0, 0, 0])
    header = [
        "ply", "format ascii 1.0", f"element vertex {len(vertices)}",
        "property float x", "property float y", "property float z",
        "property uchar red", "property uchar green", "property uchar blue",
        "property ushort objectId", "property ushort globalId", "property uchar NYU40",
        "property uchar Eigen13", "property uchar RIO27",
        f"element face {len(faces)}", "property list uchar uint vertex_indices", "end_header",
    ]  # fmt: skip
    rows = [
        f"{p[0]:.6f} {p[1]:.6f} {p[2]:.6f} {c[0]} {c[1]} {c[2]} {o} {o} {n} 0 0"
        for p, c, o, n in zip(vertices, colors, object_id, nyu, strict=True)
    ]
    rows += [f"3 {a} {b} {c}" for a, b, c in faces]
    (scan / "labels.instances.annotated.v2.ply").write_text("\n".join(header + rows) + "\n")
    groups = [
        {"id": i + 1, "objectId": i + 1, "segments": [], "label": label}
        for i, (label, _, _) in enumerate(objects)
    ]
    (scan / "semseg.v2.json").write_text(json.dumps({"sceneId": "x", "segGroups": groups}))
    return scan


def write_matrix(path: Path, matrix) -> None:
    """A 4x4 matrix as SensorData.save_mat_to_file writes it: one row per line, ``%f``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(" ".join(f"{v:f}" for v in row) + "\n" for row in np.asarray(matrix)))


def intrinsics(camera: Camera) -> np.ndarray:
    K = np.eye(4)
    K[0, 0], K[1, 1], K[0, 2], K[1, 2] = camera.fx, camera.fy, camera.cx, camera.cy
    return K


def camera_to_world(pose, tilt) -> np.ndarray:
    """4x4 T_world_cam of a yaw pose (4,) and tilt (2,)."""
    return np.asarray(yaw_pose_to_se3(jnp.asarray(pose), jnp.asarray(tilt)).as_matrix())


def write_sequence(
    folder: Path,
    scene,
    poses: np.ndarray,
    tilts: np.ndarray,
    color_camera: Camera,
    depth_camera: Camera,
    patch_shape: tuple[int, int],
    classes: np.ndarray,
    frame_ids,
) -> None:
    """A ScanNet-export folder rendered from ``scene``: colour JPEGs, uint16 mm depth PNGs of the
    depth camera's own size, camera-to-world poses, both intrinsics, and one-hot patch embeddings
    (per class of ``classes``, the patch's majority object; misses get a uniform vector)."""
    for sub in ("color", "depth", "pose", "embeddings"):
        (folder / sub).mkdir(parents=True, exist_ok=True)
    write_matrix(folder / "intrinsic" / "intrinsic_color.txt", intrinsics(color_camera))
    write_matrix(folder / "intrinsic" / "intrinsic_depth.txt", intrinsics(depth_camera))
    pose_arr, tilt_arr = jnp.asarray(poses, jnp.float32), jnp.asarray(tilts, jnp.float32)
    grid = stride_grid(color_camera, 1, *patch_shape)
    views = jax.jit(render_batch)(scene, pose_arr, color_camera, grid, tilt_arr)
    depth_grid = stride_grid(depth_camera, 1)
    depth_views = jax.jit(render_batch)(scene, pose_arr, depth_camera, depth_grid, tilt_arr)
    labels = np.asarray(scene.labels)
    for t, number in enumerate(frame_ids):
        shape = (color_camera.height, color_camera.width)
        rgb = np.asarray(views.color[t]).reshape(shape + (3,))
        Image.fromarray(np.round(np.clip(rgb, 0, 1) * 255).astype(np.uint8)).save(
            folder / "color" / f"{number}.jpg", quality=95
        )
        depth = np.asarray(depth_views.depth[t]).reshape(depth_camera.height, depth_camera.width)
        millimetres = np.where(np.isfinite(depth), np.round(depth * 1000), 0).astype(np.uint16)
        Image.fromarray(millimetres).save(folder / "depth" / f"{number}.png")
        write_matrix(folder / "pose" / f"{number}.txt", camera_to_world(poses[t], tilts[t]))
        patch_object = np.asarray(views.patch_object[t])
        emb = np.full((patch_object.size, len(classes)), 1.0 / len(classes))
        hit = patch_object >= 0
        emb[hit] = labels[patch_object[hit], None] == classes[None, :]
        np.save(folder / "embeddings" / f"{number}.npy", emb.reshape(*patch_shape, len(classes)))


# ----------------------------------------------------------------- one recording, three layouts


class Recording:
    """Frames rendered once from a scene and written in every camera layout jaxloc reads.

    Matrices are rounded to float32 first and written in text exactly (shortest repr), so the
    export folder, the ``.sens`` (float32 binary) and the 3RScan sequence hold the same numbers;
    every layout gets the same JPEG bytes and the same depth values, so the three must load into
    the same query.
    """

    def __init__(self, scene, poses, tilts, color_camera, depth_camera, patch_shape, classes):
        self.color_camera, self.depth_camera = color_camera, depth_camera
        pose_arr, tilt_arr = jnp.asarray(poses, jnp.float32), jnp.asarray(tilts, jnp.float32)
        views = jax.jit(render_batch)(
            scene, pose_arr, color_camera, stride_grid(color_camera, 1, *patch_shape), tilt_arr
        )
        depth_views = jax.jit(render_batch)(
            scene, pose_arr, depth_camera, stride_grid(depth_camera, 1), tilt_arr
        )
        labels = np.asarray(scene.labels)
        shape = (color_camera.height, color_camera.width)
        depth_shape = (depth_camera.height, depth_camera.width)
        self.jpegs, self.depth_mm, self.poses, self.embeddings, self.pixel_class = (
            [],
            [],
            [],
            [],
            [],
        )
        for t in range(len(poses)):
            rgb = np.asarray(views.color[t]).reshape(shape + (3,))
            buffer = io.BytesIO()
            Image.fromarray(np.round(np.clip(rgb, 0, 1) * 255).astype(np.uint8)).save(
                buffer, "JPEG", quality=95
            )
            self.jpegs.append(buffer.getvalue())
            depth = np.asarray(depth_views.depth[t]).reshape(depth_shape)
            self.depth_mm.append(
                np.where(np.isfinite(depth), np.round(depth * 1000), 0).astype(np.uint16)
            )
            pose = camera_to_world(poses[t], tilts[t]).astype(np.float32).astype(np.float64)
            self.poses.append(pose)
            patch_object = np.asarray(views.patch_object[t])
            emb = np.full((patch_object.size, len(classes)), 1.0 / len(classes))
            hit = patch_object >= 0
            emb[hit] = labels[patch_object[hit], None] == classes[None, :]
            self.embeddings.append(emb.reshape(*patch_shape, len(classes)))
            pixel_object = np.asarray(views.object_id[t]).reshape(shape)
            self.pixel_class.append(np.where(pixel_object >= 0, labels[pixel_object], 0))

    def K(self, camera: Camera) -> np.ndarray:
        return intrinsics(camera).astype(np.float32).astype(np.float64)

    def write_embeddings(self, folder: Path, numbers) -> None:
        (folder / "embeddings").mkdir(parents=True, exist_ok=True)
        for emb, number in zip(self.embeddings, numbers, strict=True):
            np.save(folder / "embeddings" / f"{number}.npy", emb)

    def write_export(self, folder: Path, numbers) -> Path:
        """A ScanNet export folder (SensorData.py's layout)."""
        for sub in ("color", "depth", "pose", "intrinsic"):
            (folder / sub).mkdir(parents=True, exist_ok=True)
        _write_exact(folder / "intrinsic" / "intrinsic_color.txt", self.K(self.color_camera))
        _write_exact(folder / "intrinsic" / "intrinsic_depth.txt", self.K(self.depth_camera))
        for t, number in enumerate(numbers):
            (folder / "color" / f"{number}.jpg").write_bytes(self.jpegs[t])
            Image.fromarray(self.depth_mm[t].astype(np.uint16)).save(
                folder / "depth" / f"{number}.png"
            )
            _write_exact(folder / "pose" / f"{number}.txt", self.poses[t])
        self.write_embeddings(folder, numbers)
        return folder

    def write_sens(self, path: Path, timestamps_us) -> Path:
        """A version-4 ``.sens`` (sensorData.h's writeHeaderToFile / RGBDFrame::saveToFile:
        little-endian; jpeg colour, zlib uint16 depth; an IMU count of 0 at the end), frames
        numbered 0, 1, ...; the embeddings go to ``embeddings/`` beside it."""
        name = b"StructureSensor"
        eye = np.eye(4, dtype="<f4")
        cw, ch = self.color_camera.width, self.color_camera.height
        dw, dh = self.depth_camera.width, self.depth_camera.height
        parts = [struct.pack("<IQ", 4, len(name)), name]
        for matrix in (self.K(self.color_camera), eye, self.K(self.depth_camera), eye):
            parts.append(np.asarray(matrix, "<f4").tobytes())
        parts.append(struct.pack("<2i4IfQ", 2, 1, cw, ch, dw, dh, 1000.0, len(self.poses)))
        for t, pose in enumerate(self.poses):
            depth = zlib.compress(self.depth_mm[t].astype("<u2").tobytes())
            parts.append(np.asarray(pose, "<f4").tobytes())
            parts.append(
                struct.pack(
                    "<4Q", timestamps_us[t], timestamps_us[t], len(self.jpegs[t]), len(depth)
                )
            )
            parts += [self.jpegs[t], depth]
        parts.append(struct.pack("<Q", 0))  # no IMU frames
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(b"".join(parts))
        self.write_embeddings(path.parent, range(len(self.poses)))
        return path

    def write_3rscan(self, scan: Path, numbers, T_scan_world=None) -> Path:
        """A 3RScan scan folder ``scan/sequence/`` (_info.txt as ScanNet's saveToImages writes
        it; 16-bit big-endian PGM depth with saveAsPGM's comment line; 4x4 pose text), poses
        optionally moved into another frame by ``T_scan_world``; embeddings in ``scan/``."""
        folder = scan / "sequence"
        folder.mkdir(parents=True, exist_ok=True)
        cw, ch = self.color_camera.width, self.color_camera.height
        dw, dh = self.depth_camera.width, self.depth_camera.height
        info = [
            "m_versionNumber = 4", "m_sensorName = StructureSensor",
            f"m_colorWidth = {cw}", f"m_colorHeight = {ch}", f"m_depthWidth = {dw}",
            f"m_depthHeight = {dh}", "m_depthShift = 1000",
            "m_calibrationColorIntrinsic = " + _row(self.K(self.color_camera)),
            "m_calibrationColorExtrinsic = " + _row(np.eye(4)),
            "m_calibrationDepthIntrinsic = " + _row(self.K(self.depth_camera)),
            "m_calibrationDepthExtrinsic = " + _row(np.eye(4)),
            f"m_frames.size = {len(numbers)}",
        ]  # fmt: skip
        (folder / "_info.txt").write_text("\n".join(info) + "\n")
        for t, number in enumerate(numbers):
            stem = folder / f"frame-{number:06d}"
            Path(f"{stem}.color.jpg").write_bytes(self.jpegs[t])
            header = f"P5\n# data values are 16-bit each; depth shift is 1000\n{dw} {dh}\n65535\n"
            pixels = self.depth_mm[t].astype(">u2").tobytes()
            Path(f"{stem}.depth.pgm").write_bytes(header.encode() + pixels)
            pose = self.poses[t] if T_scan_world is None else T_scan_world @ self.poses[t]
            _write_exact(Path(f"{stem}.pose.txt"), pose)
        self.write_embeddings(scan, numbers)
        return scan

    def write_labels(self, folder: Path, numbers, raw_id_of_class: dict[int, int]) -> Path:
        """16-bit label PNGs ``N.png`` of raw ids (ScanNet's label-filt), 0 where nothing."""
        folder.mkdir(parents=True, exist_ok=True)
        lut = np.zeros(max(raw_id_of_class) + 1, np.uint16)
        for class_id, raw in raw_id_of_class.items():
            lut[class_id] = raw
        for t, number in enumerate(numbers):
            Image.fromarray(lut[self.pixel_class[t]]).save(folder / f"{number}.png")
        return folder


def _row(matrix) -> str:
    return " ".join(repr(float(v)) for v in np.asarray(matrix).ravel())


def _write_exact(path: Path, matrix) -> None:
    """A 4x4 matrix in text, one row per line, each value as its shortest exact decimal."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(_row(row) + "\n" for row in np.asarray(matrix)))
