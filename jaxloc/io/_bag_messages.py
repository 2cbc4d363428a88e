"""Reading ROS bags with ``rosbags.highlevel.AnyReader``: opening one, its damage as one-line
errors, a topic's messages read lazily by their place in the bag, and the decoding of camera
messages (``sensor_msgs/Image``, ``CompressedImage``, ``CameraInfo``) into arrays.

Images decode to 8-bit RGB (colour), float64 metres (depth, 0 = invalid) or int64 class ids
(labels); intrinsics to the 4x4 pinhole matrices of :mod:`jaxloc.io.camera_frames`.
"""

from __future__ import annotations

import io
import os
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path

import numpy as np
from PIL import Image

from jaxloc.io.camera_frames import IMAGE_ERRORS, check_intrinsics
from jaxloc.io.poses import format_ns_as_seconds as seconds
from jaxloc.io.poses import match_timestamps

#: Bag files by suffix (a ROS 2 bag folder holds a ``metadata.yaml``).
BAG_SUFFIXES = (".bag", ".mcap", ".db3")
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


@contextmanager
def bag_errors(where: str) -> Iterator[None]:
    """Turn what reading a damaged bag raises into a ValueError naming ``where``: rosbags' own
    errors, and what its storage back ends raise on damaged bytes (sqlite3, struct, lz4 and zstd
    errors, assertions, overflowing sizes, undecodable text)."""
    try:
        yield
    except Exception as err:
        detail = " ".join(str(err).split())  # one line, whatever the back end wrote
        raise ValueError(f"{where}: not a readable bag ({type(err).__name__}: {detail})") from None


@contextmanager
def open_bag(path: str | os.PathLike):
    """An open ``rosbags.highlevel.AnyReader`` of the bag ``path`` (types from the bag, else ROS
    2 Humble's). Raises ModuleNotFoundError without rosbags, FileNotFoundError, ValueError."""
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
    except ModuleNotFoundError:
        raise ModuleNotFoundError(
            'reading a ROS bag needs the rosbags package: pip install "jaxloc[ros]"'
        ) from None
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(2, "No such file or folder", str(path))
    with bag_errors(str(path)):
        reader = AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    try:
        yield reader
    finally:
        reader.close()


class BagTopic:
    """One topic of an open bag: its messages' header stamps (int64 ns, increasing) and where
    each lies in the bag, for reading any one of them later."""

    def __init__(self, reader, bag: str, topic: str):
        self.reader, self.bag, self.topic = reader, bag, topic
        self.connections = reader.topics[topic].connections
        self.msgtype = reader.topics[topic].msgtype
        stamps, self.logtimes, self.nth = [], [], []
        for logtime, message in self.messages():
            stamp = message.header.stamp
            stamps.append(stamp.sec * 10**9 + stamp.nanosec or logtime)
            same = bool(self.logtimes) and self.logtimes[-1] == logtime
            self.nth.append(self.nth[-1] + 1 if same else 0)
            self.logtimes.append(logtime)
        self.stamps = np.asarray(stamps, np.int64)
        if not len(self.stamps):
            raise ValueError(f"{bag}: {topic} has no messages")
        bad = np.flatnonzero(np.diff(self.stamps) <= 0)
        if bad.size:
            i = int(bad[0]) + 1
            raise ValueError(
                f"{bag}: {topic}: message {i}'s stamp {seconds(self.stamps[i])} s is not after "
                f"message {i - 1}'s ({seconds(self.stamps[i - 1])} s); stamps must increase"
            )

    def messages(self, start: int | None = None, stop: int | None = None):
        """(receive time ns, message) of the topic between ``start`` and ``stop``."""
        return topic_messages(self.reader, self.bag, self.topic, start, stop)

    def message(self, index: int):
        """The topic's ``index``-th message, read from the bag."""
        start = self.logtimes[index]
        found = [m for _, m in self.messages(start, start + 1)]
        return found[self.nth[index]]

    def first(self):
        """The topic's first message (read without indexing the topic)."""
        return first_message(self.reader, self.bag, self.topic)

    def matched(self, stamps_ns: np.ndarray, tolerance: float, frames) -> dict[int, int]:
        """frame number -> index of this topic's message nearest in stamp to it (within
        ``tolerance`` s). ValueError naming the topic and the first frame without one."""
        index = match_timestamps(stamps_ns, self.stamps, round(tolerance * 1e9))
        missing = np.flatnonzero(index < 0)
        if missing.size:
            k = int(missing[0])
            raise ValueError(
                f"{self.bag}: {self.topic} has no message within {tolerance} s of frame "
                f"{frames[k]} ({seconds(stamps_ns[k])} s; sync_tolerance)"
            )
        return {int(n): int(i) for n, i in zip(frames, index, strict=True)}


def topic_messages(reader, bag: str, topic: str, start: int | None = None, stop: int | None = None):
    """(receive time ns, deserialized message) of ``topic`` between ``start`` and ``stop`` (ns),
    in the bag's order; a damaged bag is a ValueError naming the bag and topic."""
    with bag_errors(f"{bag}: {topic}"):
        for connection, logtime, raw in reader.messages(
            reader.topics[topic].connections, start, stop
        ):
            yield logtime, reader.deserialize(raw, connection.msgtype)


def first_message(reader, bag: str, topic: str):
    """The first message of ``topic``; ValueError naming the bag and topic when it has none."""
    for _, message in topic_messages(reader, bag, topic):
        return message
    raise ValueError(f"{bag}: {topic} has no messages")


def pick_topic(
    topics: Mapping, bag: str, candidates: list[str], named: str | None, what: str, option: str
) -> str | None:
    """The topic ``named`` (one of ``candidates``), else the only candidate, else None;
    ValueError naming the bag, the option and the candidates otherwise."""
    if named is not None:
        if named not in candidates:
            kind = f"a {topics[named].msgtype}" if named in topics else "not in the bag"
            raise ValueError(
                f"{bag}: {option}={named!r} is {kind}; {what} topics: "
                f"{', '.join(candidates) or 'none'}"
            )
        return named
    if len(candidates) > 1:
        raise ValueError(
            f"{bag}: {len(candidates)} {what} topics ({', '.join(candidates)}); name one with "
            f"{option}="
        )
    return candidates[0] if candidates else None


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
    """(H, W) float64 metres of a depth ``Image`` (0 = invalid)."""
    encoding = getattr(message, "encoding", getattr(message, "format", ""))
    if msgtype != IMAGE or encoding not in DEPTH_ENCODINGS:
        raise ValueError(
            f"{where}: depth encoding {encoding!r} of a {msgtype.split('/')[-1]} is not read "
            "(sensor_msgs/Image in 16UC1 millimetres or 32FC1 metres)"
        )
    dtype, scale = DEPTH_ENCODINGS[encoding]
    depth = _pixels(message, dtype, 1, where)[..., 0].astype(np.float64) * scale
    return np.where(np.isfinite(depth) & (depth > 0), depth, 0.0)


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


def image_encoding(reader, bag: str, topic: str) -> str:
    info = reader.topics[topic]
    if info.msgtype == COMPRESSED:
        return "compressedDepth" if "depth" in first_message(reader, bag, topic).format else ""
    return first_message(reader, bag, topic).encoding
