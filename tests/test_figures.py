"""The floor plan under the particle figures: object footprints from the map's triangles."""

from __future__ import annotations

import numpy as np
from _camera_fixtures import room_objects

from jaxloc.figures import floor_plan
from jaxloc.scene import SceneGraph


def _area(polygon: np.ndarray) -> float:
    x, y = polygon[:, 0], polygon[:, 1]
    return 0.5 * abs(np.dot(x, np.roll(y, 1)) - np.dot(y, np.roll(x, 1)))


def test_floor_plan_footprints_are_the_objects_outlines():
    """A box's footprint is its x-y rectangle, the floor covers the room, a wall (no x-y area) is
    its segment along the wall; colours are the objects'."""
    objects = room_objects()
    meshes = [mesh for _, _, mesh in objects]
    colors = np.stack([rgb for _, rgb, _ in objects])
    scene = SceneGraph.from_meshes(meshes, np.arange(len(meshes)), np.eye(len(meshes)), colors)
    plan = floor_plan(scene)
    assert len(plan) == len(objects)
    floor, bed, wall = plan[0][0], plan[5][0], plan[1][0]
    assert abs(_area(floor) - 12.0) < 1e-5
    assert abs(_area(bed) - 1.4 * 1.0) < 1e-5
    np.testing.assert_allclose(bed.min(0), [0.2, 0.2], atol=1e-6)
    np.testing.assert_allclose(bed.max(0), [1.6, 1.2], atol=1e-6)
    assert wall.shape == (2, 2)
    np.testing.assert_allclose(sorted(wall[:, 0]), [0.0, 4.0], atol=1e-6)
    np.testing.assert_allclose(wall[:, 1], [0.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(plan[6][1], colors[6], atol=1e-6)
