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


#: The demo's strides unless ``--strides`` is given: the paper's (20, 8, 4), each lowered where a
#: small image would give its round fewer rays per side than SSIM's window.
PAPER_STRIDES = (20, 8, 4)


def ray_grid_shape(stride: int, width: int, height: int) -> tuple[int, int]:
    """(rows, cols) of the ray grid of ``jaxloc.stride_grid`` at ``stride`` on a width x height
    image."""
    return len(range(stride // 2, height, stride)), len(range(stride // 2, width, stride))


def fits_ssim(stride: int, width: int, height: int) -> bool:
    """Whether ``stride`` casts at least SSIM's 7 x 7 rays on a width x height image."""
    from jaxloc.sg2loc._scores import SSIM_WINDOW

    return min(ray_grid_shape(stride, width, height)) >= SSIM_WINDOW


def largest_fitting_stride(width: int, height: int, upper: int) -> int | None:
    """The largest stride <= ``upper`` whose ray grid holds SSIM's window (None: not even 1)."""
    return next((s for s in range(upper, 0, -1) if fits_ssim(s, width, height)), None)


def check_image_size(args: argparse.Namespace) -> None:
    """``--width`` and ``--height`` of the demo's room (and ``bench filter``'s): the image must
    hold the synthetic sensor's patch grid (9 x 16 patches, at least one pixel each), an
    InputError naming the options otherwise."""
    from jaxloc.cli._errors import InputError
    from jaxloc.synthetic.indoor import SensorConfig

    rows, cols = SensorConfig.patch_rows, SensorConfig.patch_cols
    if args.width < cols or args.height < rows:
        raise InputError(
            f"--width {args.width} --height {args.height}: the image must hold the "
            f"{rows} x {cols} patch grid (want --width >= {cols} and --height >= {rows})"
        )


def fitting_strides(args: argparse.Namespace) -> tuple[int, ...]:
    """The rounds' strides for ``args.width x args.height``: ``--strides`` as given (an
    InputError naming the largest stride that fits if one gives fewer than 7 x 7 rays), else the
    paper's, each lowered to the largest stride that fits."""
    from jaxloc.cli._errors import InputError
    from jaxloc.sg2loc._scores import SSIM_WINDOW

    given = () if args.strides is None else tuple(args.strides)
    largest = largest_fitting_stride(args.width, args.height, max(PAPER_STRIDES + given))
    if largest is None:
        raise InputError(
            f"--width {args.width} --height {args.height}: the image is too small for the colour "
            f"score's {SSIM_WINDOW} x {SSIM_WINDOW} SSIM window (want at least {SSIM_WINDOW} px "
            "per side)"
        )
    if args.strides is None:
        return tuple(min(s, largest) for s in PAPER_STRIDES)
    too_coarse = [s for s in given if not fits_ssim(s, args.width, args.height)]
    if too_coarse:
        rows, cols = ray_grid_shape(too_coarse[0], args.width, args.height)
        raise InputError(
            f"--strides: stride {too_coarse[0]} gives a {rows} x {cols} ray grid at "
            f"{args.width} x {args.height}, smaller than SSIM's {SSIM_WINDOW} x {SSIM_WINDOW} "
            f"window; use strides of at most {largest}"
        )
    return given


def check_demo(args: argparse.Namespace) -> None:
    """The demo's options that depend on each other, before anything is built: the image holds
    the patch grid, the strides fit it (:func:`fitting_strides`)."""
    check_image_size(args)
    fitting_strides(args)


def run_demo(args: argparse.Namespace) -> int:
    import jax

    from jaxloc.camera import stride_grid
    from jaxloc.metrics import summarize, yaw_pose_errors
    from jaxloc.sg2loc import (
        FrameSequence,
        KLDConfig,
        SG2LocConfig,
        localize,
        render_batch,
        warm_up,
    )
    from jaxloc.sg2loc.figures import plot_rounds
    from jaxloc.synthetic import indoor

    strides = fitting_strides(args)
    if args.strides is None and strides != PAPER_STRIDES:
        shown = ",".join(map(str, strides))
        print(
            f"strides {shown} (the paper's 20,8,4, lowered to fit a "
            f"{args.width} x {args.height} image)"
        )
    start = time.perf_counter()
    episode_config = demo_episode_config(args)
    room = indoor.make_room(args.seed, episode_config.room)
    scene = indoor.scene_graph(room)
    sg2loc_config = SG2LocConfig(
        capacity=args.particles,
        strides=strides,
        kld=KLDConfig(min_particles=min(500, args.particles), max_particles=args.particles),
    )
    key = jax.random.key(args.seed)
    # the filter's programs compile on the second core while the query frames are rendered
    # (make_episode's own two steps, split around it)
    sensor = episode_config.sensor
    patch_shape = (sensor.patch_rows, sensor.patch_cols)
    frame_shapes = FrameSequence.zeros(
        sensor.camera(), args.frames, patch_shape, room.embeddings.shape[1]
    )
    warm_up(key, scene, frame_shapes, sg2loc_config, progress=True)
    del frame_shapes  # 50 MB of zeros at 960 x 540
    episode = indoor.episode_in_room(room, room, args.seed, args.frames, episode_config)
    print(
        f"room {episode.room.size[0]:.1f} x {episode.room.size[1]:.1f} m: "
        f"{scene.num_objects} objects, {scene.num_triangles} triangles, "
        f"map {scene.storage_mb():.2f} MB "
        f"({time.perf_counter() - start:.1f} s to build)"
    )
    camera = episode.sequence.camera
    grid = stride_grid(camera, min(10, strides[0]), *episode.sequence.patch_shape)
    num_views = min(3, args.frames)
    poses = np.asarray(episode.poses_gt[:num_views], np.float32)
    # the views on the host at once: eager indexing compiles a small program per array shape
    views = jax.tree.map(np.asarray, jax.jit(render_batch)(scene, poses, camera, grid))
    for t in range(num_views):
        seen = np.unique(views.object_id[t])
        depth = views.depth[t][np.isfinite(views.depth[t])]
        print(
            f"view {t + 1}: {np.sum(seen >= 0)} objects visible, depth {depth.min():.2f}-"
            f"{depth.max():.2f} m, {np.mean(views.valid[t]):.0%} rays hit"
        )
    result = localize(key, scene, episode.sequence, sg2loc_config, progress=True)
    pos_err, rot_err = yaw_pose_errors(np.asarray(result.poses), episode.poses_gt)
    localized = np.asarray(result.localized)
    for t, (p, r) in enumerate(zip(pos_err, rot_err, strict=True)):
        verdict = "localized" if localized[t] else "not localized"
        print(f"frame {t + 1}: {verdict}, position error {p:.3f} m, rotation error {r:.2f} deg")
    summary = summarize(pos_err[-1:], rot_err[-1:])
    print(
        f"last frame: {summary['median_pos_m']:.3f} m, {summary['median_rot_deg']:.2f} deg; "
        f"total {time.perf_counter() - start:.0f} s"
    )
    figure = plot_rounds(result, episode.poses_gt, args.out, scene=scene)
    print(f"figure: {figure}")
    return 0
