"""``jaxloc demo``: SG2Loc in an embedded synthetic room."""

from __future__ import annotations

import argparse
import time

import numpy as np


def demo_episode_config(args: argparse.Namespace):
    """The demo's room (4-5 m square, 15-18 objects) seen by an ``args.width x args.height``
    camera; ``bench filter`` uses it too (same scene and camera: shared compilations)."""
    from jaxloc.synthetic import indoor

    return indoor.EpisodeConfig(
        room=indoor.RoomConfig(
            length_range=(4.0, 5.0), width_range=(4.0, 5.0), num_objects=(15, 18)
        ),
        sensor=indoor.SensorConfig(width=args.width, height=args.height),
    )


def run_demo(args: argparse.Namespace) -> int:
    import jax

    from jaxloc.camera import stride_grid
    from jaxloc.metrics import summarize, yaw_pose_errors
    from jaxloc.sg2loc import SG2LocConfig, localize
    from jaxloc.sg2loc.figures import plot_rounds
    from jaxloc.sg2loc.rendering import render_batch
    from jaxloc.sg2loc.resampling import KLDConfig
    from jaxloc.synthetic import indoor

    start = time.perf_counter()
    episode = indoor.make_episode(args.seed, args.frames, demo_episode_config(args))
    scene = episode.scene
    print(
        f"room {episode.room.size[0]:.1f} x {episode.room.size[1]:.1f} m: "
        f"{scene.num_objects} objects, {scene.num_triangles} triangles, "
        f"map {scene.storage_mb():.2f} MB "
        f"({time.perf_counter() - start:.1f} s to build)"
    )
    camera = episode.sequence.camera
    grid = stride_grid(camera, 10, *episode.sequence.patch_shape)
    num_views = min(3, args.frames)
    views = jax.jit(render_batch)(
        scene, jax.numpy.asarray(episode.poses_gt[:num_views]), camera, grid
    )
    for t in range(num_views):
        seen = np.unique(np.asarray(views.object_id[t]))
        depth = np.asarray(views.depth[t])
        depth = depth[np.isfinite(depth)]
        print(
            f"view {t + 1}: {np.sum(seen >= 0)} objects visible, depth {depth.min():.2f}-"
            f"{depth.max():.2f} m, {np.mean(np.asarray(views.valid[t])):.0%} rays hit"
        )
    sg2loc_config = SG2LocConfig(
        capacity=args.particles,
        strides=args.strides,
        kld=KLDConfig(min_particles=min(500, args.particles), max_particles=args.particles),
    )
    result = localize(
        jax.random.key(args.seed), scene, episode.sequence, sg2loc_config, progress=True
    )
    pos_err, rot_err = yaw_pose_errors(np.asarray(result.poses), episode.poses_gt)
    for t, (p, r) in enumerate(zip(pos_err, rot_err, strict=True)):
        print(f"frame {t + 1}: position error {p:.3f} m, rotation error {r:.2f} deg")
    summary = summarize(pos_err[-1:], rot_err[-1:])
    print(
        f"last frame: {summary['median_pos_m']:.3f} m, {summary['median_rot_deg']:.2f} deg; "
        f"total {time.perf_counter() - start:.0f} s"
    )
    figure = plot_rounds(result, episode.poses_gt, args.out, scene=scene)
    print(f"figure: {figure}")
    return 0
