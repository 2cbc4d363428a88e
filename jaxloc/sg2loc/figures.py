"""Figures: particles per round and frame over the map's floor plan, with the MLE, the ground
truth and the trajectories (SG2Loc's Fig. 3)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from jaxloc.figures import draw_floor_plan, floor_plan
from jaxloc.scene import SceneGraph
from jaxloc.sg2loc._localization import SG2LocResult


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
                draw_floor_plan(ax, plan)
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
                draw_floor_plan(ax, plan)
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
