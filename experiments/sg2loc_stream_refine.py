"""A streaming check at a refined estimate: SG2Loc's stream with depth, its estimate refined
against the map's meshes per frame, and a depth-blind stream that confirms the place.

For each seed of ``sg2loc_verdict_evidence.py``'s conditions whose filter scores depth, its two
10-frame sequences (the map's own room, ``right``, and a look-alike wrong place, ``wrong``) are
streamed (:func:`jaxloc.sg2loc.online.filter_sequence`, no relocalization) twice: with depth, as
configured, and without depth (the depth-blind stream). Every frame's estimate of the stream with
depth is refined with depth (:func:`jaxloc.sg2loc.refine.refine_frame`, depth residuals every
``refine_stride(width)``-th pixel, the default :class:`~jaxloc.sg2loc.refine.RefineConfig`
otherwise); the pose a user acts on is the refined one where the refinement is ``ok``, else the
stream's. Logged per frame: both poses' errors, the refinement's status, the distance and yaw
difference between the depth-blind stream's estimate and the acted-on pose (``gap_pos``,
``gap_yaw``), the same for the depth-blind estimate refined with depth as the other is
(``twin_pos``, ``twin_yaw``; ``blind_status`` its refinement's status), and the depth agreement
(:func:`jaxloc.sg2loc.depth_agreement`, 5 cm + 5 %, on the stream's stride) of the depth-blind
stream's estimate (``blind_rel``), the stream's (``own_rel``) and the acted-on pose
(``acted_rel``).

``--report`` judges the check "the place is confirmed (by the depth-blind stream's agreement, or
its estimate, raw or refined, near the acted-on pose; at this frame or at some frame so far of the
sequence), the refinement is ok and the depth agrees at the refined pose (``acted_rel`` >=
tau_pose)" on the acted-on poses: flagged frames, precision (within 0.5 m and
10 degrees), recall of the frames within 0.25 m and 5 degrees, wrong-place frames flagged; per
threshold pair, and per image width at :data:`CHOSEN`.

``--budget ROUNDSxSTEPS`` sets the refinement's ``rounds`` and ``max_steps`` (default 16x20,
``RefineConfig``'s; another budget logs to ``frames_SPLIT_budgetROUNDSxSTEPS.csv``).

    JAX_PLATFORMS=cpu python experiments/sg2loc_stream_refine.py --run --seeds 5100-5123
    python experiments/sg2loc_stream_refine.py --report > \\
        experiments/results/sg2loc_stream_refine/report_dev.txt
    JAX_PLATFORMS=cpu python experiments/sg2loc_stream_refine.py --split kinect --run \\
        --seeds 7100-7123
    python experiments/sg2loc_stream_refine.py --split kinect --report > \\
        experiments/results/sg2loc_stream_refine/report_kinect.txt
"""

from __future__ import annotations

import argparse
import csv
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from sg2loc_verdict import judge, parse_seeds  # noqa: E402
from sg2loc_verdict_conditions import sg2loc_config  # noqa: E402
from sg2loc_verdict_evidence import (  # noqa: E402
    SPLITS,
    append_rows,
    episode_of,
    frame_row,
    judged_cells,
    latched,
    pending_sequences,
    pose_errors,
)

OUT = Path(__file__).resolve().parents[1] / "experiments" / "results" / "sg2loc_stream_refine"
FIELDS = ["seed", "kind", "frame", "width", "pos", "rot", "acted_pos", "acted_rot", "status"]
FIELDS += ["steps", "position_std", "inlier_fraction", "blind_rel", "own_rel", "acted_rel"]
FIELDS += ["gap_pos", "gap_yaw", "blind_status", "twin_pos", "twin_yaw"]
FIELDS += ["stream_seconds", "blind_seconds", "stream_refine_seconds", "blind_refine_seconds"]
#: (confirmation, tau_pose) chosen on the development split: the pair of the report's grid with
#: the most recall whose precision is >= 0.95 and wrong-place share <= 0.05 there.
CHOSEN = ("refined blind within 0.25 m now", 0.8)
#: The refinement's (rounds, max_steps): :class:`~jaxloc.sg2loc.refine.RefineConfig`'s defaults.
DEFAULT_BUDGET = (16, 20)


def refine_stride(width: int) -> int:
    """The refinement's depth pixel stride: about 100 columns of depth pixels, at least every 4th
    pixel (4 at 160 and 320 px wide, 10 at 960)."""
    return max(4, width // 96)


def refine_estimates(
    scene, sequence, poses: np.ndarray, config, warm: bool = False
) -> tuple[np.ndarray, list]:
    """Each frame's (x, y, z, yaw) estimate refined with its depth
    (:func:`jaxloc.sg2loc.refine.refine_frame`): the poses to act on (the refined one where the
    refinement is ok, else the estimate) and the host :class:`RefineResult` of every frame. With
    ``warm`` frame t's refinement starts from frame t-1's refined pose moved by the ego-motion
    where that refinement was ok (else from the estimate)."""
    import jax
    import jax.numpy as jnp

    from jaxloc.geometry import compose_yaw, yaw_pose_to_se3
    from jaxloc.sg2loc.refine import refine_frame

    acted, results = poses.copy(), []
    for t in range(len(poses)):
        start = poses[t]
        if warm and t and results[-1].ok:
            start = compose_yaw(jnp.asarray(acted[t - 1]), jnp.asarray(sequence.ego_motion[t - 1]))
        T_init = yaw_pose_to_se3(jnp.asarray(start), jnp.asarray(sequence.tilt[t]))
        result = refine_frame(scene, sequence.camera, T_init, config, depth=sequence.depth[t])
        results.append(jax.tree.map(np.asarray, result))
        if results[-1].ok:
            acted[t] = results[-1].yaw_pose
    return acted, results


def stream_and_refine(
    seed: int, kind: str, condition: dict, shared, budget: tuple[int, int]
) -> list[dict]:
    """The rows of one sequence (see the module docstring); ``budget``: the refinement's
    ``(rounds, max_steps)``."""
    import jax

    from jaxloc.metrics import yaw_pose_errors
    from jaxloc.sg2loc import depth_agreement, online
    from jaxloc.sg2loc.refine import RefineConfig

    episode = episode_of(seed, kind, condition)
    scene, sequence = shared.scene(episode.room), episode.sequence
    config = sg2loc_config(condition)
    stride = config.strides[0]
    seconds, estimates = {}, {}
    for name, c in (("stream", condition), ("blind", dict(condition, use_depth=0))):
        start = time.perf_counter()
        stream = online.filter_sequence(jax.random.key(seed), scene, sequence, sg2loc_config(c))
        estimates[name] = np.asarray(stream.pose)
        seconds[name] = time.perf_counter() - start
    rounds, steps = budget
    refine_config = RefineConfig(
        depth_stride=refine_stride(condition["width"]), rounds=rounds, max_steps=steps
    )
    refined = {}
    for name in ("stream", "blind"):
        start = time.perf_counter()
        refined[name] = refine_estimates(scene, sequence, estimates[name], refine_config)
        seconds[f"{name}_refine"] = time.perf_counter() - start
    poses, (acted, results) = estimates["stream"], refined["stream"]
    blind_acted, blind_results = refined["blind"]
    rel = {
        name: np.asarray(depth_agreement(scene, sequence, p, stride))
        for name, p in (("blind", estimates["blind"]), ("own", poses), ("acted", acted))
    }
    gap_pos, gap_yaw = yaw_pose_errors(estimates["blind"], acted)
    twin_pos, twin_yaw = yaw_pose_errors(blind_acted, acted)
    (pos, rot), (acted_pos, acted_rot) = (pose_errors(episode, p) for p in (poses, acted))
    return [
        {
            **frame_row(seed, kind, t, condition, pos, rot),
            "acted_pos": round(float(acted_pos[t]), 4),
            "acted_rot": round(float(acted_rot[t]), 3),
            "status": int(results[t].status),
            "steps": int(results[t].steps),
            "position_std": round(float(results[t].position_std), 4),
            "inlier_fraction": round(float(results[t].inlier_fraction), 4),
            **{f"{name}_rel": round(float(v[t]), 4) for name, v in rel.items()},
            "gap_pos": round(float(gap_pos[t]), 4),
            "gap_yaw": round(float(gap_yaw[t]), 3),
            "blind_status": int(blind_results[t].status),
            "twin_pos": round(float(twin_pos[t]), 4),
            "twin_yaw": round(float(twin_yaw[t]), 3),
            **{f"{name}_seconds": round(s, 2) for name, s in seconds.items()},
        }
        for t in range(len(poses))
    ]


def frames_file(split: str, budget: tuple[int, int]) -> Path:
    """The log of ``split`` with the refinement's ``(rounds, max_steps)`` budget."""
    suffix = "" if budget == DEFAULT_BUDGET else f"_budget{budget[0]}x{budget[1]}"
    return OUT / f"frames_{split}{suffix}.csv"


def run(seeds, split: str, budget: tuple[int, int]) -> None:
    path = frames_file(split, budget)
    for seed, kind, condition, shared in pending_sequences(seeds, split, path, depth_only=True):
        rows = stream_and_refine(seed, kind, condition, shared, budget)
        append_rows(path, FIELDS, rows)
        r = rows[0]
        print(
            f"{seed} {kind} {condition['width']}px: stream {r['stream_seconds']:.0f} s, "
            f"blind {r['blind_seconds']:.0f} s, refinements {r['stream_refine_seconds']:.0f} "
            f"and {r['blind_refine_seconds']:.0f} s",
            flush=True,
        )


def load(split: str, budget: tuple[int, int] = DEFAULT_BUDGET) -> dict[str, np.ndarray]:
    with frames_file(split, budget).open() as f:
        rows = list(csv.DictReader(f))
    return {k: np.array([r[k] for r in rows], object if k == "kind" else float) for k in FIELDS}


def confirmations(data: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """What confirms the place, per frame, by name: nothing; the depth-blind stream's agreement
    (>= tau_blind) at some frame so far; its estimate within ``g`` metres and 15 degrees of the
    acted-on pose, at this frame or at some frame so far."""
    near = lambda g: (data["gap_pos"] < g) & (data["gap_yaw"] < 15.0)  # noqa: E731
    episodes = list(zip(data["seed"], data["kind"], strict=True))
    so_far = lambda event: latched(episodes, data["frame"], event)  # noqa: E731
    out = {"none": np.ones(len(data["seed"]), bool)}
    for tau in (0.4, 0.5, 0.6, 0.7):
        out[f"blind agreed >= {tau:.1f} so far"] = so_far(data["blind_rel"] >= tau)
    for g in (0.5, 1.0):
        out[f"blind within {g:.1f} m now"] = near(g)
        out[f"blind within {g:.1f} m so far"] = so_far(near(g))
    for g in (0.1, 0.25):
        twin = (data["blind_status"] == 0) & (data["twin_pos"] < g) & (data["twin_yaw"] < 5.0)
        out[f"refined blind within {g:.2f} m now"] = twin
        out[f"refined blind within {g:.2f} m so far"] = so_far(twin)
    return out


def report(split: str, budget: tuple[int, int]) -> str:
    data = load(split, budget)
    acted = dict(data, pos=data["acted_pos"], rot=data["acted_rot"])
    right, ok = data["kind"] == "right", data["status"] == 0
    every = np.ones(len(right), bool)

    def within(pos, rot, metres, degrees):
        return int((right & (pos < metres) & (rot < degrees)).sum())

    seeds = sorted({int(s) for s in data["seed"]})
    stream_counts = [within(data["pos"], data["rot"], m, d) for m, d in ((0.25, 5), (0.5, 10))]
    acted_counts = [
        within(data["acted_pos"], data["acted_rot"], m, d) for m, d in ((0.25, 5), (0.5, 10))
    ]
    median = {
        k: np.median(data[f"{k}_seconds"])
        for k in ("stream", "blind", "stream_refine", "blind_refine")
    }
    lines = [
        f"Refinement budget: {budget[0]} rounds of {budget[1]} steps. "
        f"{len(seeds)} conditions whose filter scores depth ({', '.join(map(str, seeds))}), "
        f"{len(right)} frames, {(~right).sum()} in look-alike wrong places. Right-room frames "
        f"within 0.25 m / 5 deg (0.5 m / 10 deg): stream {stream_counts[0]} ({stream_counts[1]}), "
        f"acted-on pose {acted_counts[0]} ({acted_counts[1]}); refinement ok on "
        f"{(ok & right).sum()} right-room and {(ok & ~right).sum()} wrong-place frames, "
        f"{np.median(data['steps']):.0f} optimiser steps (median).",
        "",
        "Seconds per sequence (10 frames, compilation included), median: stream "
        f"{median['stream']:.1f}, depth-blind stream {median['blind']:.1f}, refinement of "
        f"either {median['stream_refine']:.1f} and {median['blind_refine']:.1f}.",
        "",
        "Flagged: the place is confirmed, the refinement is ok and the depth agrees at the refined "
        "pose (>= tau_pose):",
        "",
        "| confirmed by | tau_pose | flagged | precision (within 0.5 m / 10 deg) | recall of good "
        "| wrong-place frames flagged |",
        "|---|---|---|---|---|---|",
    ]
    confirmed = confirmations(data)
    for name, place in confirmed.items():
        for tau_pose in (0.8, 0.9, 0.95):
            judged = judge(acted, place & ok & (data["acted_rel"] >= tau_pose), every)
            lines.append(f"| {name} | {tau_pose:.2f} | {judged_cells(judged)}")
    name, tau_pose = CHOSEN
    flagged = confirmed[name] & ok & (data["acted_rel"] >= tau_pose)
    lines += [
        "",
        f"Per image width, confirmed by {name}, tau_pose {tau_pose} (chosen on the development "
        "split):",
        "",
        "| width | conditions | good | flagged | precision | recall of good | wrong flagged |",
        "|---|---|---|---|---|---|---|",
    ]
    for width in sorted(set(data["width"])):
        at = data["width"] == width
        j, conditions = judge(acted, flagged, at), len(set(data["seed"][at]))
        lines.append(f"| {width:.0f} | {conditions} | {j['good']} | {judged_cells(j)}")
    return "\n".join(lines)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", action="store_true", help="run the seeds into frames_SPLIT.csv")
    parser.add_argument("--split", choices=sorted(SPLITS), default="dev")
    parser.add_argument("--seeds", type=parse_seeds, default=None, help="e.g. 5100-5123")
    parser.add_argument("--report", action="store_true", help="the check's tables")
    parser.add_argument(
        "--budget", default="16x20", help="the refinement's ROUNDSxSTEPS (default 16x20)"
    )
    args = parser.parse_args(argv)
    budget = tuple(int(n) for n in args.budget.split("x"))
    if args.run:
        run(args.seeds, args.split, budget)
    if args.report:
        print(report(args.split, budget))


if __name__ == "__main__":
    main()
