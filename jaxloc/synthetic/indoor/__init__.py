"""A synthetic indoor world for SG2Loc: textured rooms, object embeddings, scene changes, camera
trajectories and noisy observations, seeded and deterministic.

World frame: the room spans ``[0, Lx] x [0, Ly] x [0, H]`` metres, z up; floor, ceiling and each
of the four walls are separate objects (classes "floor", "ceiling", "wall"), followed by 15-40
furniture objects from :data:`CLASS_NAMES` (19 furniture classes) standing on the floor or hung
on the walls without interpenetration. Meshes are coarse (about ``vertex_range`` vertices each)
and carry per-vertex colours with stripes/checker/noise texture.

Object embeddings (unit norm, ``d = embedding_dim``) mix a class part and an instance part::

    e_i = normalise( sqrt(s) c_label(i) + sqrt(1 - s) u_i )

with ``c`` and ``u`` independent random unit vectors (``c`` drawn from ``class_seed``, shared by
all rooms; ``u`` from the room's seed) and ``s = class_similarity``. Random unit vectors in
d = 400 are nearly orthogonal (cosine ~ N(0, 1/d), std 0.05), so the cosine between two objects
of one class is about ``s`` (0.5 by default) and between different classes about 0, each +- 0.05.

A query episode (:func:`make_episode`) changes the room as 3RScan's rescans do (a fraction of the
furniture moved or removed), walks a camera through the changed room and simulates the sensors:
per-patch SceneGraphLoc embeddings (the patch's dominant object's embedding at cosine
``cosine_range``, confused with another object at ``confusion_rate``), depth (relative noise,
blob holes = 0), RGB (exposure, noise) and noisy ego-motion. The map the filter uses is the
unchanged room (:attr:`Episode.scene`). A look-alike wrong place
(:func:`make_lookalike_episode`) walks another room whose objects carry the map's embeddings of
their class: the negatives of SG2Loc's verdict.
"""

from jaxloc._lazy import public_names
from jaxloc.synthetic.indoor.config import (
    ChangeConfig as ChangeConfig,
    EpisodeConfig as EpisodeConfig,
    RoomConfig as RoomConfig,
    SensorConfig as SensorConfig,
    TrajectoryConfig as TrajectoryConfig,
)
from jaxloc.synthetic.indoor.export import (
    write_scannet_export as write_scannet_export,
)
from jaxloc.synthetic.indoor.lookalike import (
    make_lookalike_episode as make_lookalike_episode,
)
from jaxloc.synthetic.indoor.merge import (
    MergedRooms as MergedRooms,
    merge_rooms as merge_rooms,
)
from jaxloc.synthetic.indoor.rooms import (
    CLASS_NAMES as CLASS_NAMES,
    Episode as Episode,
    Room as Room,
    SceneChanges as SceneChanges,
    change_room as change_room,
    episode_in_room as episode_in_room,
    make_episode as make_episode,
    make_room as make_room,
    object_embeddings as object_embeddings,
    scene_graph as scene_graph,
)

__all__ = public_names(__file__)
