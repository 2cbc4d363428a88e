"""The shape of SG2Loc's Tables 1, 2 and 7 and Fig. 3 on synthetic indoor scenes (seeds >= 1000).

Each scene is ``jaxloc.synthetic.indoor.make_episode(seed, T, config)`` with the dataset's realistic
defaults (20 % patch confusions, cosine 0.7-0.9, 2 % depth noise, 10 % holes, 2 cm / 1 degree
ego-motion drift per frame, 10 % of objects changed), at the paper's scale by default: 960x540
frames, strides 20 / 8 / 4, 2500 particles (``--width --height --strides --capacity`` reduce it;
``experiments/results/sg2loc_reduced/`` keeps the earlier 160x90 runs, see its NOTES.md).
Sequences of length T are the first T frames of one trajectory per scene. Maps are padded to one
shared :class:`jaxloc.scene.Capacity` so every scene reuses the compiled filter step.

Runs (``--phase``):

* ``A``: the default benchmark, semantic + depth + RGB, coarse-to-fine, 10 frames, on every scene
  (the accuracy check and Table 1/2's 10-frame column), with per-round diagnostics;
* ``B``: Table 7's ablations on 5-frame sequences (full, semantic only, semantic + depth, fixed
  particle count instead of KLD-sampling, a single coarse round) and Table 1/2's 5-frame column;
* ``C``: Table 1/2's 25- and 50-frame columns on the first ``--long-scenes`` scenes.

``--frames`` keeps only the jobs of those sequence lengths (e.g. ``--phase C --frames 25``).

Every finished run appends a row to ``runs_<phase>.csv`` (and per-frame errors to
``frames_<phase>.csv``) at once, so a cut run still leaves results; ``--report`` only rebuilds the
markdown tables and the figure from the CSVs present. Errors are the final round's MLE against the
ground truth, via :mod:`jaxloc.metrics`; "last" is the sequence's last frame (the filter's
estimate after the whole sequence), "all" pools every frame of the final round.

    nohup nice -n 5 env JAX_PLATFORMS=cpu .venv/bin/python experiments/sg2loc_tables.py \
        --phase A > /tmp/sg2loc_A.log 2>&1 &
    .venv/bin/python experiments/sg2loc_tables.py --report
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import functools
import os
import sys
import time
from pathlib import Path

import jax
import numpy as np

from jaxloc.geometry import wrap_angle
from jaxloc.metrics import SG2LOC_RECALL_THRESHOLDS, summarize, yaw_pose_errors
from jaxloc.scene import Capacity, SceneGraph
from jaxloc.sg2loc import (
    FrameSequence,
    KLDConfig,
    ObservationConfig,
    SG2LocConfig,
    carry_back,
    localize,
)
from jaxloc.synthetic.indoor import EpisodeConfig, SensorConfig, make_episode

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "experiments" / "results" / "sg2loc"
RECALL_KEYS = [f"R@{p:g}m,{r:g}deg" for p, r in SG2LOC_RECALL_THRESHOLDS]
ROUND_FIELDS = [f"r{r}_{q}" for r in range(3) for q in ("pos", "rot", "pos0", "rot0")]
CENTRE_FIELDS = [f"c{r}_{q}" for r in (1, 2) for q in ("dx", "dy", "dz", "dyaw", "inbox")]
RUN_FIELDS = (
    ["seed", "variant", "frames", "seconds", "pos", "rot"]
    + ROUND_FIELDS
    + CENTRE_FIELDS
    + ["gt_carry_pos", "gt_carry_rot", "mean_particles"]
)


def variant_config(name: str, args: argparse.Namespace) -> SG2LocConfig:
    """The SG2Loc configuration of one table row (the scale of ``args``, paper schedule)."""
    strides = tuple(args.strides)
    kld = KLDConfig(max_particles=args.capacity)
    full = SG2LocConfig(capacity=args.capacity, strides=strides, kld=kld)
    if name == "full":
        return full
    if name == "semantic":  # S_max = 2: the paper's sigma 0.2 of section 3.3
        observation = ObservationConfig(use_depth=False, use_color=False, sigma=0.2)
        return dataclasses.replace(full, observation=observation)
    if name == "semantic+depth":  # S_max = 4: sigma 0.2 scaled like the default 0.6 for S_max 6
        observation = ObservationConfig(use_color=False, sigma=0.4)
        return dataclasses.replace(full, observation=observation)
    if name == "fixed-count":  # w/o adaptive resampling: always `capacity` particles
        fixed = KLDConfig(min_particles=args.capacity, max_particles=args.capacity)
        return dataclasses.replace(full, kld=fixed)
    if name == "single-round":  # the paper's "coarse SG2Loc" (Table 12): one pass, coarsest stride
        return dataclasses.replace(full, strides=strides[:1])
    raise ValueError(f"unknown variant {name!r}")


PHASES = {
    "A": [("full", 10)],
    "B": [(v, 5) for v in ("full", "semantic", "semantic+depth", "fixed-count", "single-round")],
    "C": [("full", 25), ("full", 50)],
}


def prefix(sequence: FrameSequence, num_frames: int) -> FrameSequence:
    """The first ``num_frames`` frames of a sequence."""
    return FrameSequence(
        sequence.camera,
        sequence.patch_embeddings[:num_frames],
        sequence.ego_motion[: num_frames - 1],
        None if sequence.depth is None else sequence.depth[:num_frames],
        None if sequence.rgb is None else sequence.rgb[:num_frames],
        sequence.tilt[:num_frames],
    )


class SharedCapacity:
    """Pads every map to one capacity, grown (with slack) when a map does not fit.

    The starting capacity fits the rooms of the default :class:`RoomConfig` seen so far, so a map
    is usually built once; a map that does not fit raises, is measured and the capacity grows.
    """

    def __init__(self, slack: float = 1.3):
        self.capacity = Capacity(
            objects=48, triangles=48000, nodes=16000, leaves=16000, edges=0, embedding_dim=400
        )
        self.slack = slack

    def scene(self, room) -> SceneGraph:
        build = functools.partial(
            SceneGraph.from_meshes, list(room.meshes), room.labels, room.embeddings, room.colors
        )
        try:
            return build(capacity=self.capacity)
        except ValueError:
            grown = self.capacity.union(build().capacity)
        self.capacity = grown._replace(
            **{
                f: int(np.ceil(getattr(grown, f) * self.slack))
                for f in ("objects", "triangles", "nodes", "leaves", "edges")
            }
        )
        print(f"map capacity -> {self.capacity}", flush=True)
        return build(capacity=self.capacity)


def run_row(seed, variant, config, scene, episode, num_frames, key):
    """Localize the first ``num_frames`` frames: the CSV row, (T, 2) per-frame errors, result."""
    sequence = prefix(episode.sequence, num_frames)
    gt = episode.poses_gt[:num_frames]
    start = time.perf_counter()
    result = localize(key, scene, sequence, config, progress=True)
    poses = np.asarray(jax.block_until_ready(result.poses))
    seconds = time.perf_counter() - start
    pos, rot = yaw_pose_errors(poses, gt)
    row = {"seed": seed, "variant": variant, "frames": num_frames, "seconds": round(seconds, 1)}
    row.update(pos=pos[-1], rot=rot[-1])
    round_mle = np.asarray(result.round_mle)
    for r in range(3):
        if r < round_mle.shape[0]:
            p, a = yaw_pose_errors(round_mle[r], gt)
            row.update({f"r{r}_pos": p[-1], f"r{r}_rot": a[-1], f"r{r}_pos0": p[0]})
            row[f"r{r}_rot0"] = a[0]
    starts = np.asarray(result.round_start)
    for r in (1, 2):
        if r < starts.shape[0]:
            delta = starts[r] - gt[0]
            delta[3] = float(wrap_angle(delta[3]))
            half = float(config.box_half_widths[r - 1])
            inside = bool(np.all(np.abs(delta[:3]) <= half))
            inside &= bool(abs(delta[3]) <= float(config.yaw_half_range))
            row.update({f"c{r}_d{a}": delta[i] for i, a in enumerate(("x", "y", "z"))})
            row.update({f"c{r}_dyaw": np.rad2deg(delta[3]), f"c{r}_inbox": int(inside)})
    carried = np.asarray(carry_back(gt[-1], sequence.ego_motion))
    p, a = yaw_pose_errors(carried, gt[0])
    row.update(gt_carry_pos=p, gt_carry_rot=a)
    row["mean_particles"] = float(np.mean(np.asarray(result.num_particles)))
    for k, v in row.items():
        if isinstance(v, float | np.floating):
            row[k] = round(float(v), 4)
    return row, np.stack([pos, rot], axis=-1), result


def append_csv(path: Path, fields: list[str], rows: list[dict]) -> None:
    """Append rows (writing the header first for a new file); flushed at once."""
    new = not path.exists()
    with path.open("a", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=fields, restval="")
        if new:
            writer.writeheader()
        writer.writerows(rows)
        f.flush()
        os.fsync(f.fileno())


def run_phase(args: argparse.Namespace, phase: str) -> None:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    runs_csv, frames_csv = out / f"runs_{phase}.csv", out / f"frames_{phase}.csv"
    done = set()
    if runs_csv.exists():
        with runs_csv.open() as f:
            done = {(int(r["seed"]), r["variant"], int(r["frames"])) for r in csv.DictReader(f)}
    jobs = [(v, n) for v, n in PHASES[phase] if args.variants is None or v in args.variants]
    jobs = [(v, n) for v, n in jobs if args.frames is None or n in args.frames]
    if args.variants is not None:  # in the order given (cheap variants first, say)
        jobs.sort(key=lambda job: args.variants.index(job[0]))
    scenes = args.long_scenes if phase == "C" else args.scenes
    sensor = SensorConfig(width=args.width, height=args.height)
    episode_config = EpisodeConfig(sensor=sensor)
    shared = SharedCapacity()
    for seed in range(args.seed0, args.seed0 + scenes):
        todo = [(v, n) for v, n in jobs if (seed, v, n) not in done]
        if not todo:
            continue
        start = time.perf_counter()
        episode = make_episode(seed, max(n for _, n in todo), episode_config)
        scene = shared.scene(episode.room)
        print(f"seed {seed}: episode + map {time.perf_counter() - start:.1f} s", flush=True)
        for variant, num_frames in todo:
            config = variant_config(variant, args)
            key = jax.random.key(seed)
            row, errors, result = run_row(seed, variant, config, scene, episode, num_frames, key)
            append_csv(runs_csv, RUN_FIELDS, [row])
            if args.dump:
                Path(args.dump).mkdir(parents=True, exist_ok=True)
                np.savez(
                    Path(args.dump) / f"{seed}_{variant}_{num_frames}.npz",
                    round_mle=np.asarray(result.round_mle),
                    round_start=np.asarray(result.round_start),
                    num_particles=np.asarray(result.num_particles),
                    poses_gt=episode.poses_gt[:num_frames],
                )
            per_frame = [
                {"seed": seed, "variant": variant, "frames": num_frames, "t": t}
                | {"pos": round(float(e[0]), 4), "rot": round(float(e[1]), 4)}
                for t, e in enumerate(errors)
            ]
            append_csv(frames_csv, ["seed", "variant", "frames", "t", "pos", "rot"], per_frame)
            print(
                f"seed {seed} {variant} T={num_frames}: last {row['pos']:.3f} m "
                f"{row['rot']:.2f} deg; rounds "
                + " ".join(
                    f"{row.get(f'r{r}_pos', float('nan')):.3f}" for r in range(len(config.strides))
                )
                + f" ({row['seconds']:.0f} s)",
                flush=True,
            )
            if args.figure and seed == args.seed0 and variant == "full" and num_frames == 5:
                # Fig. 3: particles per round and frame, MLE vs ground truth (5 frames)
                from jaxloc.sg2loc.figures import plot_rounds

                bounds = np.asarray(scene.bounds)
                plot_rounds(result, episode.poses_gt[:5], out / "fig3_rounds.png", bounds)


def read_csv(path: Path) -> list[dict]:
    if not path.exists():
        return []
    with path.open() as f:
        return list(csv.DictReader(f))


def fmt(value: float, digits: int = 2) -> str:
    return "-" if value is None or not np.isfinite(value) else f"{value:.{digits}f}"


def report(args: argparse.Namespace, command: str) -> None:
    """Rebuild tables.md / tables.csv from every runs_*.csv and frames_*.csv present."""
    out = Path(args.out)
    runs = [r for phase in PHASES for r in read_csv(out / f"runs_{phase}.csv")]
    frames = [r for phase in PHASES for r in read_csv(out / f"frames_{phase}.csv")]
    groups: dict[tuple[str, int], list[dict]] = {}
    for r in runs:  # one run per (seed, variant, length): drop duplicates across phases
        groups.setdefault((r["variant"], int(r["frames"])), [])
        if all(int(q["seed"]) != int(r["seed"]) for q in groups[(r["variant"], int(r["frames"]))]):
            groups[(r["variant"], int(r["frames"]))].append(r)
    table = []
    for (variant, num_frames), rows in sorted(groups.items()):
        seeds = {int(r["seed"]) for r in rows}
        pos = np.array([float(r["pos"]) for r in rows])
        rot = np.array([float(r["rot"]) for r in rows])
        every = [
            f
            for f in frames
            if f["variant"] == variant
            and int(f["frames"]) == num_frames
            and int(f["seed"]) in seeds
        ]
        # keep one copy of each (seed, t)
        unique = {(int(f["seed"]), int(f["t"])): f for f in every}
        all_pos = np.array([float(f["pos"]) for f in unique.values()])
        all_rot = np.array([float(f["rot"]) for f in unique.values()])
        last, pooled = summarize(pos, rot), summarize(all_pos, all_rot)
        table.append(
            {"variant": variant, "frames": num_frames, "scenes": len(rows)}
            | {f"last_{k}": round(v, 4) for k, v in last.items()}
            | {f"all_{k}": round(v, 4) for k, v in pooled.items()}
            | {
                "seconds_per_frame": round(
                    float(np.median([float(r["seconds"]) for r in rows])) / num_frames, 2
                )
            }
        )
    if not table:
        print("no results yet")
        return
    fields = list(table[0].keys())
    tmp = out / "tables.csv.tmp"
    with tmp.open("w", newline="") as f:
        f.write(f"# {command}\n")
        writer = csv.DictWriter(f, fieldnames=fields)
        writer.writeheader()
        writer.writerows(table)
    tmp.replace(out / "tables.csv")

    def line(row, prefix_: str) -> str:
        recalls = " | ".join(fmt(row[f"{prefix_}_{k}"]) for k in RECALL_KEYS)
        return (
            f"{fmt(row[f'{prefix_}_mean_pos_m'])} | {fmt(row[f'{prefix_}_mean_rot_deg'])} | "
            f"{fmt(row[f'{prefix_}_median_pos_m'], 3)} | {fmt(row[f'{prefix_}_median_rot_deg'])} | "
            f"{recalls}"
        )

    header = (
        "| mean pos (m) | mean rot (deg) | median pos (m) | median rot (deg) | "
        + " | ".join(k.replace("R@", "R@").replace(",", ", ") for k in RECALL_KEYS)
        + " |"
    )
    md = [
        "# SG2Loc tables on synthetic scenes\n",
        "Commands (from the repository root; the runs append to the CSVs and skip finished "
        "(seed, variant, length) rows, so rerunning a command resumes it):\n",
        *[f"    {c}" for c in RUN_COMMANDS],
        f"    {command}\n",
        SCALE_NOTE,
    ]
    md.append("\n## Table 1/2 shape: full SG2Loc (semantic + depth + RGB, coarse-to-fine)\n")
    for caption, which in (
        ("Last frame of each sequence (the estimate after the whole sequence):\n", "last"),
        ("\nEvery frame of the final round (per-frame MLE), pooled:\n", "all"),
    ):
        md.append(caption)
        md.append("| frames | scenes " + header)
        md.append("|---" * (2 + 4 + len(RECALL_KEYS)) + "|")
        for row in table:
            if row["variant"] == "full":
                md.append(f"| {row['frames']} | {row['scenes']} | {line(row, which)} |")
    md.append("\n## Table 7 shape: ablations, 5-frame sequences, last frame\n")
    md.append("| variant | scenes " + header + " median s/frame (wall, shared CPU) |")
    md.append("|---" * (3 + 4 + len(RECALL_KEYS)) + "|")
    for row in table:
        if row["frames"] == 5:
            md.append(
                f"| {row['variant']} | {row['scenes']} | {line(row, 'last')} | "
                f"{row['seconds_per_frame']:.1f} |"
            )
    md.append(rounds_section(runs))
    tmp = out / "tables.md.tmp"
    tmp.write_text("\n".join(md) + "\n")
    tmp.replace(out / "tables.md")
    print("\n".join(md))


def rounds_section(runs: list[dict]) -> str:
    """Per-round last-frame errors of the coarse-to-fine runs (the round-2 investigation)."""
    rows = [r for r in runs if r["variant"] == "full" and r.get("r2_pos")]
    if not rows:
        return ""
    lines = ["\n## Coarse-to-fine rounds (full variant, every length), last frame\n"]
    lines.append(
        "| frames | runs | median pos r1 / r2 / r3 (m) | R@0.25m,10deg r1 / r2 / r3 | "
        "r3 worse than r2 by > 5 cm | centre in box r2 / r3 |"
    )
    lines.append("|---|---|---|---|---|---|")
    for num_frames in sorted({int(r["frames"]) for r in rows}):
        sel = [r for r in rows if int(r["frames"]) == num_frames]
        pos = np.array([[float(r[f"r{k}_pos"]) for k in range(3)] for r in sel])
        rot = np.array([[float(r[f"r{k}_rot"]) for k in range(3)] for r in sel])
        ok = np.mean((pos < 0.25) & (rot < 10.0), axis=0)
        worse = int(np.sum(pos[:, 2] > pos[:, 1] + 0.05))
        inbox = [np.mean([float(r[f"c{k}_inbox"]) for r in sel]) for k in (1, 2)]
        med = " / ".join(f"{v:.3f}" for v in np.median(pos, axis=0))
        lines.append(
            f"| {num_frames} | {len(sel)} | {med} | {' / '.join(f'{v:.2f}' for v in ok)} | "
            f"{worse} | {inbox[0]:.2f} / {inbox[1]:.2f} |"
        )
    return "\n".join(lines)


SCALE_NOTE = ""
RUN_COMMANDS = (
    "JAX_PLATFORMS=cpu python experiments/sg2loc_tables.py --phase A C",
    "JAX_PLATFORMS=cpu python experiments/sg2loc_tables.py --phase B --figure",
)


def main(argv: list[str] | None = None) -> None:
    global SCALE_NOTE
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--phase", nargs="+", choices=sorted(PHASES), help="runs to make, in order")
    parser.add_argument("--report", action="store_true", help="only rebuild tables from the CSVs")
    parser.add_argument("--quick", action="store_true", help="tiny smoke run (2 scenes, tiny)")
    parser.add_argument("--scenes", type=int, default=20)
    parser.add_argument("--long-scenes", type=int, default=20, help="scenes of phase C")
    parser.add_argument("--seed0", type=int, default=1000)
    parser.add_argument("--width", type=int, default=960)
    parser.add_argument("--height", type=int, default=540)
    parser.add_argument("--strides", type=int, nargs="+", default=[20, 8, 4])
    parser.add_argument("--capacity", type=int, default=2500)
    parser.add_argument("--frames", type=int, nargs="+", help="only jobs of these lengths")
    parser.add_argument("--figure", action="store_true", help="write fig3_rounds.png (phase B)")
    parser.add_argument("--out", default=str(OUT))
    parser.add_argument("--variants", nargs="+", help="only these variants, in this order")
    parser.add_argument("--dump", help="also save each run's per-round MLEs here (.npz)")
    args = parser.parse_args(argv)
    if args.quick:
        args.scenes, args.long_scenes, args.capacity = 2, 1, 600
        args.width, args.height, args.strides = 80, 45, [5, 3]
        args.out = str(Path(args.out) / "quick")
    SCALE_NOTE = (
        f"Scale: {args.width}x{args.height} sensor, 16x9 patches, strides {tuple(args.strides)}, "
        f"particle capacity {args.capacity} (KLD-sampling between 500 and {args.capacity}), "
        "seeds from " + str(args.seed0) + ". Paper: 960x540, strides (20, 8, 4), 2500 particles."
    )
    command = "python " + " ".join([Path(sys.argv[0]).as_posix(), *(argv or sys.argv[1:])])
    if args.report:
        report(args, command)
        return
    if args.phase is None:
        parser.error("give --phase A|B|C or --report")
    for phase in args.phase:
        run_phase(args, phase)


if __name__ == "__main__":
    main()
