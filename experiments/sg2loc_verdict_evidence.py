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
10/50/90 % quantiles of both; then, for the filters without depth, the check "the depth agrees at
the filter's own estimate on >= tau of its rays" per tau.

``--shadow`` localizes the sequences of the conditions whose filter scores depth again, without
depth (a depth-blind *shadow* filter: ``--shadow-rounds all``, the condition's rounds; ``first``,
only its first round's stride; ``coarse``, every round but the finest (its agreement on that
round's grid); ``quarter``, every round with a quarter of the particles; ``stream``, the filter
with depth and the depth-blind one both as streams, :func:`jaxloc.sg2loc.online.filter_sequence`),
and logs the depth agreement of the shadow's estimates. ``split`` runs the filter with depth again
on three quarters of the particles: with the ``quarter`` shadow, a check within the particle
budget of the filter alone. ``--shadow-report``
judges the check "the shadow's estimate agrees with the recording's depth on >= tau of its rays"
on the estimates of the filter that scores depth: flagged frames, precision (within 0.5 m and 10
degrees), recall of the good frames and wrong-place frames flagged, per tau.

``--split kinect`` runs the held-out generator variant of ``sg2loc_verdict_conditions.py`` (the
``"kinect"`` depth model, sizes 320x180 to 960x540) instead of the development conditions.

    JAX_PLATFORMS=cpu python experiments/sg2loc_verdict_evidence.py --run --seeds 5100-5123
    python experiments/sg2loc_verdict_evidence.py --report > \
        experiments/results/sg2loc_verdict_evidence/report_dev.txt
    JAX_PLATFORMS=cpu python experiments/sg2loc_verdict_evidence.py --shadow --seeds 5100-5123
    python experiments/sg2loc_verdict_evidence.py --shadow-report
    JAX_PLATFORMS=cpu python experiments/sg2loc_verdict_evidence.py --split kinect --run \
        --shadow --seeds 7100-7123
    python experiments/sg2loc_verdict_evidence.py --split kinect --report --shadow-report
    JAX_PLATFORMS=cpu python experiments/sg2loc_verdict_evidence.py --shadow --shadow-rounds \
        stream --seeds 5100-5123
    python experiments/sg2loc_verdict_evidence.py --shadow-report --shadow-rounds stream
    JAX_PLATFORMS=cpu python experiments/sg2loc_verdict_evidence.py --shadow --shadow-rounds \
        split --seeds 5100-5123
    python experiments/sg2loc_verdict_evidence.py --shadow-report --shadow-rounds split
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
from sg2loc_verdict import PLACE_OFFSET, judge, parse_seeds  # noqa: E402
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
#: Each split's generator variant and image sizes (None: drawn as the development conditions are);
#: ``kinect`` is the verdict experiment's held-out variant.
SPLITS = {
    "dev": ("relative", None),
    "kinect": ("kinect", [(320, 180), (480, 270), (640, 360), (960, 540)]),
}
#: The shadow check's threshold: the lowest of the report's grid, every tau from it to 0.7 keeping
#: >= 99 % of the flagged frames right on the development split.
CHOSEN_TAU = 0.5
#: The depth terms, logged for the depth-blind shadow filter's estimates too.
DEPTH_TERMS = ["inlier_10", "inlier_20", "inlier_rel", "median_error", "see_through", "occluded"]
SHADOW_FIELDS = ["seed", "kind", "frame", "pos", "rot", "seconds", *DEPTH_TERMS]


def depth_agreement(rendered: np.ndarray, sensor: np.ndarray) -> dict[str, float]:
    """The depth terms of one frame: ``rendered`` (R,) depth at the estimate (metres, +inf on a
    miss), ``sensor`` (R,) the sensor's at the same rays (0: no depth). All 0 with no valid
    sensor depth."""
    valid = np.isfinite(sensor) & (sensor > 0.0)
    if not valid.any():
        return dict.fromkeys(DEPTH_TERMS, 0.0)
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


def episode_of(seed: int, kind: str, condition: dict):
    """The 10-frame ``right`` episode of ``seed`` under ``condition``, or its look-alike wrong
    place (``wrong``)."""
    from jaxloc.synthetic.indoor import make_episode, make_lookalike_episode

    generator = episode_config(condition)
    if kind == "right":
        return make_episode(seed, 10, generator)
    return make_lookalike_episode(seed, seed + PLACE_OFFSET, 10, generator)


def pose_errors(episode, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(T,) position (m) and rotation (deg) errors of ``poses`` (T, 4) in ``episode``; NaN in a
    wrong place (no ground truth there)."""
    from jaxloc.metrics import yaw_pose_errors

    if not episode.in_map:
        return np.full(len(poses), np.nan), np.full(len(poses), np.nan)
    return yaw_pose_errors(np.asarray(poses), episode.poses_gt)


def frame_row(seed: int, kind: str, t: int, condition: dict, pos, rot) -> dict:
    """The leading columns of frame ``t``'s row: which sequence and frame, its errors."""
    return {
        "seed": seed,
        "kind": kind,
        "frame": t,
        "width": condition["width"],
        "pos": round(float(pos[t]), 4),
        "rot": round(float(rot[t]), 3),
    }


def localize_and_check(seed: int, kind: str, condition: dict, shared) -> dict:
    """Localize the ``kind`` sequence of ``condition`` offline and render each frame's estimate on
    the final round's grid: ``{"pos", "rot"}`` (T,) errors (NaN in a wrong place), ``"verdict"``
    (the final round's), ``"depth"``: each frame's :func:`depth_agreement`, ``"seconds"``."""
    import jax
    import jax.numpy as jnp

    from jaxloc import stride_grid
    from jaxloc.sg2loc import localize
    from jaxloc.sg2loc._rendering import render
    from jaxloc.sg2loc._sequence import frames_on_grid

    config, episode = sg2loc_config(condition), episode_of(seed, kind, condition)
    scene, sequence = shared.scene(episode.room), episode.sequence
    start = time.perf_counter()
    result = localize(jax.random.key(seed), scene, sequence, config)
    poses = np.asarray(result.poses)
    seconds = time.perf_counter() - start
    grid = stride_grid(sequence.camera, config.strides[-1], *sequence.patch_shape)
    frames = frames_on_grid(sequence, grid)
    draw = functools.partial(render, scene, camera=sequence.camera, grid=grid, differentiable=False)
    views = jax.jit(jax.vmap(lambda p, t: draw(pose=p, tilt=t)))(jnp.asarray(poses), frames.tilt)
    pos, rot = pose_errors(episode, poses)
    rendered, sensor = np.asarray(views.depth), np.asarray(frames.depth)
    return {
        "pos": pos,
        "rot": rot,
        "verdict": jax.tree.map(np.asarray, result.info.verdict),
        "depth": [depth_agreement(rendered[t], sensor[t]) for t in range(len(poses))],
        "seconds": seconds,
    }


def append_rows(path: Path, fields: list[str], rows: list[dict]) -> None:
    new = not path.exists()
    with path.open("a", newline="") as f:
        writer = csv.DictWriter(f, fields)
        if new:
            writer.writeheader()
        writer.writerows(rows)


def done_runs(path: Path) -> set[tuple[int, str]]:
    if not path.exists():
        return set()
    with path.open() as f:
        return {(int(r["seed"]), r["kind"]) for r in csv.DictReader(f)}


def pending_sequences(seeds, split: str, path: Path, depth_only: bool = False):
    """Yield ``(seed, kind, condition, shared)`` for every sequence of ``seeds`` (the ``right`` and
    ``wrong`` one of each condition; with ``depth_only`` only the conditions whose filter scores
    depth) that ``path`` does not hold yet. ``shared`` is the maps' :class:`SharedCapacity`; the
    compiled programs are dropped between conditions (each compiles programs of its own
    shapes)."""
    import jax
    from sg2loc_tables import SharedCapacity

    from jaxloc import enable_compilation_cache

    enable_compilation_cache()
    path.parent.mkdir(parents=True, exist_ok=True)
    done, shared = done_runs(path), SharedCapacity()
    for seed in seeds:
        condition = draw_condition(seed, *SPLITS[split])
        if depth_only and not condition["use_depth"]:
            continue
        jax.clear_caches()
        for kind in ("right", "wrong"):
            if (seed, kind) not in done:
                yield seed, kind, condition, shared


def run(seeds, split: str) -> None:
    path = OUT / f"frames_{split}.csv"
    for seed, kind, condition, shared in pending_sequences(seeds, split, path):
        out = localize_and_check(seed, kind, condition, shared)
        verdict, rows = out["verdict"], []
        for t, agreement in enumerate(out["depth"]):
            terms = {
                "semantic_fraction": verdict.semantic_fraction[t],
                "mass": verdict.mass[t],
                "depth_deficit": verdict.depth_deficit[t],
                "ess": verdict.ess_fraction[t],
                "spread_z": verdict.spread[t, 2],
                **agreement,
            }
            rows.append(
                {
                    "seed": seed,
                    "kind": kind,
                    "frame": t,
                    "pos": round(float(out["pos"][t]), 4),
                    "rot": round(float(out["rot"][t]), 3),
                    "use_depth": condition["use_depth"],
                    "width": condition["width"],
                    "sigma": condition["sigma"],
                    "seconds": round(out["seconds"], 2),
                    **{k: round(float(v), 4) for k, v in terms.items()},
                }
            )
        append_rows(path, FIELDS, rows)
        print(f"seed {seed} {kind} {condition['width']}px: {out['seconds']:.0f} s", flush=True)


#: The shadow filter's variants: the condition's every round, only its first round's stride,
#: every round but the finest (``coarse``), every round with a quarter of the particles, or
#: streaming (both filters as streams); ``split`` runs the filter with depth on the other three
#: quarters of the particles (with the ``quarter`` shadow, the particle budget of the filter
#: alone); ``split_floor`` and ``quarter_floor`` the same with KLD-sampling's floor (500 particles)
#: split too, 3/4 and 1/4.
SHADOWS = ("all", "first", "coarse", "quarter", "stream", "split", "split_floor", "quarter_floor")
STREAM_FIELDS = ["seed", "kind", "frame", "width", "pos", "rot", "seconds", "inlier_rel"]
STREAM_FIELDS += ["inlier_20"]
STREAM_FIELDS += ["depth_inlier_rel", "depth_inlier_20"]


def stream_and_check(seed: int, kind: str, condition: dict, shared) -> list[dict]:
    """Stream the ``kind`` sequence of ``condition`` (:func:`jaxloc.sg2loc.online.filter_sequence`,
    no relocalization) with depth and depth-blind: per frame the errors of the stream with depth,
    and the depth agreement (:func:`jaxloc.sg2loc.depth_agreement`, on the stream's stride) of both
    streams' estimates (``depth_`` the stream with depth)."""
    import jax

    from jaxloc.sg2loc import AgreementConfig, depth_agreement, online

    episode = episode_of(seed, kind, condition)
    scene, sequence = shared.scene(episode.room), episode.sequence
    start, shares = time.perf_counter(), {}
    for name, c in (("depth_", condition), ("", dict(condition, use_depth=0))):
        config = sg2loc_config(c)
        stream = online.filter_sequence(jax.random.key(seed), scene, sequence, config)
        for suffix, tolerance in (("inlier_rel", None), ("inlier_20", AgreementConfig(0.2, 0.0))):
            share = depth_agreement(scene, sequence, stream.pose, config.strides[0], tolerance)
            shares[name + suffix] = np.asarray(share)
        if name == "depth_":  # the estimate a user acts on
            poses = np.asarray(stream.pose)
    pos, rot = pose_errors(episode, poses)
    seconds = round(time.perf_counter() - start, 2)
    return [
        {
            **frame_row(seed, kind, t, condition, pos, rot),
            "seconds": seconds,
            **{k: round(float(v[t]), 4) for k, v in shares.items()},
        }
        for t in range(len(poses))
    ]


def shadow_file(rounds: str, split: str) -> Path:
    return OUT / (f"shadow_{split}.csv" if rounds == "all" else f"shadow_{rounds}_{split}.csv")


def run_shadow(seeds, rounds: str, split: str) -> None:
    """For the conditions whose filter scores depth: the same sequences localized without depth
    (a depth-blind shadow filter, one of :data:`SHADOWS`), its estimates' depth agreement on its
    final grid in :func:`shadow_file`."""
    path = shadow_file(rounds, split)
    for seed, kind, condition, shared in pending_sequences(seeds, split, path, depth_only=True):
        blind = dict(condition, use_depth=0)
        if rounds == "first":
            blind["strides"] = str(condition["strides"]).split("/")[0]
        elif rounds == "coarse":
            blind["strides"] = "/".join(str(condition["strides"]).split("/")[:-1])
        elif rounds.startswith("quarter"):
            blind["capacity"] = condition["capacity"] // 4
        elif rounds.startswith("split"):  # not blind: the filter with depth on the rest
            blind = dict(condition, capacity=condition["capacity"] - condition["capacity"] // 4)
        if rounds.endswith("_floor"):
            from jaxloc.sg2loc import KLDConfig

            floor = int(KLDConfig().min_particles)
            blind["min_particles"] = floor // 4 if rounds.startswith("quarter") else floor * 3 // 4
        if rounds == "stream":
            append_rows(path, STREAM_FIELDS, stream_and_check(seed, kind, condition, shared))
            print(f"stream {seed} {kind} {condition['width']}px", flush=True)
            continue
        out = localize_and_check(seed, kind, blind, shared)
        rows = [
            {
                "seed": seed,
                "kind": kind,
                "frame": t,
                "pos": round(float(out["pos"][t]), 4),
                "rot": round(float(out["rot"][t]), 3),
                "seconds": round(out["seconds"], 2),
                **{k: round(float(v), 4) for k, v in agreement.items()},
            }
            for t, agreement in enumerate(out["depth"])
        ]
        append_rows(path, SHADOW_FIELDS, rows)
        print(f"shadow {seed} {kind} {condition['width']}px: {out['seconds']:.0f} s", flush=True)


def auc(positive: np.ndarray, negative: np.ndarray) -> float:
    """The probability that a positive scores above a negative (ties count half)."""
    greater = (positive[:, None] > negative[None, :]).mean()
    equal = (positive[:, None] == negative[None, :]).mean()
    return float(greater + 0.5 * equal)


def report(split: str) -> str:
    with (OUT / f"frames_{split}.csv").open() as f:
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
    return "\n".join(lines + own_estimate_table(data))


def judged_cells(j: dict) -> str:
    """The table cells of one :func:`judge` result: flagged, precision, recall of the good frames,
    wrong-place frames flagged."""
    return f"{j['flagged']} | {j['precision']:.3f} | {j['recall']:.3f} | {j['false_accept']:.3f} |"


def own_estimate_table(data: dict[str, np.ndarray]) -> list[str]:
    """The check for a filter that does not score depth: flag a frame when the recording's depth
    agrees at the filter's own estimate (``inlier_rel`` >= tau), per tau."""
    blind = data["use_depth"] == 0
    lines = [
        "",
        "Filters without depth, flagged when inlier_rel at their own estimate >= tau:",
        "",
        "| tau | flagged | precision (within 0.5 m / 10 deg) | recall of good | wrong-place frames "
        "flagged |",
        "|---|---|---|---|---|",
    ]
    for tau in (0.5, 0.6, 0.7, 0.8):
        lines.append(f"| {tau:.1f} | {judged_cells(judge(data, data['inlier_rel'] >= tau, blind))}")
    return lines


def shadow_report(rounds: str, split: str) -> str:
    """The depth-blind shadow filter's check: a frame is flagged when the shadow's estimate agrees
    with the recording's depth on >= tau of its rays (``inlier_rel``); judged on the estimates of
    the filter that scores depth (``frames_dev.csv``), per tau. ``split``: the estimates of the
    filter with depth on three quarters of the particles, checked by the ``quarter`` shadow."""
    tables = []
    pairs = {"split": ("split", "quarter"), "split_floor": ("split_floor", "quarter_floor")}
    shadows = pairs.get(rounds, (rounds,))
    for path in (OUT / f"frames_{split}.csv", *(shadow_file(r, split) for r in shadows)):
        with path.open() as f:
            tables.append({(r["seed"], r["kind"], r["frame"]): r for r in csv.DictReader(f)})
    full, shadow = tables[0], tables[-1]
    if rounds in pairs:  # the three-quarter filter's errors and agreement, the condition's width
        full = {k: dict(full[k], **r) for k, r in tables[1].items()}
    if rounds == "stream":  # the streams' own file holds the stream with depth's terms
        full = {
            k: dict(r, inlier_rel=r["depth_inlier_rel"], inlier_20=r["depth_inlier_20"])
            for k, r in shadow.items()
        }
    keys = sorted(k for k in shadow if k in full)
    value = lambda table, name: np.array([float(table[k][name]) for k in keys])  # noqa: E731
    right = np.array([k[1] == "right" for k in keys])
    pos, rot = value(full, "pos"), value(full, "rot")
    good, near, wrong = (
        right & (pos < 0.25) & (rot < 5.0),
        right & (pos < 0.5) & (rot < 10.0),
        ~right,
    )
    blind_good = right & (value(shadow, "pos") < 0.25) & (value(shadow, "rot") < 5.0)
    blind = (
        " (the depth-blind stream's errors are not logged)"
        if rounds == "stream"
        else f" The shadow filter (the same, without depth) puts {blind_good.sum()} right-room "
        "frames within 0.25 m and 5 deg."
    )
    seeds = sorted({int(k[0]) for k in keys})
    lines = [
        f"{len(seeds)} conditions whose filter scores depth ({', '.join(map(str, seeds))}), "
        f"{len(keys)} frames: {good.sum()} good (the depth filter's estimate within 0.25 m and "
        f"5 deg), {near.sum()} within 0.5 m and 10 deg, {wrong.sum()} wrong-place frames.{blind}",
        "",
        "| check | AUC good vs wrong |",
        "|---|---|",
    ]
    for label, table in (("at the depth filter's estimate", full), ("at the shadow's", shadow)):
        for term in ("inlier_rel", "inlier_20"):
            score = auc(value(table, term)[good], value(table, term)[wrong])
            lines.append(f"| {term} {label} | {score:.2f} |")
    lines += [
        "",
        "| flag: shadow inlier_rel >= | flagged | precision (within 0.5 m / 10 deg) | recall of "
        "good | wrong-place frames flagged |",
        "|---|---|---|---|---|",
    ]
    agreement, every = value(shadow, "inlier_rel"), np.ones(len(keys), bool)
    data = {"kind": np.array([k[1] for k in keys]), "pos": pos, "rot": rot}
    for tau in (0.5, 0.6, 0.7, 0.8, 0.85, 0.9, 0.95):
        lines.append(f"| {tau:.2f} | {judged_cells(judge(data, agreement >= tau, every))}")
    if rounds == "stream":
        lines += latched_table(keys, shadow, data)
    lines += [
        "",
        f"Per image width at tau = {CHOSEN_TAU} (chosen on the development split):",
        "",
        "| width | conditions | good | flagged | precision | recall of good | wrong flagged |",
        "|---|---|---|---|---|---|---|",
    ]
    width = value(full, "width")
    for w in sorted(set(width)):
        at = width == w
        j, n = judge(data, agreement >= CHOSEN_TAU, at), len({k[0] for k in np.array(keys)[at]})
        lines.append(f"| {w:.0f} | {n} | {j['good']} | {judged_cells(j)}")
    return "\n".join(lines)


def latched(episodes: list, frames, event: np.ndarray) -> np.ndarray:
    """Per row: ``event`` is True at this or an earlier frame of the row's sequence (``episodes``
    names each row's sequence, ``frames`` its frame index; rows in any order)."""
    out, seen = np.zeros(len(event), bool), {}
    for i in sorted(range(len(event)), key=lambda i: frames[i]):
        seen[episodes[i]] = seen.get(episodes[i], False) or bool(event[i])
        out[i] = seen[episodes[i]]
    return out


def latched_table(keys: list, shadow: dict, data: dict) -> list[str]:
    """The streams' latched check: frame t is flagged when the depth-blind stream agreed with the
    depth (>= tau_blind) at some frame up to t of its sequence (the place is confirmed) and the
    stream with depth agrees at its own estimate at t (>= tau_own: the pose is precise)."""
    blind = np.array([float(shadow[k]["inlier_rel"]) for k in keys])
    own = np.array([float(shadow[k]["depth_inlier_rel"]) for k in keys])
    episodes, frames = [k[:2] for k in keys], [int(k[2]) for k in keys]
    confirmed = lambda tau: latched(episodes, frames, blind >= tau)  # noqa: E731

    lines = [
        "",
        "Latched: the depth-blind stream agreed (>= tau_blind) at some frame so far, and the "
        "stream with depth agrees at its own estimate (>= tau_own):",
        "",
        "| tau_blind | tau_own | flagged | precision | recall of good | wrong-place frames "
        "flagged |",
        "|---|---|---|---|---|---|",
    ]
    every = np.ones(len(keys), bool)
    for tau_blind in (0.5, 0.6, 0.7, 0.8):
        place = confirmed(tau_blind)
        for tau_own in (0.7, 0.8, 0.9):
            j = judge(data, place & (own >= tau_own), every)
            lines.append(f"| {tau_blind:.1f} | {tau_own:.1f} | {judged_cells(j)}")
    return lines


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", action="store_true", help="run the seeds into frames_SPLIT.csv")
    parser.add_argument("--split", choices=sorted(SPLITS), default="dev")
    parser.add_argument("--seeds", type=parse_seeds, default=None, help="e.g. 5100-5119")
    parser.add_argument("--report", action="store_true", help="the AUC table")
    parser.add_argument("--shadow", action="store_true", help="run the shadow filter's seeds")
    parser.add_argument("--shadow-report", action="store_true", help="the shadow check's table")
    parser.add_argument(
        "--shadow-rounds", choices=SHADOWS, default="all", help="the shadow's variant"
    )
    args = parser.parse_args(argv)
    if args.run:
        run(args.seeds, args.split)
    if args.shadow:
        run_shadow(args.seeds, args.shadow_rounds, args.split)
    if args.report:
        print(report(args.split))
    if args.shadow_report:
        print(shadow_report(args.shadow_rounds, args.split))


if __name__ == "__main__":
    main()
