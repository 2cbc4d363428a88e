"""Look-alike wrong places: frames of a room that is not in the map but looks like it to the
patch embeddings.

SG2Loc matches image patches to map objects by their embeddings, which SceneGraphLoc learns per
object class and instance. A place that is not in the map but holds the same kinds of furniture
(another office of the same building) is the hard negative of a localizer's verdict: its patches
match map objects of their class well, so the particles converge somewhere, yet no pose renders the
right objects at the right depths. :func:`make_lookalike_episode` makes such a place: each object
of another synthetic room carries the embedding of a map object of its class (floor, ceiling and
walls those of the map's; a class the map lacks keeps the room's own embedding, which is as
similar to the map's objects as any object of another class). The frames are then simulated
exactly as :func:`~jaxloc.synthetic.indoor.make_episode` does, with the map's sensor settings.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from jaxloc.synthetic.indoor.config import EpisodeConfig
from jaxloc.synthetic.indoor.rooms import Episode, Room, episode_in_room, make_room


def borrow_embeddings(room: Room, map_room: Room, rng: np.random.Generator) -> Room:
    """``room`` with each object's embedding replaced by that of a map object of its class,
    drawn uniformly (the structure objects: the map's wall / floor / ceiling of the same class);
    an object whose class the map lacks keeps its own embedding."""
    embeddings = room.embeddings.copy()
    for i, label in enumerate(room.labels):
        same = np.flatnonzero(map_room.labels == label)
        if same.size:
            embeddings[i] = map_room.embeddings[rng.choice(same)]
    return dataclasses.replace(room, embeddings=embeddings)


def make_lookalike_episode(
    map_seed: int, place_seed: int, num_frames: int, config: EpisodeConfig | None = None
) -> Episode:
    """A query sequence walked through the room ``make_room(place_seed)`` whose objects carry the
    embeddings of ``make_room(map_seed)``'s objects of the same class, localized against the
    latter: ``episode.scene`` is the map (``map_seed``'s room), ``episode.in_map`` is False, and
    ``poses_gt`` are poses in the place's own frame (no pose in the map is right).

    Deterministic for the two seeds; ``place_seed`` must differ from ``map_seed``.
    """
    if int(map_seed) == int(place_seed):
        raise ValueError(f"a look-alike place needs another seed than the map's ({map_seed})")
    config = config or EpisodeConfig()
    map_room = make_room(map_seed, config.room)
    rng = np.random.default_rng([int(map_seed), int(place_seed)])
    place = borrow_embeddings(make_room(place_seed, config.room), map_room, rng)
    return episode_in_room(map_room, place, place_seed, num_frames, config)
