"""A synthetic episode written as a ScanNet export folder, to try ``jaxloc localize-camera`` (and
time it) without downloading a dataset.

The layout is the one :mod:`jaxloc.io.scannet_export` reads (ScanNet's ``SensReader`` export):
``color/N.jpg`` (the episode's noisy colour frames), ``depth/N.png`` (uint16 millimetres, 0 where
the sensor has no depth), ``pose/N.txt`` (the true camera-to-world poses),
``intrinsic/intrinsic_color.txt`` and ``intrinsic_depth.txt`` (the episode's camera), and
``embeddings/N.npy`` (the episode's patch embeddings, in the map's embedding space).
"""

from __future__ import annotations

import os
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from PIL import Image

from jaxloc.geometry import yaw_pose_to_se3
from jaxloc.synthetic.indoor.rooms import Episode


def _write_matrix(path: Path, matrix: np.ndarray) -> None:
    path.write_text("".join(" ".join(repr(float(v)) for v in row) + "\n" for row in matrix))


def write_scannet_export(episode: Episode, folder: str | os.PathLike) -> Path:
    """Write ``episode``'s frames as a ScanNet export folder (frames numbered 0, 1, ...).

    The frames are the working-size images of ``episode.sequence`` (its depth and colour are
    required); the intrinsics are its camera's; the poses are the ground truth with each frame's
    tilt. Returns the folder. The map to localize in is ``episode.scene``
    (:func:`jaxloc.save_scene` it next to the folder).
    """
    sequence = episode.sequence
    if sequence.depth is None or sequence.rgb is None:
        raise ValueError("the episode needs depth and colour frames (SensorConfig)")
    folder = Path(folder)
    for sub in ("color", "depth", "pose", "intrinsic", "embeddings"):
        (folder / sub).mkdir(parents=True, exist_ok=True)
    camera = sequence.camera
    K = np.eye(4)
    K[0, 0], K[1, 1], K[0, 2], K[1, 2] = camera.fx, camera.fy, camera.cx, camera.cy
    _write_matrix(folder / "intrinsic" / "intrinsic_color.txt", K)
    _write_matrix(folder / "intrinsic" / "intrinsic_depth.txt", K)
    poses = jax.vmap(yaw_pose_to_se3)(jnp.asarray(episode.poses_gt), jnp.asarray(sequence.tilt))
    matrices = np.asarray(poses.as_matrix(), np.float64)
    for t in range(sequence.num_frames):
        rgb = np.round(np.clip(np.asarray(sequence.rgb[t]), 0, 1) * 255).astype(np.uint8)
        Image.fromarray(rgb).save(folder / "color" / f"{t}.jpg", quality=95)
        depth = np.asarray(sequence.depth[t])
        millimetres = np.round(np.clip(depth, 0, 65.535) * 1000).astype(np.uint16)
        Image.fromarray(millimetres).save(folder / "depth" / f"{t}.png")
        _write_matrix(folder / "pose" / f"{t}.txt", matrices[t])
        np.save(folder / "embeddings" / f"{t}.npy", np.asarray(sequence.patch_embeddings[t]))
    return folder
