"""The camera messages of a bag: a topic's messages indexed by stamp and read one at a time
(:class:`BagTopic`), and ``sensor_msgs/Image``, ``CompressedImage`` and ``CameraInfo`` decoded
into arrays.

Images decode to 8-bit RGB (colour), float64 metres (depth, 0 = invalid) or int64 class ids
(labels); intrinsics to the 4x4 pinhole matrices of :mod:`jaxloc.io.camera_frames`.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
from PIL import Image

from jaxloc.io._rosbag import first_message, message_at, places, seconds, stamp_ns, topic_messages
from jaxloc.io.camera_frames import IMAGE_ERRORS, check_intrinsics
from jaxloc.io.poses import match_timestamps

IMAGE, COMPRESSED = "sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
#: Colour encodings read: channels and the order of R, G, B among them.
COLOR_ENCODINGS = {
    "rgb8": (3, [0, 1, 2]),
    "bgr8": (3, [2, 1, 0]),
    "rgba8": (4, [0, 1, 2]),
    "bgra8": (4, [2, 1, 0]),
    "mono8": (1, [0, 0, 0]),
}
#: Depth encodings read: pixel type and metres per unit.
DEPTH_ENCODINGS = {"16UC1": (np.uint16, 1e-3), "32FC1": (np.float32, 1.0)}
#: Label-image encodings read (class ids).
LABEL_ENCODINGS = {"mono8": np.uint8, "8UC1": np.uint8, "mono16": np.uint16, "16UC1": np.uint16}


class BagTopic:
    """One topic of an open bag: its messages' header stamps (int64 ns, increasing; the receive
    time where a stamp is 0) and where each lies in the bag, for reading any one of them later.

    Raises:
        ValueError: naming the bag and topic: no messages, stamps that do not increase.
    """

    def __init__(self, reader, path: Path, topic: str):
        self.reader, self.path, self.topic = reader, path, topic
        self.msgtype = reader.topics[topic].msgtype
        stamps, log_times = [], []
        for log_time, message in topic_messages(reader, path, topic):
            stamps.append(stamp_ns(message.header) or log_time)
            log_times.append(log_time)
        self.places = places(log_times)
        self.stamps = np.asarray(stamps, np.int64)
        if not len(self.stamps):
            raise ValueError(f"{path}: {topic} has no messages")
        bad = np.flatnonzero(np.diff(self.stamps) <= 0)
        if bad.size:
            i = int(bad[0]) + 1
            raise ValueError(
                f"{path}: {topic}: message {i}'s stamp {seconds(self.stamps[i])} s is not after "
                f"message {i - 1}'s ({seconds(self.stamps[i - 1])} s); stamps must increase"
            )

    def message(self, index: int):
        """The topic's ``index``-th message, read from the bag."""
        where = f"{self.path}: {self.topic} (message {index})"
        return message_at(self.reader, self.path, self.topic, self.places[index], where)

    def first(self):
        """The topic's first message."""
        return first_message(self.reader, self.path, self.topic)

    def matched(self, stamps_ns: np.ndarray, tolerance: float, frames) -> dict[int, int]:
        """frame number -> index of this topic's message nearest in stamp to it (within
        ``tolerance`` s). ValueError naming the topic and the first frame without one."""
        index = match_timestamps(stamps_ns, self.stamps, round(tolerance * 1e9))
        missing = np.flatnonzero(index < 0)
        if missing.size:
            k = int(missing[0])
            raise ValueError(
                f"{self.path}: {self.topic} has no message within {tolerance} s of frame "
                f"{frames[k]} ({seconds(stamps_ns[k])} s; sync_tolerance)"
            )
        return {int(n): int(i) for n, i in zip(frames, index, strict=True)}


def _pixels(message, dtype, channels: int, where: str) -> np.ndarray:
    """(H, W, channels) pixels of a ``sensor_msgs/Image`` (rows of ``step`` bytes)."""
    dtype = np.dtype(dtype).newbyteorder(">" if message.is_bigendian else "<")
    height, width, step = int(message.height), int(message.width), int(message.step)
    data = np.asarray(message.data, np.uint8)
    row = width * channels * dtype.itemsize
    if height < 1 or width < 1 or step < row or data.size < height * step:
        raise ValueError(
            f"{where}: {data.size} bytes for a {width}x{height} {message.encoding} image "
            f"of {step} bytes a row"
        )
    rows = np.ascontiguousarray(data[: height * step].reshape(height, step)[:, :row])
    return rows.view(dtype).reshape(height, width, channels)


def color_image(message, msgtype: str, where: str) -> Image.Image:
    """The 8-bit RGB image of a colour ``Image`` or ``CompressedImage`` message."""
    if msgtype == COMPRESSED:
        try:
            image = Image.open(io.BytesIO(np.asarray(message.data, np.uint8).tobytes()))
            image.load()
        except IMAGE_ERRORS as err:
            raise ValueError(f"{where}: not a readable image ({type(err).__name__})") from None
        if image.format not in ("JPEG", "PNG"):
            raise ValueError(f"{where}: a {image.format} image; JPEG or PNG are read")
        return image.convert("RGB")
    if message.encoding not in COLOR_ENCODINGS:
        raise ValueError(
            f"{where}: colour encoding {message.encoding!r} is not one of "
            f"{', '.join(COLOR_ENCODINGS)}"
        )
    channels, order = COLOR_ENCODINGS[message.encoding]
    return Image.fromarray(_pixels(message, np.uint8, channels, where)[..., order], "RGB")


def depth_image(message, msgtype: str, where: str) -> np.ndarray:
    """(H, W) float64 metres of a depth ``Image`` or ``compressedDepth`` image (0 = invalid)."""
    encoding = getattr(message, "encoding", getattr(message, "format", ""))
    if msgtype == COMPRESSED and "compressedDepth" in encoding:
        depth = _compressed_depth(message, where)
    elif msgtype == IMAGE and encoding in DEPTH_ENCODINGS:
        dtype, scale = DEPTH_ENCODINGS[encoding]
        depth = _pixels(message, dtype, 1, where)[..., 0].astype(np.float64) * scale
    else:
        raise ValueError(
            f"{where}: depth encoding {encoding!r} of a {msgtype.split('/')[-1]} is not read "
            "(sensor_msgs/Image in 16UC1 millimetres or 32FC1 metres, or their PNG "
            "compressedDepth)"
        )
    return np.where(np.isfinite(depth) & (depth > 0), depth, 0.0)


def _compressed_depth(message, where: str) -> np.ndarray:
    """(H, W) metres of a ``compressedDepth`` ``CompressedImage`` (image_transport's
    compressed_depth_image_transport; ``format`` "16UC1; compressedDepth png" or "32FC1; ..."):
    a 12-byte header (an int32, then the float32 quantization ``a``, ``b``) before a 16-bit PNG of
    millimetres (16UC1) or of the quantized inverse depth ``q`` (32FC1: ``a / (q - b)`` metres,
    ``q = 0`` invalid). RVL-coded images are refused."""
    encoding, _, codec = (part.strip() for part in message.format.partition(";"))
    data = np.asarray(message.data, np.uint8).tobytes()
    if encoding not in DEPTH_ENCODINGS or codec not in ("compressedDepth", "compressedDepth png"):
        raise ValueError(
            f"{where}: compressed depth {message.format!r} is not read (16UC1 or 32FC1, "
            "PNG-coded compressedDepth)"
        )
    if len(data) <= 12:
        raise ValueError(f"{where}: {len(data)} bytes, no compressedDepth image after its header")
    try:
        image = Image.open(io.BytesIO(data[12:]))
        image.load()
    except IMAGE_ERRORS as err:
        raise ValueError(
            f"{where}: not a readable compressedDepth PNG ({type(err).__name__})"
        ) from None
    pixels = np.asarray(image)
    if image.format != "PNG" or pixels.ndim != 2:
        raise ValueError(f"{where}: a compressedDepth image is one 16-bit grey PNG after 12 bytes")
    pixels = pixels.astype(np.float64)
    if encoding == "16UC1":
        return pixels * DEPTH_ENCODINGS["16UC1"][1]
    a, b = np.frombuffer(data[4:12], "<f4").astype(np.float64)
    inverse = pixels - b
    return np.divide(a, inverse, out=np.zeros_like(pixels), where=(pixels > 0) & (inverse > 0))


def label_image(message, msgtype: str, where: str) -> np.ndarray:
    """(H, W) int64 class ids of a label ``Image``."""
    encoding = getattr(message, "encoding", "")
    if msgtype != IMAGE or encoding not in LABEL_ENCODINGS:
        raise ValueError(
            f"{where}: label encoding {encoding!r} is not read (sensor_msgs/Image in "
            f"{', '.join(LABEL_ENCODINGS)})"
        )
    return _pixels(message, LABEL_ENCODINGS[encoding], 1, where)[..., 0].astype(np.int64)


def camera_intrinsics(message, where: str) -> tuple[np.ndarray, tuple[int, int]]:
    """(4, 4) intrinsics and (W, H) of a ``CameraInfo`` message (ROS 1 ``K`` or ROS 2 ``k``)."""
    k = getattr(message, "k", None)
    k = np.asarray(message.K if k is None else k, np.float64).reshape(3, 3)
    K = np.eye(4)
    K[:3, :3] = k
    return check_intrinsics(K, where), (int(message.width), int(message.height))


def image_encoding(reader, path: Path, topic: str) -> str:
    """The encoding of a topic's first image (``compressedDepth`` for compressed depth)."""
    first = first_message(reader, path, topic)
    if reader.topics[topic].msgtype == COMPRESSED:
        return "compressedDepth" if "compressedDepth" in first.format else ""
    return first.encoding
