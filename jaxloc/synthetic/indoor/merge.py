"""Several synthetic rooms merged into one large map (SG2Loc appendix D's large environment).

Rooms are laid side by side along +x with ``gap`` metres between their walls (room r spans
``[x_r, x_r + Lx_r] x [0, Ly_r] x [0, H_r]``, ``x_0 = 0``), so no two rooms overlap and every
room stays closed by its own floor, ceiling and four walls. The merged scene graph is
:meth:`jaxloc.SceneGraph.from_meshes` on the concatenated, translated meshes with the rooms'
labels, embeddings and colours; a pose ``(x, y, z, yaw)`` in room r's frame is
``(x + x_r, y, z, yaw)`` in the merged frame.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import trimesh

from jaxloc.scene import Capacity, SceneGraph
from jaxloc.synthetic.indoor.rooms import Room


@dataclass(frozen=True, eq=False)
class MergedRooms:
    """The rooms' objects in one world frame (metres, z up), in room order.

    Attributes:
        meshes: n translated trimesh meshes (all rooms' objects).
        labels: (n,) int32 classes; embeddings: (n, d) float32; colors: (n, 3) float32.
        room_of_object: (n,) int32 index of each object's room.
        offsets: (R, 3) float64 translation of each room's frame into the merged frame.
        sizes: (R, 3) float64 each room's (Lx, Ly, H).
    """

    meshes: tuple[trimesh.Trimesh, ...]
    labels: np.ndarray
    embeddings: np.ndarray
    colors: np.ndarray
    room_of_object: np.ndarray
    offsets: np.ndarray
    sizes: np.ndarray

    @property
    def num_rooms(self) -> int:
        return self.offsets.shape[0]

    def scene_graph(self, capacity: Capacity | None = None) -> SceneGraph:
        """The merged map as one :class:`jaxloc.SceneGraph` (optionally padded to ``capacity``)."""
        return SceneGraph.from_meshes(
            list(self.meshes), self.labels, self.embeddings, self.colors, capacity=capacity
        )

    def to_merged(self, poses: np.ndarray, room: int) -> np.ndarray:
        """Poses (..., 4) = (x, y, z, yaw) in room ``room``'s frame -> the merged frame."""
        poses = np.array(poses, np.float64, copy=True)
        poses[..., :3] += self.offsets[room]
        return poses

    def room_at(self, xy: np.ndarray) -> np.ndarray:
        """(...,) int: the room whose floor contains each merged-frame point ``xy`` (..., 2), or
        -1 for points outside every room (in a gap or beyond a shorter room)."""
        xy = np.asarray(xy, np.float64)
        out = np.full(xy.shape[:-1], -1, np.int64)
        for r in range(self.num_rooms):
            lo = self.offsets[r, :2]
            hi = lo + self.sizes[r, :2]
            inside = np.all((xy >= lo) & (xy <= hi), axis=-1)
            out = np.where(inside & (out < 0), r, out)
        return out


def merge_rooms(rooms: Sequence[Room], gap: float = 0.3) -> MergedRooms:
    """Lay ``rooms`` side by side along +x, ``gap`` metres apart, in one frame.

    Args:
        rooms: at least one :class:`~jaxloc.synthetic.indoor.Room`; embeddings of one dimension.
        gap: free space between consecutive rooms' walls (metres, > 0 so walls never coincide).

    Raises:
        ValueError: no rooms, a non-positive gap or differing embedding dimensions.
    """
    rooms = list(rooms)
    if not rooms:
        raise ValueError("merge_rooms needs at least one room")
    if not gap > 0:
        raise ValueError(f"gap must be > 0 metres, got {gap}")
    dims = {room.embeddings.shape[1] for room in rooms}
    if len(dims) != 1:
        raise ValueError(f"rooms have different embedding dimensions {sorted(dims)}")
    sizes = np.array([room.size for room in rooms], np.float64)
    starts = np.concatenate([[0.0], np.cumsum(sizes[:-1, 0] + gap)])
    offsets = np.stack([starts, np.zeros_like(starts), np.zeros_like(starts)], axis=1)
    meshes = tuple(
        mesh.copy().apply_translation(offset)
        for room, offset in zip(rooms, offsets, strict=True)
        for mesh in room.meshes
    )
    return MergedRooms(
        meshes=meshes,
        labels=np.concatenate([room.labels for room in rooms]).astype(np.int32),
        embeddings=np.concatenate([room.embeddings for room in rooms]).astype(np.float32),
        colors=np.concatenate([room.colors for room in rooms]).astype(np.float32),
        room_of_object=np.concatenate(
            [np.full(room.num_objects, r, np.int32) for r, room in enumerate(rooms)]
        ),
        offsets=offsets,
        sizes=sizes,
    )
