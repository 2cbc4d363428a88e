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

    python benchmarks/localize_run.py --baseline /tmp/jaxloc-prev --repeats 3
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
    import resource

    import jax

    from jaxloc.sg2loc import SG2LocConfig, kld_for_capacity, localize
    from jaxloc.synthetic import indoor

    sensor = indoor.SensorConfig(width=args.width, height=args.height)
    episode = indoor.make_episode(args.seed, args.frames, indoor.EpisodeConfig(sensor=sensor))
    config = SG2LocConfig(capacity=args.particles, kld=kld_for_capacity(args.particles))
    key = jax.random.key(args.seed)

    def call() -> float:
        start = time.perf_counter()
        jax.block_until_ready(localize(key, episode.scene, episode.sequence, config).poses)
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
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(child(args)))
        return
    trees = [ROOT, *(b.resolve() for b in args.baseline)]
    forwarded = [f"--{k}={getattr(args, k)}" for k in ("calls", "frames", "particles", "width")]
    forwarded += [f"--height={args.height}", f"--seed={args.seed}", "--child"]
    rows: dict[Path, list[dict]] = {tree: [] for tree in trees}
    load_before = " ".join(f"{v:.2f}" for v in os.getloadavg())
    for _ in range(args.repeats):
        for tree in trees:
            env = dict(os.environ, JAXLOC_NO_CACHE="1")
            env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(tree), env.get("PYTHONPATH")]))
            command = [sys.executable, __file__, *forwarded]
            done = subprocess.run(command, capture_output=True, text=True, env=env, cwd=tree)
            if done.returncode != 0:
                raise SystemExit(f"{tree}: the child failed:\n{done.stderr[-2000:]}")
            rows[tree].append(json.loads(done.stdout.strip().splitlines()[-1]))
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
    for tree, results in rows.items():
        label = "this one" if tree == ROOT else str(tree)
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
