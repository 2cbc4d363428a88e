"""Synthetic rooms and query episodes (the package docstring of :mod:`jaxloc.synthetic.indoor`
describes the world, the embeddings and the episodes)."""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import trimesh

from jaxloc.scene import SceneGraph
from jaxloc.sg2loc import FrameSequence
from jaxloc.synthetic.indoor import frames, layout
from jaxloc.synthetic.indoor.config import (
    ChangeConfig,
    EpisodeConfig,
    RoomConfig,
)
from jaxloc.synthetic.indoor.furniture import CLASS_NAMES, FURNITURE, STRUCTURE_CLASSES
from jaxloc.synthetic.indoor.meshes import build_furniture, build_structure
from jaxloc.synthetic.indoor.trajectory import FreeSpace, sample_trajectory

#: Structure objects of every room, its first objects: floor, ceiling and 4 walls.
NUM_STRUCTURE = 6
_CLASS_STREAM = 0xC1A55  # keeps the class vectors' stream apart from any room's seed


@dataclass(frozen=True, eq=False)
class Room:
    """A room's objects, world frame (metres, z up), in object order.

    Attributes:
        size: (Lx, Ly, H), the room spans ``[0, Lx] x [0, Ly] x [0, H]``.
        meshes: n trimesh meshes with per-vertex RGBA colours.
        labels: (n,) int32 class index into :data:`CLASS_NAMES`.
        embeddings: (n, d) float32 unit object embeddings.
        colors: (n, 3) float32 mean vertex colour in [0, 1].
        object_ids: (n,) int32 each object's index in the map room (``arange(n)`` for a map;
            a changed room lacks the removed objects' ids).
        placements: n :class:`~jaxloc.synthetic.indoor.layout.Placement` (None for the floor,
            ceiling and walls): footprint and height of each furniture object.
        walkway: the central rectangle kept free of floor furniture.
    """

    size: tuple[float, float, float]
    meshes: tuple[trimesh.Trimesh, ...]
    labels: np.ndarray
    embeddings: np.ndarray
    colors: np.ndarray
    object_ids: np.ndarray
    placements: tuple[layout.Placement | None, ...]
    walkway: layout.Placement

    @property
    def num_objects(self) -> int:
        return len(self.meshes)

    @property
    def furniture(self) -> np.ndarray:
        """(n,) bool: which objects are furniture (not floor, ceiling or wall)."""
        return np.array([p is not None for p in self.placements])

    def subset(self, keep: np.ndarray) -> Room:
        """The room with only the objects at positions ``keep``."""
        keep = np.asarray(keep)
        return Room(
            self.size,
            tuple(self.meshes[i] for i in keep),
            self.labels[keep],
            self.embeddings[keep],
            self.colors[keep],
            self.object_ids[keep],
            tuple(self.placements[i] for i in keep),
            self.walkway,
        )


@dataclass(frozen=True)
class SceneChanges:
    """Object ids (into the map room) moved and removed between the map and the query."""

    moved: np.ndarray
    removed: np.ndarray


def object_embeddings(
    labels: np.ndarray,
    rng: np.random.Generator,
    dim: int = 400,
    class_similarity: float = 0.5,
    class_seed: int = 0,
) -> np.ndarray:
    """(n, dim) float32 unit embeddings ``normalise(sqrt(s) c_label + sqrt(1 - s) u_i)``.

    The class vectors ``c`` come from ``class_seed`` (the same for every room), the instance
    vectors ``u`` from ``rng``; see the module docstring for the resulting cosines.
    """
    classes = np.random.default_rng([_CLASS_STREAM, class_seed]).normal(
        size=(len(CLASS_NAMES), dim)
    )
    classes /= np.linalg.norm(classes, axis=1, keepdims=True)
    instances = rng.normal(size=(len(labels), dim))
    instances /= np.linalg.norm(instances, axis=1, keepdims=True)
    mixed = np.sqrt(class_similarity) * classes[labels] + np.sqrt(1 - class_similarity) * instances
    return (mixed / np.linalg.norm(mixed, axis=1, keepdims=True)).astype(np.float32)


def _mean_color(mesh: trimesh.Trimesh) -> np.ndarray:
    return np.asarray(mesh.visual.vertex_colors)[:, :3].mean(axis=0) / 255.0


def _place_furniture(rng, size, config: RoomConfig, walkway):
    """Rejection-sample furniture placements; returns [(class index, dims, placement)]."""
    area = size[0] * size[1]
    low, high = config.num_objects
    target = int(rng.integers(low, max(low, min(high, low + int(area / 2))) + 1))
    specs = [spec for spec, _ in FURNITURE]
    weights = np.array([s.weight for s in specs])
    placed, blockers, counts = [], [walkway], np.zeros(len(specs), int)
    for _ in range(60 * max(target, 1)):
        if len(placed) == target:
            break
        k = int(rng.choice(len(specs), p=weights / weights.sum()))
        spec = specs[k]
        if counts[k] >= spec.max_count:
            continue
        dims = rng.uniform(spec.size_min, spec.size_max)
        p = layout.sample_placement(rng, size, spec.mount, dims, rng.uniform(*spec.elevation))
        others = [q for _, _, q in placed] + (blockers if spec.mount != "wall" else [])
        if spec.name == "door":
            clearance = layout.door_clearance(p)
            if not layout.inside_room(clearance, size) or not layout.fits(
                clearance, [q for _, _, q in placed if q.mount != "wall"], size
            ):
                continue
        if layout.fits(p, others, size):
            placed.append((k, dims, p))
            counts[k] += 1
            if spec.name == "door":
                blockers.append(clearance)
    if len(placed) < low:
        raise RuntimeError(
            f"placed only {len(placed)} of the {low} furniture objects required in a "
            f"{size[0]:.1f} x {size[1]:.1f} m room; lower num_objects or walkway_fraction"
        )
    return placed, blockers


def make_room(seed: int, config: RoomConfig | None = None) -> Room:
    """A furnished, textured room drawn from ``seed`` (deterministic).

    Objects 0-5 are the floor, ceiling and four walls (walls counter-clockwise from y = 0);
    furniture follows. See :class:`RoomConfig` for the ranges.
    """
    config = config or RoomConfig()
    rng = np.random.default_rng(seed)
    size = (
        float(rng.uniform(*config.length_range)),
        float(rng.uniform(*config.width_range)),
        float(rng.uniform(*config.height_range)),
    )
    walkway = layout.walkway(size, rng, config.walkway_fraction)
    placed, _ = _place_furniture(rng, size, config, walkway)
    lo, hi = config.vertex_range
    structure = build_structure(rng, size, rng.integers(lo, hi + 1, NUM_STRUCTURE))
    meshes = [mesh for _, mesh in structure]
    labels = [CLASS_NAMES.index(name) for name, _ in structure]
    for k, dims, placement in placed:
        mesh = build_furniture(rng, k, dims, int(rng.integers(lo, hi + 1)))
        meshes.append(mesh.apply_transform(placement.transform()))
        labels.append(len(STRUCTURE_CLASSES) + k)
    labels = np.asarray(labels, np.int32)
    embeddings = object_embeddings(
        labels, rng, config.embedding_dim, config.class_similarity, config.class_seed
    )
    return Room(
        size,
        tuple(meshes),
        labels,
        embeddings,
        np.array([_mean_color(m) for m in meshes], np.float32),
        np.arange(len(meshes), dtype=np.int32),
        (None,) * NUM_STRUCTURE + tuple(p for _, _, p in placed),
        walkway,
    )


def change_room(
    room: Room, rng: np.random.Generator, config: ChangeConfig | None = None
) -> tuple[Room, SceneChanges]:
    """The room after ``config.fraction`` of its furniture was moved or removed.

    Moved objects keep their id, label and embedding; their mesh is carried rigidly to a free
    spot (no collision with other objects, door swing areas or the walkway).
    """
    config = config or ChangeConfig()
    furniture = np.flatnonzero(room.furniture)
    movable = [
        i for i in furniture if FURNITURE[room.labels[i] - len(STRUCTURE_CLASSES)][0].movable
    ]
    count = min(int(round(config.fraction * len(furniture))), len(movable))
    chosen = rng.choice(movable, size=count, replace=False) if count else np.zeros(0, int)
    meshes, placements = list(room.meshes), list(room.placements)
    doors = [
        layout.door_clearance(p)
        for p, label in zip(placements, room.labels, strict=True)
        if p is not None and CLASS_NAMES[label] == "door"
    ]
    moved, removed = [], []
    for i in sorted(int(i) for i in chosen):
        old = placements[i]
        if rng.uniform() < config.move_probability:
            others = [p for j, p in enumerate(placements) if p is not None and j != i]
            if old.mount != "wall":
                others += doors + [room.walkway]
            for _ in range(50):
                new = layout.moved(rng, old, room.size)
                if layout.fits(new, others, room.size):
                    relative = new.transform() @ np.linalg.inv(old.transform())
                    meshes[i] = meshes[i].copy().apply_transform(relative)
                    placements[i] = new
                    moved.append(i)
                    break
            else:
                removed.append(i)
        else:
            removed.append(i)
    changed = Room(
        room.size,
        tuple(meshes),
        room.labels,
        room.embeddings,
        room.colors,
        room.object_ids,
        tuple(placements),
        room.walkway,
    )
    keep = np.setdiff1d(np.arange(room.num_objects), removed)
    return changed.subset(keep), SceneChanges(
        np.asarray(moved, np.int32), np.asarray(removed, np.int32)
    )


def scene_graph(room: Room) -> SceneGraph:
    """The room as a :class:`jaxloc.SceneGraph` (labels, embeddings, per-vertex colours)."""
    return SceneGraph.from_meshes(list(room.meshes), room.labels, room.embeddings, room.colors)


@dataclass(frozen=True, eq=False)
class Episode:
    """One query sequence in a synthetic room, with its ground truth.

    Attributes:
        room: the map room (before changes); :attr:`scene` is its scene graph.
        query_room: the changed room the frames were rendered from.
        changes: which map objects were moved or removed.
        sequence: the observations (:class:`jaxloc.FrameSequence`).
        poses_gt: (T, 4) float32 true camera poses (x, y, z, yaw).
        patch_objects: (T, rows, cols) int32 the map object dominating each patch (-1: none).
        confused: (T, rows, cols) bool, patches whose embedding came from another object.
        in_map: False for a look-alike wrong place
            (:func:`~jaxloc.synthetic.indoor.lookalike.make_lookalike_episode`): the frames come
            from a room that is not the map, so no pose in the map is right; ``poses_gt``,
            ``changes`` and ``patch_objects`` then refer to that room (``query_room``).
    """

    room: Room
    query_room: Room
    changes: SceneChanges
    sequence: FrameSequence
    poses_gt: np.ndarray
    patch_objects: np.ndarray
    confused: np.ndarray
    in_map: bool = True

    @functools.cached_property
    def scene(self) -> SceneGraph:
        """The map: the scene graph of the unchanged room (built on first use)."""
        return scene_graph(self.room)


def make_episode(seed: int, num_frames: int, config: EpisodeConfig | None = None) -> Episode:
    """A query sequence of ``num_frames`` frames in the room ``make_room(seed, config.room)``.

    Deterministic for a seed: the room, the changes, the trajectory and the sensor noise each
    draw from their own stream of ``numpy.random.SeedSequence(seed)``.
    """
    if not isinstance(num_frames, int | np.integer) or num_frames < 1:
        raise ValueError(f"num_frames must be a positive int, got {num_frames!r}")
    config = config or EpisodeConfig()
    room = make_room(seed, config.room)
    return episode_in_room(room, room, seed, num_frames, config)


def episode_in_room(
    map_room: Room, room: Room, seed: int, num_frames: int, config: EpisodeConfig
) -> Episode:
    """The episode of :func:`make_episode` walked through ``room`` (changed, then rendered, its
    patches embedded with ``room.embeddings``) and localized against ``map_room``: the same room
    for :func:`make_episode`, another one for a look-alike wrong place
    (:func:`~jaxloc.synthetic.indoor.lookalike.make_lookalike_episode`)."""
    change_rng, path_rng, sensor_rng = (
        np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(3)
    )
    query_room, changes = change_room(room, change_rng, config.changes)
    t = config.trajectory
    obstacles = [
        p for r in (room, query_room) for p in r.placements if p is not None and p.mount != "wall"
    ]
    space = FreeSpace(room.size, obstacles, t.wall_clearance, t.object_clearance)
    poses, tilts = sample_trajectory(
        path_rng, space, num_frames, t.step_range, t.height_range, t.yaw_amplitude, t.tilt_sigma
    )
    s = config.sensor
    camera = s.camera()
    object_image, depth, color = frames.render_views(
        query_room.meshes, query_room.object_ids, camera, poses, tilts
    )
    dominant = frames.dominant_objects(object_image, camera, s.patch_rows, s.patch_cols)
    embeddings, confused = frames.patch_embeddings(
        sensor_rng, dominant, room.embeddings, s.confusion_rate, s.cosine_range
    )
    sequence = FrameSequence(
        camera,
        embeddings,
        frames.noisy_ego_motion(sensor_rng, poses, s.ego_translation_sigma, s.ego_yaw_sigma),
        depth=frames.sensor_depth(sensor_rng, depth, s.depth_noise, s.hole_rate, s.depth_model),
        rgb=frames.sensor_rgb(sensor_rng, color, s.rgb_noise, s.exposure_sigma),
        tilt=tilts,
    )
    in_map = map_room is room
    return Episode(map_room, query_room, changes, sequence, poses, dominant, confused, in_map)
