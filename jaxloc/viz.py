"""Figures: particles per round and frame with the MLE and the ground truth (SG2Loc's Fig. 3)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from jaxloc.sg2loc import SG2LocResult


def plot_rounds(
    result: SG2LocResult,
    poses_gt: np.ndarray,
    path: str | Path,
    bounds: np.ndarray | None = None,
    max_frames: int = 6,
) -> Path:
    """Draw the particles (x-y, top view) of every round (rows) and frame (columns) to a PNG.

    Args:
        result: output of :func:`jaxloc.sg2loc.localize`.
        poses_gt: (T, 4) ground-truth poses.
        path: the PNG file to write.
        bounds: optional (2, 3) scene AABB for the axes.
        max_frames: frames shown per round (evenly spaced, always including the last).
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
    fig, axes = plt.subplots(
        num_rounds, len(frames), figsize=(2.4 * len(frames), 2.4 * num_rounds), squeeze=False
    )
    for r in range(num_rounds):
        for c, t in enumerate(frames):
            ax = axes[r, c]
            alive = weights[r, t] > 0
            ax.scatter(particles[r, t, alive, 0], particles[r, t, alive, 1], s=1, c="0.6")
            ax.plot(*poses_gt[t, :2], "o", color="tab:green", ms=6, label="ground truth")
            ax.plot(*mle[r, t, :2], "x", color="tab:blue", ms=7, mew=2, label="MLE")
            if bounds is not None:
                ax.set_xlim(bounds[0, 0], bounds[1, 0])
                ax.set_ylim(bounds[0, 1], bounds[1, 1])
            ax.set_aspect("equal")
            ax.set_xticks([])
            ax.set_yticks([])
            if r == num_rounds - 1:
                ax.set_xlabel(f"frame {t + 1}")
            if c == 0:
                ax.set_ylabel(f"round {r + 1}")
    axes[0, 0].legend(loc="upper left", fontsize=6)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
