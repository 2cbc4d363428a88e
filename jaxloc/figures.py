"""Figures of a map: the objects' floor plan (top view), drawn under the methods' figures."""

from __future__ import annotations

import numpy as np

from jaxloc.scene import SceneGraph


def floor_plan(scene: SceneGraph) -> list[tuple[np.ndarray, np.ndarray]]:
    """Object footprints: per real object, the convex hull of its triangles' x-y corners, as
    ((K, 2) polygon in metres, world frame; (3,) RGB in [0, 1]). Objects whose corners span no
    area in x-y (a wall seen from above) give their x-y segment as a 2-point polygon."""
    from scipy.spatial import ConvexHull, QhullError  # here: ~0.3 s to import, for figures only

    triangles = np.asarray(scene.triangles)
    owner = np.asarray(scene.triangle_object)
    colors = np.asarray(scene.colors)
    out = []
    for index in range(scene.num_objects):
        points = triangles[owner == index].reshape(-1, 3)[:, :2].astype(np.float64)
        try:
            polygon = points[ConvexHull(points).vertices]
        except QhullError:  # flat in x-y: the segment between the two farthest-apart corners
            direction = points - points.mean(0)
            axis = np.linalg.svd(direction, full_matrices=False)[2][0]
            along = direction @ axis
            polygon = points[[np.argmin(along), np.argmax(along)]]
        out.append((polygon, np.clip(colors[index], 0.0, 1.0)))
    return out


def draw_floor_plan(ax, plan: list[tuple[np.ndarray, np.ndarray]]) -> None:
    """Draw a :func:`floor_plan` on the matplotlib axes ``ax`` (filled footprints, wall lines)."""
    from matplotlib.patches import Polygon

    for polygon, color in plan:
        if len(polygon) >= 3:
            ax.add_patch(Polygon(polygon, closed=True, fc=(*color, 0.35), ec="0.3", lw=0.4))
        else:
            ax.plot(polygon[:, 0], polygon[:, 1], color="0.3", lw=1.2)
