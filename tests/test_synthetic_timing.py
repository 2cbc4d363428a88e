"""The speed checks of :mod:`jaxloc.synthetic.timing` at tiny sizes: every time positive and
finite, every count the one the inputs imply."""

from __future__ import annotations

import math

import pytest

from jaxloc.synthetic import indoor
from jaxloc.synthetic.timing import time_filter, time_raycast, time_triplet


def finite_positive(*values: float) -> bool:
    return all(math.isfinite(v) and v > 0 for v in values)


def test_time_raycast_counts_poses_times_grid_rays():
    t = time_raycast(seed=0, poses=2, width=32, height=18, stride=4, objects=1, vertices=100)
    assert (t.poses, t.rays_per_pose, t.rays, t.repeats) == (2, 32, 64, 3)  # 8 x 4 px
    assert t.num_objects >= 1 and t.num_triangles > 0
    assert finite_positive(t.compile_s, t.wall_s, t.rays_per_s, t.rays_per_cpu_s)
    assert t.rays_per_s == pytest.approx(t.rays / t.wall_s)


def test_time_filter_is_per_frame():
    sensor = indoor.SensorConfig(width=112, height=63)
    room = indoor.RoomConfig(length_range=(4.0, 5.0), width_range=(4.0, 5.0), num_objects=(4, 4))
    config = indoor.EpisodeConfig(room=room, sensor=sensor)
    t = time_filter(config, seed=1, frames=2, particles=32, stride=8)
    assert (t.particles, t.rays_per_particle, t.frames) == (32, 112, 2)  # 14 x 8 px
    assert finite_positive(t.build_s, t.wall_s, t.s_per_frame) and t.compile_s >= 0
    assert t.s_per_frame == pytest.approx(t.wall_s / 2)
    assert t.cpu_s_per_frame == pytest.approx(t.cpu_s / 2)


def test_time_triplet_localizes_every_query():
    from jaxloc.m2loc import build_map, m2loc_config
    from jaxloc.synthetic.outdoor import make_outdoor_world

    world = make_outdoor_world("dense", seed=0, blocks=1, bridge_length=0)
    config = m2loc_config(num_scales=1, top_k=10)
    triplet_map = build_map(world.points, world.labels, config, world.road_normals)
    t = time_triplet(triplet_map, world.points, world.labels, world.road_normals, queries=2, seed=1)
    assert t.queries == 2 and 0 < t.query_instances[0] <= t.query_instances[1]
    assert finite_positive(t.descriptor_ms, t.match_ms) and t.compile_s >= 0
    assert 0.0 <= t.success_rate <= 1.0
