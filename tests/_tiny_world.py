"""A tiny SG2Loc world for the robustness tests (bad inputs, long runs, sharding).

A 4 x 3 x 2.5 m room (floor, ceiling, four walls) with three boxes, 8-d embeddings, a 32x18
camera with a 3x4 patch grid (3x3 rays per patch, 108 rays per particle), 16 particles and synthetic
frames: the first frame's observations are rendered-like random values (unit patch embeddings,
depth in [0.5, 4] m with holes, rgb in [0, 1]) and the ego-motion is a slow forward walk with a
turn. Nothing here has to converge: it exercises the filter's code paths at the smallest sizes, so
one compilation of :data:`RUN_PASS` (shared by every test module that imports this one) is cheap.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import trimesh

from jaxloc.camera import Camera, patch_grid
from jaxloc.scene import SceneGraph
from jaxloc.sg2loc._filter import Region, StepConfig, run_pass
from jaxloc.sg2loc._particles import ParticleState, init_region
from jaxloc.sg2loc._resampling import KLDConfig
from jaxloc.sg2loc._scores import ObservationConfig
from jaxloc.sg2loc._sequence import Frame, FrameSequence

CAPACITY = 16
EMBEDDING_DIM = 8
ROOM = (4.0, 3.0, 2.5)
CHUNK = 4

#: Trace counts of :data:`RUN_PASS` (a Python side effect runs only while tracing).
TRACES = {"run_pass": 0}


def _counted_run_pass(key, state, frames, scene, config):
    TRACES["run_pass"] += 1
    return run_pass(key, state, frames, scene, config)


#: The shared compiled filter pass: every caller uses CHUNK frames and these shapes.
RUN_PASS = jax.jit(_counted_run_pass)


def room_meshes() -> list[trimesh.Trimesh]:
    """Floor, ceiling, four walls (thin boxes) and three furniture boxes, world frame, metres."""
    lx, ly, lz = ROOM
    t = 0.05
    boxes = [
        ((lx, ly, t), (lx / 2, ly / 2, -t / 2)),
        ((lx, ly, t), (lx / 2, ly / 2, lz + t / 2)),
        ((t, ly, lz), (-t / 2, ly / 2, lz / 2)),
        ((t, ly, lz), (lx + t / 2, ly / 2, lz / 2)),
        ((lx, t, lz), (lx / 2, -t / 2, lz / 2)),
        ((lx, t, lz), (lx / 2, ly + t / 2, lz / 2)),
        ((0.6, 0.6, 0.8), (0.8, 0.7, 0.4)),
        ((1.0, 0.5, 1.2), (3.0, 2.4, 0.6)),
        ((0.4, 0.4, 1.8), (3.4, 0.5, 0.9)),
    ]
    meshes = []
    for extents, centre in boxes:
        mesh = trimesh.creation.box(extents=extents)
        mesh.apply_translation(centre)
        meshes.append(mesh)
    return meshes


def scene(seed: int = 0) -> SceneGraph:
    meshes = room_meshes()
    rng = np.random.default_rng(seed)
    labels = np.arange(len(meshes)) % 5
    colors = rng.uniform(0.1, 0.9, (len(meshes), 3))
    return SceneGraph.from_meshes(
        meshes, labels, rng.normal(size=(len(meshes), EMBEDDING_DIM)), colors
    )


def camera() -> Camera:
    return Camera.from_fov(32, 18, hfov_deg=60.0)


def step_config(scene_graph: SceneGraph) -> StepConfig:
    cam = camera()
    return StepConfig(
        camera=cam,
        grid=patch_grid(cam, 3, 4, rays_per_side=3),
        observation=ObservationConfig(),
        kld=KLDConfig(min_particles=4, max_particles=CAPACITY),
        region=Region.of_scene(scene_graph),
        inject_count=2,
        inject_every=3,
    )


def frames(num_frames: int, seed: int = 0, first_index: int = 0) -> Frame:
    """``num_frames`` synthetic frames on the grid of :func:`step_config` (host arrays)."""
    rng = np.random.default_rng(seed)
    config = step_config(scene())
    num_rays = config.grid.uv.shape[0]
    h, w = config.grid.shape
    patches = config.grid.rows * config.grid.cols
    embeddings = rng.normal(size=(num_frames, patches, EMBEDDING_DIM))
    embeddings /= np.linalg.norm(embeddings, axis=-1, keepdims=True)
    depth = rng.uniform(0.5, 4.0, (num_frames, num_rays))
    depth[rng.random(depth.shape) < 0.1] = 0.0
    motion = np.tile([0.1, 0.0, 0.0, 0.05], (num_frames, 1))
    index = np.arange(first_index, first_index + num_frames)
    motion[index == 0] = 0.0
    return Frame(
        index=jnp.asarray(index, jnp.int32),
        motion=jnp.asarray(motion, jnp.float32),
        patch_embeddings=jnp.asarray(embeddings, jnp.float32),
        depth=jnp.asarray(depth, jnp.float32),
        rgb=jnp.asarray(rng.uniform(0, 1, (num_frames, h, w, 3)), jnp.float32),
        tilt=jnp.zeros((num_frames, 2), jnp.float32),
    )


def initial_state(scene_graph: SceneGraph, seed: int = 1) -> ParticleState:
    region = step_config(scene_graph).region
    return init_region(jax.random.key(seed), CAPACITY, region.lo, region.hi, region.floor_z)


def sequence(num_frames: int, seed: int = 0) -> FrameSequence:
    """A ``num_frames`` user-level :class:`~jaxloc.FrameSequence` on :func:`camera` (3x4
    patches)."""
    rng = np.random.default_rng(seed)
    cam = camera()
    h, w = cam.height, cam.width
    embeddings = rng.normal(size=(num_frames, 3, 4, EMBEDDING_DIM))
    depth = rng.uniform(0.5, 4.0, (num_frames, h, w))
    depth[rng.random(depth.shape) < 0.1] = 0.0
    return FrameSequence(
        cam,
        embeddings.astype(np.float32),
        np.tile(np.float32([0.1, 0.0, 0.0, 0.05]), (num_frames - 1, 1)),
        depth=depth.astype(np.float32),
        rgb=rng.uniform(0, 1, (num_frames, h, w, 3)).astype(np.float32),
    )
