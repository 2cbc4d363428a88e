"""ScanNet's ``.sens`` files (SensorData version 4), read frame by frame without exporting.

Layout (ScanNet/ScanNet ``SensReader/c++/src/sensorData.h``: ``writeHeaderToFile``,
``RGBDFrame::saveToFile``; ``SensReader/python/SensorData.py``), little-endian, packed::

    uint32   version (4)
    uint64   sensor-name length n, then n bytes of name
    4 x 16 float32   colour intrinsic, colour extrinsic, depth intrinsic, depth extrinsic
                     (4x4 row-major; the intrinsics [fx 0 cx 0; 0 fy cy 0; 0 0 1 0; 0 0 0 1])
    int32    colour compression (0 raw RGB, 1 png, 2 jpeg)
    int32    depth compression (0 raw uint16, 1 zlib uint16, 2 occi: not supported)
    uint32   colour width, colour height, depth width, depth height
    float32  depth shift (uint16 depth per metre, typically 1000)
    uint64   number of frames F
    F frames: float32[16] camera-to-world (row-major; all -inf = no pose), uint64 colour and
             depth timestamps (microseconds), uint64 colour and depth byte sizes, the two payloads
    (then IMU records, which are not read)

The frames are indexed once (96-byte frame headers, payloads skipped) and read one at a time, so
memory does not grow with the file. The colour and depth extrinsics are not applied: as in
ScanNet's exporter, depth is taken to share the colour camera's centre and axes.
"""

from __future__ import annotations

import io
import os
import struct
import zlib
from pathlib import Path
from typing import NamedTuple

import numpy as np
from PIL import Image

from jaxloc.io.camera_frames import (
    IMAGE_ERRORS,
    Frame,
    FrameSource,
    check_intrinsics,
    checked_pose,
)

#: The ``.sens`` (SensorData) file version this reader accepts.
VERSION = 4
#: ``.sens`` colour compression codes and their names.
COLOR_COMPRESSION = {0: "raw", 1: "png", 2: "jpeg"}
#: ``.sens`` depth compression codes this reader supports (not occi, code 2).
DEPTH_COMPRESSION = {0: "raw_ushort", 1: "zlib_ushort"}
_FRAME_HEADER = struct.Struct("<16f4Q")
#: The largest image side a header may state (a damaged size cannot allocate terabytes).
MAX_SIZE = 1 << 15


class SensHeader(NamedTuple):
    """The header of a ``.sens`` file.

    Attributes:
        sensor_name: the sensor's name.
        K_color, E_color, K_depth, E_depth: (4, 4) float64 intrinsics and extrinsics.
        color_compression, depth_compression: their names (see the module docstring).
        color_size, depth_size: (W, H) of the images.
        depth_shift: uint16 depth units per metre.
        num_frames: frames in the file.
        frames_offset: byte offset of the first frame.
    """

    sensor_name: str
    K_color: np.ndarray
    E_color: np.ndarray
    K_depth: np.ndarray
    E_depth: np.ndarray
    color_compression: str
    depth_compression: str
    color_size: tuple[int, int]
    depth_size: tuple[int, int]
    depth_shift: float
    num_frames: int
    frames_offset: int


def _read(handle, size: int, path: Path, what: str) -> bytes:
    data = handle.read(size)
    if len(data) != size:
        raise ValueError(f"{path}: truncated .sens file (in the {what})")
    return data


def read_sens_header(path: str | os.PathLike) -> SensHeader:
    """The header of a ``.sens`` file.

    Raises:
        FileNotFoundError: no such file.
        ValueError: naming the file: not version 4, truncated, an unsupported compression, a
            non-finite or non-pinhole intrinsic matrix, zero image sizes or depth shift.
    """
    path = Path(path)
    with path.open("rb") as handle:
        (version,) = struct.unpack("<I", _read(handle, 4, path, "header"))
        if version != VERSION:
            raise ValueError(f"{path}: not a version-{VERSION} .sens file (version {version})")
        (name_length,) = struct.unpack("<Q", _read(handle, 8, path, "header"))
        if name_length > 4096:
            raise ValueError(f"{path}: not a .sens file (sensor name of {name_length} bytes)")
        name = _read(handle, name_length, path, "header").decode("utf-8", "replace")
        matrices = np.frombuffer(_read(handle, 256, path, "header"), "<f4").reshape(4, 4, 4)
        color_type, depth_type = struct.unpack("<2i", _read(handle, 8, path, "header"))
        sizes = struct.unpack("<4I", _read(handle, 16, path, "header"))
        (shift,) = struct.unpack("<f", _read(handle, 4, path, "header"))
        (num_frames,) = struct.unpack("<Q", _read(handle, 8, path, "header"))
        offset = handle.tell()
    if color_type not in COLOR_COMPRESSION or depth_type not in DEPTH_COMPRESSION:
        raise ValueError(
            f"{path}: unsupported compression (colour {color_type}, depth {depth_type}); "
            f"supported: colour {COLOR_COMPRESSION}, depth {DEPTH_COMPRESSION}"
        )
    if min(sizes) == 0 or max(sizes) > MAX_SIZE or not (np.isfinite(shift) and shift > 0):
        raise ValueError(f"{path}: image sizes {sizes} or depth shift {shift} are not plausible")
    K_color, E_color, K_depth, E_depth = (m.astype(np.float64) for m in matrices)
    check_intrinsics(K_color, f"{path} (colour intrinsics)")
    check_intrinsics(K_depth, f"{path} (depth intrinsics)")
    return SensHeader(
        name,
        K_color,
        E_color,
        K_depth,
        E_depth,
        COLOR_COMPRESSION[color_type],
        DEPTH_COMPRESSION[depth_type],
        (sizes[0], sizes[1]),
        (sizes[2], sizes[3]),
        float(shift),
        int(num_frames),
        offset,
    )


def index_frames(path: str | os.PathLike, header: SensHeader) -> list[int]:
    """The byte offset of every frame (the headers are read, the payloads skipped).

    Raises:
        ValueError: naming the file: the file ends before the header's frame count.
    """
    path = Path(path)
    size = path.stat().st_size
    offsets, offset = [], header.frames_offset
    with path.open("rb") as handle:
        for index in range(header.num_frames):
            handle.seek(offset)
            data = _read(handle, _FRAME_HEADER.size, path, f"header of frame {index}")
            *_, color_bytes, depth_bytes = _FRAME_HEADER.unpack(data)
            offsets.append(offset)
            offset += _FRAME_HEADER.size + color_bytes + depth_bytes
            if offset > size:
                raise ValueError(f"{path}: truncated .sens file (in frame {index})")
    return offsets


def _decode_color(data: bytes, header: SensHeader, where: str) -> Image.Image:
    width, height = header.color_size
    if header.color_compression == "raw":
        if len(data) != width * height * 3:
            raise ValueError(f"{where}: raw colour of {len(data)} bytes, not {width}x{height}x3")
        return Image.fromarray(np.frombuffer(data, np.uint8).reshape(height, width, 3))
    try:
        image = Image.open(io.BytesIO(data))
        image.load()
    except IMAGE_ERRORS as err:
        raise ValueError(f"{where}: colour image does not decode ({err})") from None
    if image.size != (width, height):
        raise ValueError(f"{where}: colour image is {image.size}, the header says {width}x{height}")
    return image.convert("RGB")


def _decode_depth(data: bytes, header: SensHeader, where: str) -> np.ndarray:
    width, height = header.depth_size
    if header.depth_compression == "zlib_ushort":
        try:  # never inflate past one image (a damaged stream cannot exhaust memory)
            data = zlib.decompressobj().decompress(data, 2 * width * height + 1)
        except zlib.error as err:
            raise ValueError(f"{where}: depth does not decompress ({err})") from None
    if len(data) != 2 * width * height:
        raise ValueError(f"{where}: depth of {len(data)} bytes, not {width}x{height} uint16")
    return np.frombuffer(data, "<u2").reshape(height, width).astype(np.float64) / header.depth_shift


def open_sens(path: str | os.PathLike) -> FrameSource:
    """Open a ``.sens`` file for frame-by-frame reading (frames numbered 0, 1, ... in file
    order; timestamps are the colour timestamps in seconds).

    Raises:
        FileNotFoundError: no such file.
        ValueError: naming the file, as :func:`read_sens_header` and :func:`index_frames`; when a
            frame is loaded: a payload that does not decode, a non-rigid pose.
    """
    path = Path(path)
    header = read_sens_header(path)
    offsets = index_frames(path, header)
    if not offsets:
        raise ValueError(f"{path}: no frames")

    def load(number: int, with_depth: bool) -> Frame:
        where = f"{path} (frame {number})"
        with path.open("rb") as handle:
            handle.seek(offsets[number])
            values = _FRAME_HEADER.unpack(_read(handle, _FRAME_HEADER.size, path, where))
            time_color, _, color_bytes, depth_bytes = values[16:]
            color = _decode_color(_read(handle, color_bytes, path, where), header, where)
            depth = None
            if with_depth:
                depth = _decode_depth(_read(handle, depth_bytes, path, where), header, where)
        matrix = np.asarray(values[:16], np.float64).reshape(4, 4)
        pose = checked_pose(matrix, where)
        return Frame(number, time_color * 1e-6, color, depth, pose)

    return FrameSource(
        "sens",
        path,
        header.K_color,
        header.color_size,
        header.K_depth,
        header.depth_size,
        tuple(range(len(offsets))),
        True,
        load,
    )
