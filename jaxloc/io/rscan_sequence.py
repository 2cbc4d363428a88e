"""3RScan RGB-D sequences, and the rescan-to-reference transforms of ``3RScan.json``.

Layout (WaldJohannaU/3RScan ``README.md``, ``FAQ.md``, ``c++/rio_lib``: ``sequence.cc``
``LoadInfoIntrinsics`` / ``LoadPose``; the files are those of ScanNet's ``saveToImages``,
``SensReader/c++/src/sensorData.h``)::

    <scan_id>/sequence/_info.txt                 "key = values" lines: m_colorWidth,
                                                 m_colorHeight, m_depthWidth, m_depthHeight,
                                                 m_depthShift, m_calibrationColorIntrinsic,
                                                 m_calibrationDepthIntrinsic (16 numbers,
                                                 row-major), ...
    <scan_id>/sequence/frame-NNNNNN.color.jpg    colour frames
    <scan_id>/sequence/frame-NNNNNN.depth.pgm    16-bit depth, m_depthShift per metre (mm)
    <scan_id>/sequence/frame-NNNNNN.pose.txt     4x4 camera-to-world, the scan's own frame

Orientation: the phone was held upright, so the stored images look turned by 90 degrees, but
``_info.txt``'s sizes and intrinsics and the poses describe the images as stored; 3RScan's own
back-projection and SceneGraphLoc's ground-truth projection use them unrotated, and so does this
reader (only 3RScan's renderer rotates its *rendered* outputs). A rescan lives in its own frame:
``3RScan.json`` gives each rescan's ``transform`` to its reference scan, 16 numbers in column-major
order (3RScan's ``ReadMatrix`` fills an Eigen matrix linearly), applied as
``T_reference_cam = transform @ T_rescan_cam``.
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

import numpy as np

from jaxloc.io._numbering import check_distinct_numbers
from jaxloc.io.camera_frames import (
    FRAME_NUMBER_CLASH,
    Frame,
    FrameSource,
    check_intrinsics,
    check_rigid,
    depth_metres,
    read_image,
    read_matrix,
)

_FRAME = re.compile(r"^frame-(\d+)\.color\.jpg$")
_SIZE_KEYS = ("m_colorWidth", "m_colorHeight", "m_depthWidth", "m_depthHeight")


def sequence_folder(path: str | os.PathLike) -> Path | None:
    """The folder holding ``_info.txt``: ``path`` itself or its ``sequence/``; None if neither."""
    path = Path(path)
    for folder in (path, path / "sequence"):
        if (folder / "_info.txt").is_file():
            return folder
    return None


def read_info(path: str | os.PathLike) -> dict[str, list[str]]:
    """The ``key = values`` lines of an ``_info.txt`` (values split on white space).

    Raises:
        ValueError: naming the file and line: a line without `` = ``, a key given twice (which
            value holds would be a guess), not UTF-8 text.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not a UTF-8 text file") from None
    info = {}
    for line_number, line in enumerate(text.splitlines(), start=1):
        if not line.strip():
            continue
        key, equals, value = line.partition("=")
        if not equals or not key.strip():
            raise ValueError(f"{path}:{line_number}: expected 'key = values'")
        if key.strip() in info:
            raise ValueError(f"{path}:{line_number}: {key.strip()} is given twice")
        info[key.strip()] = value.split()
    return info


def _numbers(info: dict, key: str, count: int, path: Path) -> np.ndarray:
    if key not in info:
        raise ValueError(f"{path}: no '{key}' line")
    try:
        values = np.asarray([float(v) for v in info[key]], np.float64)
    except ValueError:
        raise ValueError(f"{path}: '{key}' holds a non-number") from None
    if values.size != count or not np.all(np.isfinite(values)):
        raise ValueError(f"{path}: '{key}' must hold {count} finite numbers")
    return values


def open_rscan_sequence(path: str | os.PathLike) -> FrameSource:
    """Open a 3RScan scan (``<scan_id>/`` or its ``sequence/``) for frame-by-frame reading.

    Raises:
        FileNotFoundError: no ``_info.txt`` there.
        ValueError: naming the file: a malformed ``_info.txt`` (sizes, depth shift,
            intrinsics), no frames, two frames of one number (``frame-000001`` and
            ``frame-1``); when a frame is loaded: an unreadable image, a depth image of another
            size than ``_info.txt`` says, a malformed or non-rigid pose.
    """
    folder = sequence_folder(path)
    if folder is None:
        raise FileNotFoundError(2, "No 3RScan sequence (_info.txt)", str(Path(path)))
    info_path = folder / "_info.txt"
    info = read_info(info_path)
    sizes = [_numbers(info, key, 1, info_path)[0] for key in _SIZE_KEYS]
    if min(sizes) < 1 or any(s != round(s) for s in sizes):
        raise ValueError(f"{info_path}: image sizes must be positive integers")
    color_size, depth_size = (int(sizes[0]), int(sizes[1])), (int(sizes[2]), int(sizes[3]))
    shift = _numbers(info, "m_depthShift", 1, info_path)[0]
    if shift <= 0:
        raise ValueError(f"{info_path}: m_depthShift must be > 0")
    K_color = _numbers(info, "m_calibrationColorIntrinsic", 16, info_path).reshape(4, 4)
    K_depth = _numbers(info, "m_calibrationDepthIntrinsic", 16, info_path).reshape(4, 4)
    check_intrinsics(K_color, f"{info_path} (colour intrinsics)")
    check_intrinsics(K_depth, f"{info_path} (depth intrinsics)")
    numbered = sorted((int(m.group(1)), p) for p in folder.iterdir() if (m := _FRAME.match(p.name)))
    if not numbered:
        raise ValueError(f"{folder}: no frames (frame-NNNNNN.color.jpg files)")
    check_distinct_numbers(numbered, FRAME_NUMBER_CLASH)  # frame-000001 and frame-1
    stems = {number: path.name.removesuffix(".color.jpg") for number, path in numbered}

    def load(number: int, with_depth: bool) -> Frame:
        stem = folder / stems[number]
        color = read_image(stem.with_name(stem.name + ".color.jpg"))
        if color.size != color_size:
            raise ValueError(f"{stem}.color.jpg: size {color.size}, _info.txt says {color_size}")
        depth = None
        if with_depth:
            depth_path = stem.with_name(stem.name + ".depth.pgm")
            depth = depth_metres(read_image(depth_path), shift, str(depth_path))
            if depth.shape[::-1] != depth_size:
                raise ValueError(f"{depth_path}: size differs from _info.txt's {depth_size}")
        pose_path = stem.with_name(stem.name + ".pose.txt")
        pose = read_matrix(pose_path, allow_invalid=True)
        if pose is not None:
            check_rigid(pose, str(pose_path))
        return Frame(number, None, color.convert("RGB"), depth, pose)

    return FrameSource(
        "3rscan", folder, K_color, color_size, K_depth, depth_size, tuple(sorted(stems)), True, load
    )


def read_rescan_transform(json_path: str | os.PathLike, scan_id: str) -> np.ndarray:
    """The (4, 4) transform from rescan ``scan_id``'s frame to its reference scan's frame.

    A reference scan maps to the identity. Raises ValueError naming the file when the file is not
    3RScan's JSON, the scan is not in it, or its transform is not 16 finite numbers of a rigid
    transform; FileNotFoundError for a missing file.
    """
    path = Path(json_path)
    try:
        scenes = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ValueError(f"{path}: not a readable JSON file ({err})") from None
    if not isinstance(scenes, list):
        raise ValueError(f"{path}: expected 3RScan.json's list of scenes")
    found = []  # the scan's entries: None for a reference scan, else its rescan entry
    for scene in scenes:
        if not isinstance(scene, dict):
            raise ValueError(f"{path}: a scene entry is not an object")
        if scene.get("reference") == scan_id:
            found.append(None)
        scans = scene.get("scans", [])
        if not isinstance(scans, list):
            raise ValueError(f"{path}: scene {scene.get('reference')!r}: 'scans' is not a list")
        found += [s for s in scans if isinstance(s, dict) and s.get("reference") == scan_id]
    if not found:
        raise ValueError(f"{path}: no scan {scan_id!r} (neither a reference nor a rescan)")
    if len(found) > 1:
        raise ValueError(f"{path}: scan {scan_id!r} is listed {len(found)} times")
    if found[0] is None:
        return np.eye(4)
    values = found[0].get("transform")
    if not isinstance(values, list) or len(values) != 16:
        raise ValueError(f"{path}: scan {scan_id}: 'transform' is not 16 numbers")
    try:
        matrix = np.asarray(values, np.float64).reshape(4, 4).T  # column-major
    except (TypeError, ValueError):
        raise ValueError(f"{path}: scan {scan_id}: non-numeric transform") from None
    if not np.all(np.isfinite(matrix)):
        raise ValueError(f"{path}: scan {scan_id}: non-finite transform")
    return check_rigid(matrix, f"{path} (scan {scan_id})")


def scan_id_of(path: str | os.PathLike) -> str:
    """The 3RScan scan id of a scan or sequence folder: the folder's name (the parent's for
    ``<scan_id>/sequence``)."""
    folder = Path(path).resolve()
    return folder.parent.name if folder.name == "sequence" else folder.name
