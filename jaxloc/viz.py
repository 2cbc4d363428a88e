"""Figures: particles per round and frame over the map's floor plan, with the MLE, the ground
truth and the trajectories (SG2Loc's Fig. 3)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from jaxloc.scene import SceneGraph
from jaxloc.sg2loc import SG2LocResult


def floor_plan(scene: SceneGraph) -> list[tuple[np.ndarray, np.ndarray]]:
    """Object footprints: per real object, the convex hull of its triangles' x-y corners, as
    ((K, 2) polygon in metres, world frame; (3,) RGB in [0, 1]). Objects whose corners span no
    area in x-y (a wall seen from above) give their x-y segment as a 2-point polygon."""
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


def _draw_floor_plan(ax, plan) -> None:
    from matplotlib.patches import Polygon

    for polygon, color in plan:
        if len(polygon) >= 3:
            ax.add_patch(Polygon(polygon, closed=True, fc=(*color, 0.35), ec="0.3", lw=0.4))
        else:
            ax.plot(polygon[:, 0], polygon[:, 1], color="0.3", lw=1.2)


def plot_rounds(
    result: SG2LocResult,
    poses_gt: np.ndarray | None,
    path: str | Path,
    bounds: np.ndarray | None = None,
    max_frames: int = 6,
    scene: SceneGraph | None = None,
) -> Path:
    """Draw the particles (x-y, top view) of every round (rows) and frame (columns) to a PNG.

    With ``scene``, each panel lies over the map's floor plan (:func:`floor_plan`) and a last
    column shows the estimated (final round) and true trajectories.

    Args:
        result: output of :func:`jaxloc.sg2loc.localize`.
        poses_gt: (T, 4) ground-truth poses, or None when there are none.
        path: the PNG file to write.
        bounds: optional (2, 3) scene AABB for the axes (default the scene's, when given).
        max_frames: frames shown per round (evenly spaced, always including the last).
        scene: the map, for the floor plan and the trajectory panel.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    particles = np.asarray(result.particles)
    weights = np.asarray(result.particle_weights)
    mle = np.asarray(result.round_mle)
    num_rounds, num_frames = particles.shape[:2]
    frames = np.unique(
        np.linspace(0, num_frames - 1, min(max_frames, num_frames)).round().astype(int)
    )
    plan = floor_plan(scene) if scene is not None else None
    if bounds is None and scene is not None:
        bounds = np.asarray(scene.bounds)
    columns = len(frames) + (plan is not None)
    fig, axes = plt.subplots(
        num_rounds, columns, figsize=(2.4 * columns, 2.4 * num_rounds), squeeze=False
    )
    for r in range(num_rounds):
        for c, t in enumerate(frames):
            ax = axes[r, c]
            if plan is not None:
                _draw_floor_plan(ax, plan)
            alive = weights[r, t] > 0
            ax.scatter(particles[r, t, alive, 0], particles[r, t, alive, 1], s=1, c="0.45")
            if poses_gt is not None:
                ax.plot(*poses_gt[t, :2], "o", color="tab:green", ms=6, label="ground truth")
            ax.plot(*mle[r, t, :2], "x", color="tab:blue", ms=7, mew=2, label="MLE")
            if r == num_rounds - 1:
                ax.set_xlabel(f"frame {t + 1}")
            if c == 0:
                ax.set_ylabel(f"round {r + 1}")
        if plan is not None:
            ax = axes[r, -1]
            if r == 0:
                _draw_floor_plan(ax, plan)
                if poses_gt is not None:
                    ax.plot(poses_gt[:, 0], poses_gt[:, 1], "-o", color="tab:green", ms=2, lw=1)
                ax.plot(mle[-1, :, 0], mle[-1, :, 1], "-x", color="tab:blue", ms=3, lw=1)
                ax.set_title("trajectories", fontsize=7)
            else:
                ax.axis("off")
    for ax in axes.ravel():
        if bounds is not None:
            ax.set_xlim(bounds[0, 0], bounds[1, 0])
            ax.set_ylim(bounds[0, 1], bounds[1, 1])
        ax.set_aspect("equal")
        ax.set_xticks([])
        ax.set_yticks([])
    axes[0, 0].legend(loc="upper left", fontsize=6)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
