"""``jaxloc demo``: SG2Loc in an embedded synthetic room."""

from __future__ import annotations

import argparse
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from jaxloc.cli._errors import reading
from jaxloc.cli._options import RERUN_HELP, add_list, command, given, positive_int, seed

_DESCRIPTION = """\
Localize a camera in an embedded synthetic room (SG2Loc, no downloads).

Builds a synthetic room and a query sequence, renders a few views, runs the coarse-to-fine
particle filter with a progress bar, prints per-frame errors and writes a figure of the particles
per round and frame.
"""
_EPILOG = """\
examples:
  jaxloc demo
  jaxloc demo --seed 3 --frames 10 --out demo.png
  jaxloc demo --width 160 --height 120   # strides lowered to fit: 18,8,4
  jaxloc demo --strides 10 6 4           # or --strides 10,6,4
  jaxloc demo --rerun demo.rrd           # then: rerun demo.rrd (pip install "jaxloc[viz]")
"""


def add_parser(commands) -> None:
    """Register ``demo`` on the ``jaxloc`` subcommand parsers."""
    demo = command(commands, "demo", _DESCRIPTION, _EPILOG)
    add = demo.add_argument
    add("--seed", type=seed, default=1, help="room and sequence seed")
    add("--frames", type=positive_int, default=6, help="frames in the sequence")
    add("--particles", type=positive_int, help="particle capacity (default SG2LocConfig.capacity)")
    add("--width", type=positive_int, help="image width, px (default SensorConfig.width)")
    add("--height", type=positive_int, help="image height, px (default SensorConfig.height)")
    strides = "pixel stride of each coarse-to-fine round, each casting at least SSIM's 7 x 7 rays"
    fit = "(default SG2LocConfig.strides, each lowered to the largest that fits the image)"
    add_list(add, "--strides", positive_int, "20,8,4", f"{strides} {fit}", metavar="S")
    add("--out", type=Path, default=Path("jaxloc_demo.png"), help="figure (PNG)")
    add("--rerun", type=Path, metavar="F.rrd", help=RERUN_HELP)


def demo_episode_config(args: argparse.Namespace):
    """The demo's room seen by the synthetic camera of ``--width`` x ``--height`` (an InputError
    if that cannot hold its patch grid); ``bench filter``'s too (shared compilations)."""
    from jaxloc.synthetic import indoor

    with reading("--width/--height"):
        sensor = indoor.SensorConfig(**given(width=args.width, height=args.height))
    room = indoor.RoomConfig(length_range=(4.0, 5.0), width_range=(4.0, 5.0), num_objects=(15, 18))
    return indoor.EpisodeConfig(room=room, sensor=sensor)


def fitting_strides(args: argparse.Namespace) -> tuple[int, ...]:
    """``--strides`` (an InputError if one casts fewer than SSIM's 7 x 7 rays on the image), else
    ``SG2LocConfig.strides``, each lowered to the largest stride that fits."""
    from jaxloc.sg2loc import SG2LocConfig, check_ssim_strides
    from jaxloc.sg2loc._scores import largest_ssim_stride

    sensor = demo_episode_config(args).sensor
    if args.strides is None:
        largest = largest_ssim_stride(sensor.width, sensor.height)
        return tuple(min(s, largest) for s in SG2LocConfig.strides)
    with reading():
        check_ssim_strides(args.strides, sensor.width, sensor.height, "--strides")
    return args.strides


def run_demo(args: argparse.Namespace) -> int:
    import jax

    from jaxloc.camera import stride_grid
    from jaxloc.io import write_rerun
    from jaxloc.metrics import summarize_sequence
    from jaxloc.sg2loc import (
        FrameSequence,
        SG2LocConfig,
        kld_for_capacity,
        localize,
        render_batch,
        warm_up,
    )
    from jaxloc.sg2loc.figures import plot_rounds
    from jaxloc.synthetic import indoor

    strides = fitting_strides(args)
    episode_config = demo_episode_config(args)
    sensor = episode_config.sensor
    if args.strides is None and strides != SG2LocConfig.strides:
        shown, paper = (",".join(map(str, s)) for s in (strides, SG2LocConfig.strides))
        print(
            f"strides {shown} (the paper's {paper}, lowered to fit a {sensor.width} x "
            f"{sensor.height} image)"
        )
    start = time.perf_counter()
    room = indoor.make_room(args.seed, episode_config.room)
    scene = indoor.scene_graph(room)
    capacity = args.particles or SG2LocConfig.capacity
    config = SG2LocConfig(capacity=capacity, strides=strides, kld=kld_for_capacity(capacity))
    key = jax.random.key(args.seed)
    patches, dim = (sensor.patch_rows, sensor.patch_cols), room.embeddings.shape[1]
    with ThreadPoolExecutor(1) as pool:  # the query renders (mostly GIL-free) as the filter traces
        rendering = pool.submit(
            indoor.episode_in_room, room, room, args.seed, args.frames, episode_config
        )
        frame_shapes = FrameSequence.zeros(sensor.camera(), args.frames, patches, dim)
        warm_up(key, scene, frame_shapes, config, progress=True)
        del frame_shapes  # 50 MB of zeros at 960 x 540
        episode = rendering.result()
    print(
        f"room {episode.room.size[0]:.1f} x {episode.room.size[1]:.1f} m: "
        f"{scene.num_objects} objects, {scene.num_triangles} triangles, map "
        f"{scene.storage_mb():.2f} MB ({time.perf_counter() - start:.1f} s to build)"
    )
    camera = episode.sequence.camera
    grid = stride_grid(camera, min(10, strides[0]), *episode.sequence.patch_shape)
    num_views = min(3, args.frames)
    poses = np.asarray(episode.poses_gt[:num_views], np.float32)
    # the views on the host at once: eager indexing compiles a small program per array shape
    views = jax.tree.map(np.asarray, jax.jit(render_batch)(scene, poses, camera, grid))
    per_view = zip(views.object_id, views.depth, views.valid, strict=True)
    for t, (ids, depth, hit) in enumerate(per_view, start=1):
        seen, depth = np.sum(np.unique(ids) >= 0), depth[np.isfinite(depth)]
        print(
            f"view {t}: {seen} objects visible, depth {depth.min():.2f}-{depth.max():.2f} m, "
            f"{np.mean(hit):.0%} rays hit"
        )
    result = localize(key, scene, episode.sequence, config, progress=True)
    errors = summarize_sequence(np.asarray(result.poses), episode.poses_gt)
    localized = np.asarray(result.localized)
    per_frame = (errors["position_error_m"], errors["rotation_error_deg"], localized)
    for t, (p, r, ok) in enumerate(zip(*per_frame, strict=True), start=1):
        verdict = "localized" if ok else "not localized"
        print(f"frame {t}: {verdict}, position error {p:.3f} m, rotation error {r:.2f} deg")
    summary = errors["last_frame"]
    print(
        f"last frame: {summary['median_pos_m']:.3f} m, {summary['median_rot_deg']:.2f} deg; "
        f"total {time.perf_counter() - start:.0f} s"
    )
    print(f"figure: {plot_rounds(result, episode.poses_gt, args.out, scene=scene)}")
    if args.rerun is not None:
        path = write_rerun(args.rerun, scene, result, episode.sequence, episode.poses_gt)
        print(f"rerun: {path}")
    return 0
