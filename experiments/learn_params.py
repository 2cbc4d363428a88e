"""Learned vs hand-set SG2Loc likelihood parameters (sigma, lambda_depth, lambda_color).

1. Training windows (:func:`jaxloc.sg2loc.learn.sequence_windows`) from synthetic training episodes
   (seeds 2000, 2001, ...), scored on both ray grids the filter uses (the coarse and the fine
   stride); Adam on the window loss (:mod:`jaxloc.sg2loc.learn`, default ``"nll"``;
   ``"expected_error"`` is trained too, for comparison of the learned values only).
2. Held-out episodes (seeds 3000, 3001, ...; never used for training or in tests): windows for
   the learning curve's held-out loss, and the full coarse-to-fine filter
   (:func:`jaxloc.sg2loc.localize`) with the hand-set defaults (sigma 0.6, lambdas 2, 2) and
   with the learned ("nll") parameters, the same PRNG key for both.

Variants: ``--windows filter`` trains on the filter's own particle sets instead
(:func:`jaxloc.sg2loc.learn.filter_windows`, ``--iterations`` alternations of filter runs on the
training episodes and fits); ``--loss-frames every`` scores every prefix of a window
(``LossConfig.frames``); ``--kernel-m/--kernel-deg/--box-m/--box-deg`` set the loss kernel and the
local particles' box. The tables add a per-scene paired comparison and a bootstrap over scenes.

Reduced, CPU-feasible scale (the machine is 2 shared cores): small coarse rooms (4-6 x 4-5 m,
15-20 objects of 100-200 vertices), 160x90 images with the 9x16 patch grid, strides (10, 5)
(the paper's 20, 8, 4 at 960x540 scaled to a 6x smaller image, two rounds), capacity 400.

    nice -n 5 .venv/bin/python experiments/learn_params.py
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import jax  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from jaxloc.camera import stride_grid  # noqa: E402
from jaxloc.metrics import SG2LOC_RECALL_THRESHOLDS, summarize, yaw_pose_errors  # noqa: E402
from jaxloc.scene import SceneGraph  # noqa: E402
from jaxloc.sg2loc import ObservationConfig, SG2LocConfig, learn, localize  # noqa: E402
from jaxloc.synthetic.indoor import EpisodeConfig, RoomConfig, SensorConfig, make_episode

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "experiments" / "results" / "learn"

EPISODE_CONFIG = EpisodeConfig(
    room=RoomConfig(
        length_range=(4.0, 6.0),
        width_range=(4.0, 5.0),
        num_objects=(15, 20),
        vertex_range=(100, 200),
    ),
    sensor=SensorConfig(width=160, height=90),
)
STRIDES = (10, 5)
TRAIN_SEED0 = 2000
HELDOUT_SEED0 = 3000


def log(message: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {message}", flush=True)


def padded_scenes(episodes) -> list[SceneGraph]:
    """Every episode's map padded to one capacity (one compilation for all scenes)."""
    capacity = episodes[0].scene.capacity
    for episode in episodes[1:]:
        capacity = capacity.union(episode.scene.capacity)
    return [
        SceneGraph.from_meshes(
            list(e.room.meshes), e.room.labels, e.room.embeddings, e.room.colors, capacity=capacity
        )
        for e in episodes
    ]


def windows_of(
    key, episodes, scenes, starts, window_length, num_particles, half_width, yaw_half_range
) -> learn.Windows:
    parts = []
    for i, (episode, scene) in enumerate(zip(episodes, scenes, strict=True)):
        for stride in STRIDES:
            grid = stride_grid(episode.sequence.camera, stride, *episode.sequence.patch_shape)
            parts.append(
                learn.sequence_windows(
                    jax.random.fold_in(key, 100 * i + stride),
                    scene,
                    episode.sequence,
                    episode.poses_gt,
                    grid,
                    starts,
                    window_length,
                    num_particles,
                    local_half_width=half_width,
                    local_yaw_half_range=yaw_half_range,
                )
            )
    return learn.concat_windows(parts)


def filter_config(args, observation: ObservationConfig) -> SG2LocConfig:
    """The reduced-scale filter of this experiment (two rounds, capacity ``--capacity``)."""
    return SG2LocConfig(
        capacity=args.capacity, strides=STRIDES, box_half_widths=(0.8,), observation=observation
    )


def filter_windows_of(episodes, scenes, observation, args, seed0: int) -> learn.Windows:
    """Run the filter with ``observation`` on every episode; its particle sets as windows."""
    parts = []
    for i, (episode, scene) in enumerate(zip(episodes, scenes, strict=True)):
        result = localize(
            jax.random.key(seed0 + i), scene, episode.sequence, filter_config(args, observation)
        )
        used = dataclasses.replace(
            observation, use_depth=result.used_depth, use_color=result.used_color
        )
        parts.append(
            learn.filter_windows(
                scene,
                episode.sequence,
                episode.poses_gt,
                result.particles,
                result.particle_weights,
                STRIDES,
                used,
            )
        )
    return learn.concat_windows(parts)


def fit_on_filter_windows(
    key, args, start, default, losses, train_eps, train_scenes, held_eps, held_scenes
):
    """Alternate filter runs and fits: iteration i runs the filter on the training episodes with
    the current parameters, adds its particle sets to the training windows and continues Adam on
    all of them. The held-out windows (learning curve only) are the hand-set filter's."""
    t0 = time.time()
    held_windows = filter_windows_of(held_eps, held_scenes, default, args, HELDOUT_SEED0)
    log(f"held-out filter windows: {held_windows.valid.shape[0]} in {time.time() - t0:.0f} s")
    learned, curves = {}, {}
    for kind, loss in losses.items():
        params, collected, parts = start, [], []
        for it in range(args.iterations):
            t0 = time.time()
            observation = params.to_config(default)
            collected.append(
                filter_windows_of(
                    train_eps, train_scenes, observation, args, TRAIN_SEED0 + 1000 * it
                )
            )
            train_windows = learn.concat_windows(collected)
            params, history = learn.train(
                jax.random.fold_in(key, 3 + it),
                params,
                default,
                train_windows,
                held_windows,
                num_steps=args.steps,
                loss=loss,
            )
            parts.append(history._replace(step=history.step + it * args.steps))
            log_fit(f"{kind} iteration {it} ({train_windows.valid.shape[0]} windows)", history, t0)
        learned[kind] = params
        curves[kind] = learn.History(*(np.concatenate(xs) for xs in zip(*parts, strict=True)))
    return learned, curves


def log_fit(name: str, c: learn.History, t0: float) -> None:
    log(
        f"{name}: train loss {c.train_loss[0]:.3f} -> {c.train_loss[-1]:.3f}, held-out "
        f"{c.heldout_loss[0]:.3f} -> {c.heldout_loss[-1]:.3f}, sigma {c.sigma[-1]:.3f} "
        f"lambda_depth {c.lambda_depth[-1]:.3f} lambda_color {c.lambda_color[-1]:.3f} "
        f"({time.time() - t0:.0f} s)"
    )


def write_atomic(path: Path, text: str) -> None:
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--train-scenes", type=int, default=6)
    parser.add_argument("--heldout-scenes", type=int, default=5)
    parser.add_argument("--frames", type=int, default=8)
    parser.add_argument("--window", type=int, default=3)
    parser.add_argument("--particles", type=int, default=256)
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--capacity", type=int, default=400)
    parser.add_argument("--out", type=Path, default=OUT, help="results folder")
    loss_default = learn.LossConfig()
    parser.add_argument(
        "--kernel-m",
        type=float,
        default=float(loss_default.position_scale),
        help="loss kernel width in position (metres; default: the library's)",
    )
    parser.add_argument(
        "--kernel-deg",
        type=float,
        default=float(np.rad2deg(loss_default.yaw_scale)),
        help="loss kernel width in yaw (degrees; default: the library's)",
    )
    parser.add_argument(
        "--box-m",
        type=float,
        default=learn.LOCAL_HALF_WIDTH,
        help="half-width of the local particles' box (metres; default: the library's)",
    )
    parser.add_argument(
        "--box-deg",
        type=float,
        default=float(np.rad2deg(learn.LOCAL_YAW_HALF_RANGE)),
        help="yaw half-range of the local particles (degrees; default: the library's)",
    )
    parser.add_argument(
        "--loss-frames",
        choices=learn.LOSS_FRAMES,
        default=loss_default.frames,
        help="the loss of the whole window's posterior ('last') or of every prefix ('every')",
    )
    parser.add_argument(
        "--windows",
        choices=("box", "filter"),
        default="box",
        help="training windows: particles drawn around the truth and over the room ('box', "
        "jaxloc.sg2loc.learn.sequence_windows) or the filter's own particle sets ('filter', "
        "jaxloc.sg2loc.learn.filter_windows, alternating filter runs and fits)",
    )
    parser.add_argument(
        "--iterations", type=int, default=2, help="filter runs / fits with --windows filter"
    )
    args = parser.parse_args()
    out = args.out
    command = "nice -n 5 .venv/bin/python experiments/learn_params.py " + " ".join(sys.argv[1:])
    out.mkdir(parents=True, exist_ok=True)
    starts = tuple(range(0, args.frames - args.window + 1, args.window))

    t0 = time.time()
    train_eps = [
        make_episode(TRAIN_SEED0 + i, args.frames, EPISODE_CONFIG) for i in range(args.train_scenes)
    ]
    held_eps = [
        make_episode(HELDOUT_SEED0 + i, args.frames, EPISODE_CONFIG)
        for i in range(args.heldout_scenes)
    ]
    scenes = padded_scenes(train_eps + held_eps)
    train_scenes, held_scenes = scenes[: len(train_eps)], scenes[len(train_eps) :]
    log(f"{len(scenes)} episodes built in {time.time() - t0:.0f} s; capacity {scenes[0].capacity}")

    key = jax.random.key(0)
    default = ObservationConfig()
    start = learn.LikelihoodParams.from_config(default)
    losses = {
        kind: learn.LossConfig(
            kind=kind,
            frames=args.loss_frames,
            position_scale=args.kernel_m,
            yaw_scale=np.deg2rad(args.kernel_deg),
        )
        for kind in learn.LOSS_KINDS
    }
    if args.windows == "box":
        t0 = time.time()
        box = (args.box_m, float(np.deg2rad(args.box_deg)))
        train_windows = windows_of(
            jax.random.fold_in(key, 1),
            train_eps,
            train_scenes,
            starts,
            args.window,
            args.particles,
            *box,
        )
        held_windows = windows_of(
            jax.random.fold_in(key, 2),
            held_eps,
            held_scenes,
            starts,
            args.window,
            args.particles,
            *box,
        )
        log(
            f"windows: {train_windows.valid.shape[0]} train, {held_windows.valid.shape[0]} "
            f"held-out ({args.window} frames x {args.particles} particles) in "
            f"{time.time() - t0:.0f} s"
        )
        learned, curves = {}, {}
        for kind, loss in losses.items():
            t0 = time.time()
            learned[kind], curves[kind] = learn.train(
                jax.random.fold_in(key, 3),
                start,
                default,
                train_windows,
                held_windows,
                num_steps=args.steps,
                loss=loss,
            )
            log_fit(kind, curves[kind], t0)
    else:
        learned, curves = fit_on_filter_windows(
            key, args, start, default, losses, train_eps, train_scenes, held_eps, held_scenes
        )
    write_curves(curves, command, out)

    rows = {
        "hand-set": default,
        "learned (nll)": learned["nll"].to_config(default),
    }
    errors = {name: [] for name in rows}
    for i, (episode, scene) in enumerate(zip(held_eps, held_scenes, strict=True)):
        for name, observation in rows.items():
            t0 = time.time()
            config = filter_config(args, observation)
            result = localize(jax.random.key(HELDOUT_SEED0 + i), scene, episode.sequence, config)
            pos, rot = yaw_pose_errors(np.asarray(result.poses), episode.poses_gt)
            errors[name].append((pos, rot))
            log(
                f"scene {HELDOUT_SEED0 + i} {name}: median {np.median(pos):.2f} m "
                f"{np.median(rot):.1f} deg, last {pos[-1]:.2f} m {rot[-1]:.1f} deg "
                f"({time.time() - t0:.0f} s)"
            )
        write_table(errors, rows, args, command, learned, curves, out)
    log("done")


def write_curves(curves, command: str, out: Path) -> None:
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    for kind, c in curves.items():
        axes[0].plot(c.step, c.train_loss, label=f"{kind}: train")
        axes[0].plot(c.step, c.heldout_loss, "--", label=f"{kind}: held-out")
        axes[1].plot(c.step, c.heldout_position_error, label=kind)
    c = curves["nll"]
    for name in ("sigma", "lambda_depth", "lambda_color"):
        axes[2].plot(c.step, getattr(c, name), label=name)
    axes[0].set(xlabel="Adam step", ylabel="window loss (own units)", title="loss")
    axes[1].set(xlabel="Adam step", ylabel="metres", title="held-out weighted mean position error")
    axes[2].set(xlabel="Adam step", title="parameters (nll)", yscale="log")
    for ax in axes:
        ax.legend(fontsize=7)
    fig.tight_layout()
    tmp = out / "learning_curve.tmp.png"
    fig.savefig(tmp, dpi=110)
    os.replace(tmp, out / "learning_curve.png")
    plt.close(fig)
    lines = [
        f"# {command}",
        "loss,step,train_loss,heldout_loss,heldout_position_error_m,"
        "sigma,lambda_depth,lambda_color",
    ]
    for kind, c in curves.items():
        for row in zip(*c, strict=True):
            lines.append(",".join([kind] + [f"{v:.6g}" for v in row]))
    write_atomic(out / "learning_curve.csv", "\n".join(lines) + "\n")


def paired_lines(hand_set: list, learned: list, resamples: int = 2000) -> list[str]:
    """Per-scene comparison of two runs on the same scenes: wins / losses / ties of the scene's
    median and last-frame position error (ties within 1 cm), and a bootstrap over scenes (95 %
    interval) of the difference of the pooled median position error and of R@(0.25 m, 10 deg)."""
    count = min(len(hand_set), len(learned))
    if count == 0:
        return []
    lines = [f"Paired over the {count} scenes (learned vs hand-set):", ""]
    for label, pick in (("median position error", np.median), ("last-frame position", None)):
        a = np.array([pick(p) if pick else p[-1] for p, _ in hand_set[:count]])
        b = np.array([pick(p) if pick else p[-1] for p, _ in learned[:count]])
        wins, losses = int(np.sum(b < a - 0.01)), int(np.sum(b > a + 0.01))
        lines.append(
            f"- {label} per scene: learned better on {wins}, worse on {losses}, "
            f"within 1 cm on {count - wins - losses}"
        )
    rng = np.random.default_rng(0)
    diffs = {"median": [], "recall": []}
    for _ in range(resamples):
        picks = rng.integers(0, count, count)
        stats = []
        for run in (hand_set, learned):
            pos = np.concatenate([run[i][0] for i in picks])
            rot = np.concatenate([run[i][1] for i in picks])
            stats.append((np.median(pos), np.mean((pos < 0.25) & (rot < 10.0))))
        diffs["median"].append(stats[1][0] - stats[0][0])
        diffs["recall"].append(stats[1][1] - stats[0][1])
    for key, label, unit in (
        ("median", "pooled median position error", " m"),
        ("recall", "pooled R@(0.25 m, 10 deg)", ""),
    ):
        lo, hi = np.percentile(diffs[key], [2.5, 97.5])
        lines.append(
            f"- {label}, learned minus hand-set, bootstrap over scenes: 95 % interval "
            f"[{lo:+.3f}, {hi:+.3f}]{unit}"
        )
    return lines


def write_table(errors, rows, args, command, learned, curves, out) -> None:
    header = ["parameters", "sigma", "lambda_depth", "lambda_color", "frames"]
    summaries = {}
    for name, observation in rows.items():
        pos = np.concatenate([p for p, _ in errors[name]])
        rot = np.concatenate([r for _, r in errors[name]])
        last_pos = np.array([p[-1] for p, _ in errors[name]])
        last_rot = np.array([r[-1] for _, r in errors[name]])
        s = summarize(pos, rot)
        s_last = summarize(last_pos, last_rot)
        values = [float(observation.sigma), float(observation.lambda_depth)]
        values.append(float(observation.lambda_color))
        summaries[name] = (values, pos.size, s, s_last)
    keys = ["median_pos_m", "median_rot_deg"] + [
        f"R@{p:g}m,{r:g}deg" for p, r in SG2LOC_RECALL_THRESHOLDS
    ]
    csv_rows = [["# " + command], header + keys + [f"last_{k}" for k in keys]]
    md = [
        "# Hand-set vs learned likelihood parameters on held-out scenes",
        "",
        f"Command: `{command}`",
        "",
        f"Held-out seeds {HELDOUT_SEED0}..{HELDOUT_SEED0 + len(errors['hand-set']) - 1} "
        f"({len(errors['hand-set'])} scenes done of {args.heldout_scenes}), {args.frames} frames "
        f"each, 160x90 images, strides {STRIDES}, capacity {args.capacity}; errors of the final "
        "round's MLE at every frame (all frames) and at the last frame. Recalls are fractions.",
        "",
        "| parameters | sigma | lambda_depth | lambda_color | n | median pos (m) | median rot (deg)"
        " | R@0.25m,2deg | R@0.1m,5deg | R@0.25m,10deg | last-frame median pos (m) | "
        "last-frame R@0.25m,10deg |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, (values, count, s, s_last) in summaries.items():
        csv_rows.append(
            [name, *[f"{v:.4g}" for v in values], str(count)]
            + [f"{s[k]:.4g}" for k in keys]
            + [f"{s_last[k]:.4g}" for k in keys]
        )
        md.append(
            f"| {name} | {values[0]:.3f} | {values[1]:.3f} | {values[2]:.3f} | {count} | "
            + " | ".join(f"{s[k]:.3f}" for k in keys)
            + f" | {s_last['median_pos_m']:.3f} | {s_last['R@0.25m,10deg']:.3f} |"
        )
    md += ["", *paired_lines(errors["hand-set"], errors["learned (nll)"])]
    md += ["", "Learned values of both losses (after the last Adam step):", ""]
    for kind, params in learned.items():
        sigma, ld, lc = (float(v) for v in params.values())
        c = curves[kind]
        md.append(
            f"- `{kind}`: sigma {sigma:.3f}, lambda_depth {ld:.3f}, lambda_color {lc:.3f}; "
            f"train loss {c.train_loss[0]:.3f} -> {c.train_loss[-1]:.3f}, held-out loss "
            f"{c.heldout_loss[0]:.3f} -> {c.heldout_loss[-1]:.3f}, held-out weighted position "
            f"error {c.heldout_position_error[0]:.3f} -> {c.heldout_position_error[-1]:.3f} m"
        )
    write_atomic(out / "table.md", "\n".join(md) + "\n")
    write_atomic(out / "table.csv", "\n".join(",".join(r) for r in csv_rows) + "\n")
    params_json = {k: [float(v) for v in p.values()] for k, p in learned.items()}
    write_atomic(out / "learned_params.json", json.dumps(params_json, indent=1) + "\n")


if __name__ == "__main__":
    main()
