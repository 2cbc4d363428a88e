"""Which per-frame evidence at SG2Loc's estimate tells a right estimate from a look-alike wrong
place: the verdict's own terms beside depth agreement measured by rendering the estimate.

For each seed, the condition of :func:`sg2loc_verdict_conditions.draw_condition` (image size,
strides, particles, likelihood width and weights, with or without depth and colour, camera
heights, sensor noise, patch confusion, mesh coarseness) and two 10-frame sequences, the map's
own room (``right``) and a look-alike wrong place (``wrong``), each localized offline
(:func:`jaxloc.sg2loc.localize`). Every frame's estimate is rendered on the final round's ray grid
and compared with the sequence's sensor depth, whether or not the filter used depth:

* ``inlier_10``, ``inlier_20``: the share of the rays with valid sensor depth whose rendered depth
  is within 0.1 m / 0.2 m of it (a rendered miss is an outlier);
* ``inlier_rel``: the same within 0.05 m + 5 % of the sensor depth;
* ``median_error``: the median absolute depth error over those rays (a miss counts 1 m);
* ``see_through``: the share where the map puts a surface more than 0.3 m in front of what the
  sensor sees (the sensor sees through a mapped object);
* ``occluded``: the share where the sensor sees something more than 0.3 m in front of the map.

``--report`` prints, per group (filter with depth, without depth), each term's AUC of separating
the frames within 0.25 m and 5 degrees in the right room (good) from the wrong place's frames
(1: every good frame scores higher; a term where lower is better is negated first), and the
10/50/90 % quantiles of both.

    JAX_PLATFORMS=cpu python experiments/sg2loc_verdict_evidence.py --run --seeds 5100-5119
    python experiments/sg2loc_verdict_evidence.py --report > \
        experiments/results/sg2loc_verdict_evidence/report_dev.txt
"""

from __future__ import annotations

import argparse
import csv
import functools
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from sg2loc_verdict import PLACE_OFFSET, parse_seeds  # noqa: E402
from sg2loc_verdict_conditions import (  # noqa: E402
    draw_condition,
    episode_config,
    sg2loc_config,
)

OUT = Path(__file__).resolve().parents[1] / "experiments" / "results" / "sg2loc_verdict_evidence"
#: (name, higher is better) of every logged term.
TERMS = [
    ("semantic_fraction", True),
    ("mass", True),
    ("depth_deficit", False),
    ("ess", False),
    ("spread_z", False),
    ("inlier_10", True),
    ("inlier_20", True),
    ("inlier_rel", True),
    ("median_error", False),
    ("see_through", False),
    ("occluded", False),
]
FIELDS = ["seed", "kind", "frame", "pos", "rot", "use_depth", "width", "sigma", "seconds"]
FIELDS += [name for name, _ in TERMS]


def depth_agreement(rendered: np.ndarray, sensor: np.ndarray) -> dict[str, float]:
    """The depth terms of one frame: ``rendered`` (R,) depth at the estimate (metres, +inf on a
    miss), ``sensor`` (R,) the sensor's at the same rays (0: no depth). All 0 with no valid
    sensor depth."""
    valid = np.isfinite(sensor) & (sensor > 0.0)
    if not valid.any():
        return {name: 0.0 for name in ("inlier_10", "inlier_20", "inlier_rel", "median_error",
                                       "see_through", "occluded")}  # fmt: skip
    s, r = sensor[valid], rendered[valid]
    hit = np.isfinite(r) & (r > 0.0)
    error = np.where(hit, np.abs(np.where(hit, r, 0.0) - s), np.inf)
    return {
        "inlier_10": float(np.mean(error <= 0.1)),
        "inlier_20": float(np.mean(error <= 0.2)),
        "inlier_rel": float(np.mean(error <= 0.05 + 0.05 * s)),
        "median_error": float(np.median(np.minimum(error, 1.0))),
        "see_through": float(np.mean(hit & (np.where(hit, r, 0.0) < s - 0.3))),
        "occluded": float(np.mean(hit & (np.where(hit, r, 0.0) > s + 0.3))),
    }


def run(seeds) -> None:
    import jax
    import jax.numpy as jnp
    from sg2loc_tables import SharedCapacity

    from jaxloc import enable_compilation_cache, stride_grid
    from jaxloc.metrics import yaw_pose_errors
    from jaxloc.sg2loc import localize
    from jaxloc.sg2loc._filter import frames_on_grid
    from jaxloc.sg2loc._rendering import render
    from jaxloc.synthetic.indoor import make_episode, make_lookalike_episode

    enable_compilation_cache()
    OUT.mkdir(parents=True, exist_ok=True)
    path = OUT / "frames_dev.csv"
    done = set()
    if path.exists():
        with path.open() as f:
            done = {(int(r["seed"]), r["kind"]) for r in csv.DictReader(f)}
    shared = SharedCapacity()
    for seed in seeds:
        jax.clear_caches()  # every condition compiles programs of its own shapes
        condition = draw_condition(seed, "relative", None)
        config = sg2loc_config(condition)
        generator = episode_config(condition)
        for kind in ("right", "wrong"):
            if (seed, kind) in done:
                continue
            if kind == "right":
                episode = make_episode(seed, 10, generator)
            else:
                episode = make_lookalike_episode(seed, seed + PLACE_OFFSET, 10, generator)
            scene, sequence = shared.scene(episode.room), episode.sequence
            start = time.perf_counter()
            result = localize(jax.random.key(seed), scene, sequence, config)
            poses = np.asarray(result.poses)
            seconds = time.perf_counter() - start
            grid = stride_grid(sequence.camera, config.strides[-1], *sequence.patch_shape)
            frames = frames_on_grid(sequence, grid)
            draw = functools.partial(
                render, scene, camera=sequence.camera, grid=grid, differentiable=False
            )
            views = jax.jit(jax.vmap(lambda p, t, draw=draw: draw(pose=p, tilt=t)))(
                jnp.asarray(poses), frames.tilt
            )
            if episode.in_map:
                pos, rot = yaw_pose_errors(poses, episode.poses_gt)
            else:
                pos = rot = np.full(len(poses), np.nan)
            verdict = jax.tree.map(np.asarray, result.info.verdict)
            rows = []
            for t in range(len(poses)):
                terms = {
                    "semantic_fraction": verdict.semantic_fraction[t],
                    "mass": verdict.mass[t],
                    "depth_deficit": verdict.depth_deficit[t],
                    "ess": verdict.ess_fraction[t],
                    "spread_z": verdict.spread[t, 2],
                    **depth_agreement(np.asarray(views.depth[t]), np.asarray(frames.depth[t])),
                }
                rows.append(
                    {
                        "seed": seed,
                        "kind": kind,
                        "frame": t,
                        "pos": round(float(pos[t]), 4),
                        "rot": round(float(rot[t]), 3),
                        "use_depth": condition["use_depth"],
                        "width": condition["width"],
                        "sigma": condition["sigma"],
                        "seconds": round(seconds, 2),
                        **{k: round(float(v), 4) for k, v in terms.items()},
                    }
                )
            new = not path.exists()
            with path.open("a", newline="") as f:
                writer = csv.DictWriter(f, FIELDS)
                if new:
                    writer.writeheader()
                writer.writerows(rows)
            print(f"seed {seed} {kind} {condition['width']}px: {seconds:.0f} s", flush=True)


def auc(positive: np.ndarray, negative: np.ndarray) -> float:
    """The probability that a positive scores above a negative (ties count half)."""
    greater = (positive[:, None] > negative[None, :]).mean()
    equal = (positive[:, None] == negative[None, :]).mean()
    return float(greater + 0.5 * equal)


def report() -> str:
    with (OUT / "frames_dev.csv").open() as f:
        rows = list(csv.DictReader(f))
    data = {k: np.array([r[k] for r in rows], None if k == "kind" else float) for k in FIELDS}
    good = (data["kind"] == "right") & (data["pos"] < 0.25) & (data["rot"] < 5.0)
    wrong = data["kind"] == "wrong"
    seeds = sorted({int(s) for s in data["seed"]})
    lines = [
        f"{len(seeds)} seeds ({seeds[0]}-{seeds[-1]}), {len(rows)} frames; good: within 0.25 m "
        "and 5 deg in the right room; wrong: the look-alike place's frames. AUC: the chance that "
        "a good frame's term is better than a wrong one's.",
        "",
        "| filter | term | AUC | good: 10/50/90 % | wrong: 10/50/90 % |",
        "|---|---|---|---|---|",
    ]
    for use_depth in (1, 0):
        group = data["use_depth"] == use_depth
        label = "with depth" if use_depth else "without depth"
        g, w = good & group, wrong & group
        lines[0] += f" {label}: {g.sum()} good, {w.sum()} wrong."
        if not (g.any() and w.any()):
            continue
        for name, higher in TERMS:
            if not use_depth and name == "depth_deficit":
                continue
            sign = 1.0 if higher else -1.0
            score = auc(sign * data[name][g], sign * data[name][w])
            quantiles = [
                "/".join(f"{q:.2f}" for q in np.percentile(data[name][m], [10, 50, 90]))
                for m in (g, w)
            ]
            lines.append(f"| {label} | {name} | {score:.2f} | {quantiles[0]} | {quantiles[1]} |")
    return "\n".join(lines)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", action="store_true", help="run the seeds into frames_dev.csv")
    parser.add_argument("--seeds", type=parse_seeds, default=None, help="e.g. 5100-5119")
    parser.add_argument("--report", action="store_true", help="the AUC table")
    args = parser.parse_args(argv)
    if args.run:
        run(args.seeds)
    if args.report:
        print(report())


if __name__ == "__main__":
    main()
