"""ScanNet's RGB-D export folder (what ``SensReader/python/reader.py`` writes from a ``.sens``).

Layout (ScanNet/ScanNet ``SensReader/python/SensorData.py``: ``export_color_images``,
``export_depth_images``, ``export_poses``, ``export_intrinsics``)::

    SEQ_DIR/color/N.jpg                     colour frames (N = the .sens frame index)
    SEQ_DIR/depth/N.png                     optional: uint16 depth in millimetres, 0 = invalid
    SEQ_DIR/pose/N.txt                      optional: 4x4 camera-to-world matrix (4 text rows);
                                            all -inf marks a frame without a pose
    SEQ_DIR/intrinsic/intrinsic_color.txt   4x4 K of the colour camera
    SEQ_DIR/intrinsic/intrinsic_depth.txt   4x4 K of the depth camera (needed when the depth
                                            images have another size than the colour ones)

The exporter writes depth with ScanNet's depth shift (1000 per metre).
"""

from __future__ import annotations

import os
from pathlib import Path

from jaxloc.io.camera_frames import (
    Frame,
    FrameSource,
    check_intrinsics,
    check_rigid,
    depth_metres,
    frame_numbers,
    read_image,
    read_matrix,
)

#: ScanNet's depth shift: depth png value / 1000 = metres.
DEPTH_SCALE = 1000.0


def is_scannet_export(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a folder with ``color/`` and ``intrinsic/`` (the export's layout)."""
    path = Path(path)
    return (path / "color").is_dir() and (path / "intrinsic").is_dir()


def open_scannet_export(folder: str | os.PathLike) -> FrameSource:
    """Open an export folder (layout in the module docstring) for frame-by-frame reading.

    Raises:
        FileNotFoundError: a missing folder or intrinsics file.
        ValueError: naming the file: malformed intrinsics, frame files not named by numbers,
            two colour files of one number (``1.jpg`` and ``01.jpg`` or ``1.png``), an
            unreadable first colour image.
    """
    folder = Path(folder)
    colors = dict(frame_numbers(folder / "color", (".jpg", ".jpeg", ".png")))
    color_K_path = folder / "intrinsic" / "intrinsic_color.txt"
    K = check_intrinsics(read_matrix(color_K_path), str(color_K_path))
    first = min(colors)
    size = read_image(colors[first]).size
    depth_folder = folder / "depth"
    has_depth = depth_folder.is_dir()
    K_depth, depth_size = None, None
    if has_depth:
        K_path = folder / "intrinsic" / "intrinsic_depth.txt"
        depth_size = read_image(depth_folder / f"{first}.png").size
        if K_path.is_file():
            K_depth = check_intrinsics(read_matrix(K_path), str(K_path))
        elif depth_size != size:
            raise ValueError(
                f"{depth_folder / f'{first}.png'}: depth is {depth_size[0]}x{depth_size[1]}, the "
                f"colour images {size[0]}x{size[1]}, and there is no {K_path}"
            )
    has_poses = (folder / "pose").is_dir()

    def load(number: int, with_depth: bool) -> Frame:
        color = read_image(colors[number])
        if color.size != size:
            raise ValueError(f"{colors[number]}: size {color.size} differs from frame {first}'s")
        depth = None
        if with_depth and has_depth:
            path = depth_folder / f"{number}.png"
            depth = depth_metres(read_image(path), DEPTH_SCALE, str(path))
            if depth.shape[::-1] != depth_size:
                raise ValueError(f"{path}: size differs from frame {first}'s depth")
        pose = None
        if has_poses:
            path = folder / "pose" / f"{number}.txt"
            if not path.is_file():
                raise FileNotFoundError(2, "No such file (the frame's pose)", str(path))
            pose = read_matrix(path, allow_invalid=True)
            if pose is not None:
                check_rigid(pose, str(path))
        return Frame(number, None, color, depth, pose)

    numbers = tuple(sorted(colors))
    return FrameSource(
        "scannet-export", folder, K, size, K_depth, depth_size, numbers, has_poses, load
    )
