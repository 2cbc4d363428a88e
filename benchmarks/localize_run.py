"""Seconds of a whole :func:`jaxloc.sg2loc.localize` call, compilation apart, beside older
checkouts in the same run.

The paper's scale by default: a synthetic room (:mod:`jaxloc.synthetic.indoor`, default room and
sensor, 960x540), ``--frames`` frames, 2500 particles, strides 20, 8, 4, the depth and colour
scores. Each checkout runs in a fresh child process with its tree first on ``PYTHONPATH``
(``git worktree add /tmp/jaxloc-base <commit>``), the checkouts alternating for ``--repeats``
rounds so that a slow spell of the machine hits them alike. A child times:

* ``first``: the first call (tracing, compilation and the run; no persistent cache);
* ``run``: the median of ``--calls`` further calls (the compiled program only), and that per
  frame;
* the child's peak RSS.

``--split``: instead of older checkouts, this checkout's filter beside the same particle budget
split between a check and the filter: ``localize`` with depth on three quarters of the particles,
a depth-blind ``localize`` on the other quarter and ``depth_agreement`` at the depth-blind
estimates (``experiments/sg2loc_verdict_evidence.py --shadow-rounds split``); and the same with
KLD-sampling's floor (``KLDConfig.min_particles``) split 3/4 and 1/4 too (``split_floor``).

``--check``: this checkout's filter beside the filter followed by the check of the SG2Loc guide
("A check the pose was not fitted to"), :func:`jaxloc.sg2loc.depth_blind_check`: a depth-blind
``localize`` of the same particles and ``depth_agreement`` at its estimates, over every stride
(``check``, ``skip_finest=False``) or every stride but the finest (``check_coarse``, its default;
``experiments/sg2loc_verdict_evidence.py --shadow-rounds coarse``).

    python benchmarks/localize_run.py --baseline /tmp/jaxloc-prev --repeats 3
    python benchmarks/localize_run.py --split --repeats 3
    python benchmarks/localize_run.py --check --repeats 2
    python benchmarks/localize_run.py --frames 2 --particles 300 --width 320 --height 180
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def child(args: argparse.Namespace) -> dict:
    import dataclasses
    import resource

    import jax

    from jaxloc.sg2loc import (
        KLDConfig,
        SG2LocConfig,
        depth_agreement,
        depth_blind_check,
        kld_for_capacity,
        localize,
    )
    from jaxloc.synthetic import indoor

    sensor = indoor.SensorConfig(width=args.width, height=args.height)
    episode = indoor.make_episode(args.seed, args.frames, indoor.EpisodeConfig(sensor=sensor))
    scene, sequence = episode.scene, episode.sequence
    key = jax.random.key(args.seed)

    def configured(capacity: int, use_depth: bool = True, floor: int | None = None):
        kld = KLDConfig() if floor is None else KLDConfig(min_particles=floor)
        kld = kld_for_capacity(capacity, kld)
        config = SG2LocConfig(capacity=capacity, kld=kld)
        observation = dataclasses.replace(config.observation, use_depth=use_depth)
        return dataclasses.replace(config, observation=observation)

    if args.variant.startswith("split"):
        quarter, floor = args.particles // 4, int(KLDConfig().min_particles)
        floors = (floor * 3 // 4, floor // 4) if args.variant == "split_floor" else (None, None)
        config = configured(args.particles - quarter, floor=floors[0])
        blind_config = configured(quarter, False, floors[1])

        def run():
            result = localize(key, scene, sequence, config)
            blind = localize(key, scene, sequence, blind_config)
            share = depth_agreement(scene, sequence, blind.poses, config.strides[-1])
            return result.poses, share
    elif args.variant.startswith("check"):
        config = configured(args.particles)
        skip_finest = args.variant == "check_coarse"

        def run():
            result = localize(key, scene, sequence, config)
            check = depth_blind_check(key, scene, sequence, config, skip_finest=skip_finest)
            return result.poses, check.passed
    else:
        config = configured(args.particles)

        def run():
            return localize(key, scene, sequence, config).poses

    def call() -> float:
        start = time.perf_counter()
        jax.block_until_ready(run())
        return time.perf_counter() - start

    first = call()
    runs = [call() for _ in range(args.calls)]
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return {"first": first, "run": statistics.median(runs), "peak_mib": peak}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--baseline", type=Path, action="append", default=[])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--calls", type=int, default=2, help="compiled calls timed per child")
    parser.add_argument("--frames", type=int, default=6)
    parser.add_argument("--particles", type=int, default=2500)
    parser.add_argument("--width", type=int, default=960)
    parser.add_argument("--height", type=int, default=540)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--split", action="store_true", help="the budget split beside the filter")
    parser.add_argument("--check", action="store_true", help="the check beside the filter")
    parser.add_argument("--variant", default="alone", help=argparse.SUPPRESS)
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(child(args)))
        return
    runs = [(ROOT, "alone"), *((b.resolve(), "alone") for b in args.baseline)]
    if args.split:
        runs = [(ROOT, "alone"), (ROOT, "split"), (ROOT, "split_floor")]
    if args.check:
        runs = [(ROOT, "alone"), (ROOT, "check"), (ROOT, "check_coarse")]
    forwarded = [f"--{k}={getattr(args, k)}" for k in ("calls", "frames", "particles", "width")]
    forwarded += [f"--height={args.height}", f"--seed={args.seed}", "--child"]
    rows: dict[tuple[Path, str], list[dict]] = {run: [] for run in runs}
    load_before = " ".join(f"{v:.2f}" for v in os.getloadavg())
    for _ in range(args.repeats):
        for tree, variant in runs:
            env = dict(os.environ, JAXLOC_NO_CACHE="1")
            env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(tree), env.get("PYTHONPATH")]))
            command = [sys.executable, __file__, *forwarded, f"--variant={variant}"]
            done = subprocess.run(command, capture_output=True, text=True, env=env, cwd=tree)
            if done.returncode != 0:
                raise SystemExit(f"{tree}: the child failed:\n{done.stderr[-2000:]}")
            rows[tree, variant].append(json.loads(done.stdout.strip().splitlines()[-1]))
    load_after = " ".join(f"{v:.2f}" for v in os.getloadavg())
    print(
        f"localize: {args.frames} frames, {args.width}x{args.height}, {args.particles} particles, "
        f"strides 20,8,4; {args.repeats} rounds, medians (every round's value in brackets). "
        f"Load average before: {load_before}, after: {load_after}.\n"
    )
    print(
        "| checkout | first call (s) | compiled call (s) | per frame, all rounds (s) "
        "| peak RSS (MiB) |"
    )
    print("|---|---|---|---|---|")
    labels = {"alone": "this one", "split": "3/4 with depth + 1/4 depth-blind + agreement"}
    labels["split_floor"] = labels["split"] + ", KLD floor split too"
    labels["check"] = "+ depth-blind localize + agreement"
    labels["check_coarse"] = labels["check"] + ", strides 20,8"
    for (tree, variant), results in rows.items():
        label = labels[variant] if tree == ROOT else str(tree)
        first, run = ([r[k] for r in results] for k in ("first", "run"))
        shown = " ".join(f"{v:.2f}" for v in first)
        per_frame = statistics.median(run) / args.frames
        peak = max(r["peak_mib"] for r in results)
        print(
            f"| {label} | {statistics.median(first):.2f} [{shown}] | "
            f"{statistics.median(run):.2f} [{' '.join(f'{v:.2f}' for v in run)}] | "
            f"{per_frame:.3f} | {peak:.0f} |"
        )


if __name__ == "__main__":
    main()
