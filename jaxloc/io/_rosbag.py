"""What every bag reader shares: opening a bag with ``rosbags``, its damage as one-line errors,
picking topics, header stamps, and reading messages lazily by their place in the bag.

Bags are read with the pure-Python ``rosbags`` (``rosbags.highlevel.AnyReader``): a ROS 1
``.bag``, a ROS 2 bag folder (``metadata.yaml`` with sqlite3 or MCAP storage), or a bare ``.mcap``
or ``.db3`` file. Whatever ``rosbags`` or its storage back ends raise on a damaged or truncated bag
(its own errors, sqlite3's, struct's, lz4's and zstd's, assertions, overflowing sizes) becomes one
``ValueError`` naming the bag. Message types are named as ``rosbags`` names them for both ROS
versions (``sensor_msgs/msg/PointCloud2``). Stamps are integer nanoseconds.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

from jaxloc.io.poses import format_ns_as_seconds

#: File suffixes of bags given as one file: ROS 1, and ROS 2 storage files without their folder.
BAG_SUFFIXES = (".bag", ".mcap", ".db3")


def is_bag(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a ROS bag: a ``.bag``, ``.mcap`` or ``.db3`` file, or a folder with a
    ROS 2 ``metadata.yaml``."""
    path = Path(path)
    if path.is_dir():
        return (path / "metadata.yaml").is_file()
    return path.suffix.lower() in BAG_SUFFIXES


def seconds(ns: int) -> str:
    """Integer nanoseconds as exact decimal seconds without trailing zeros (``"1700000000.05"``)."""
    return format_ns_as_seconds(ns).rstrip("0").rstrip(".")


def _reason(error: BaseException) -> str:
    """``Type: message`` of an error, on one line and at most 200 characters of message."""
    detail = " ".join(str(error).split())[:200]
    return f"{type(error).__name__}: {detail}" if detail else type(error).__name__


def open_bag(path: str | os.PathLike) -> Any:
    """An open ``rosbags.highlevel.AnyReader`` of the bag (types from the bag, else ROS 2
    Humble's); close it with ``.close()`` (or ``contextlib.closing``).

    Raises:
        FileNotFoundError: no such file or folder.
        ValueError: naming the bag: not a bag ``rosbags`` reads (damaged, truncated, unknown
            storage).
    """
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(2, "No such file or folder", str(path))
    try:
        # the default types serve ROS 2 bags that store no message definitions
        reader = AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except Exception as error:  # rosbags' errors differ by storage (its own, apsw's, struct's)
        raise ValueError(f"{path}: not a readable bag ({_reason(error)})") from None
    return reader


def messages(reader: Any, path: Path, topics: Sequence[str], start=None, stop=None) -> Iterator:
    """``(topic, msgtype, log_time_ns, raw)`` of the messages of ``topics`` logged in
    [``start``, ``stop``), in log-time order, one at a time (one pass over the bag, whatever the
    number of topics); a damaged part of the bag raises ``ValueError`` naming the bag and the
    topics."""
    connections = [c for c in reader.connections if c.topic in topics]
    if not connections:
        return
    iterator = reader.messages(connections, start, stop)
    try:
        while True:
            try:
                connection, log_time, raw = next(iterator)
            except StopIteration:
                return
            except Exception as error:
                raise ValueError(
                    f"{path}: {', '.join(topics)}: not a readable bag ({_reason(error)})"
                ) from None
            yield connection.topic, connection.msgtype, log_time, raw
    finally:
        iterator.close()  # a reader left half-way keeps no cursor open


def deserialize(reader: Any, raw: bytes, msgtype: str, where: str) -> Any:
    """The message of ``raw``; a message that does not decode raises ``ValueError`` naming
    ``where``."""
    try:
        return reader.deserialize(raw, msgtype)
    except Exception as error:
        raise ValueError(
            f"{where}: a {msgtype} message does not decode ({_reason(error)})"
        ) from None


def topic_messages(reader: Any, path: Path, topic: str, start=None, stop=None) -> Iterator:
    """``(log_time_ns, message)`` of ``topic`` logged in [``start``, ``stop``), deserialized, in
    the bag's order (errors as :func:`messages` and :func:`deserialize`)."""
    for _, msgtype, log_time, raw in messages(reader, path, [topic], start, stop):
        yield log_time, deserialize(reader, raw, msgtype, f"{path}: {topic}")


def first_message(reader: Any, path: Path, topic: str) -> Any:
    """The first message of ``topic``; ValueError naming the bag and topic when it has none."""
    found = topic_messages(reader, path, topic)
    try:
        for _, message in found:
            return message
    finally:
        found.close()
    raise ValueError(f"{path}: {topic} has no messages")


def message_at(reader: Any, path: Path, topic: str, place: tuple[int, int], where: str) -> Any:
    """The message of ``topic`` at ``place`` (its log time and its rank among the topic's
    messages of that log time, :func:`places`); ValueError naming ``where`` when it is gone."""
    log_time, rank = place
    found = messages(reader, path, [topic], log_time, log_time + 1)
    try:
        for seen, (_, msgtype, _, raw) in enumerate(found):
            if seen == rank:
                return deserialize(reader, raw, msgtype, where)
    finally:
        found.close()
    raise ValueError(f"{where}: the message is not where it was (the bag changed?)")


def places(log_times: Sequence[int]) -> list[tuple[int, int]]:
    """Per message of one topic (in the bag's order) its place for :func:`message_at`: its log
    time and how many of the topic's messages before it share that log time."""
    out, previous, rank = [], None, 0
    for log_time in log_times:
        rank = rank + 1 if log_time == previous else 0
        out.append((int(log_time), rank))
        previous = log_time
    return out


def stamp_ns(header: Any) -> int:
    """A ``std_msgs/Header``'s stamp in integer nanoseconds."""
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def topic_types(reader: Any) -> dict[str, str | None]:
    """Topic name -> message type."""
    return {name: info.msgtype for name, info in reader.topics.items()}


def topics_of(reader: Any, msgtypes: Sequence[str]) -> list[str]:
    """The bag's topics of one of ``msgtypes``, sorted."""
    return sorted(name for name, msgtype in topic_types(reader).items() if msgtype in msgtypes)


def no_topic(reader: Any, path: Path, what: str) -> ValueError:
    """The error of a bag without a topic of ``what``, listing its topics and their types."""
    listed = [f"{name} ({msgtype})" for name, msgtype in sorted(topic_types(reader).items())]
    return ValueError(f"{path}: no {what} topic (topics: {listed})")


def pick_topic(
    reader: Any, path: Path, candidates: Sequence[str], named: str | None, what: str, option: str
) -> str | None:
    """The topic ``named`` (one of ``candidates``), else the only candidate, else None.

    Raises:
        ValueError: naming the bag, ``option`` and the candidates: a named topic that is absent
            or not a candidate; several candidates and none named.
    """
    candidates = sorted(candidates)
    if named is not None:
        if named not in candidates:
            types = topic_types(reader)
            why = f"a {types[named]}" if named in types else f"no topic {named!r}"
            raise ValueError(
                f"{path}: {option}={named!r} is not a {what} topic ({why}); candidates: "
                f"{candidates or 'none'}"
            )
        return named
    if len(candidates) > 1:
        raise ValueError(
            f"{path}: {len(candidates)} {what} topics {candidates}; name one with {option}="
        )
    return candidates[0] if candidates else None
