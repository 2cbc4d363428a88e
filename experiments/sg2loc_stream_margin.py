"""A streaming check by the depth-blind likelihood: is the pose a user acts on as plausible to the
depth-blind observation model as the best pose the depth-blind stream has found?

The conditions and sequences of ``sg2loc_stream_refine.py`` (the development or held-out
conditions whose filter scores depth, their right-room and look-alike wrong-place sequences of 10
frames) are streamed with and without depth (``online.init`` and ``online.update`` per frame, no
relocalization). Each frame's estimate of the stream with depth is refined with its depth
(``refine_frame``, 4 rounds of 10 steps, depth pixels every ``refine_stride(width)``-th pixel);
the pose acted on is the refined one where the refinement is ``ok``. Then, at every frame, the
depth-blind observation model (the depth-blind stream's: patches, and colour where scored) scores
the acted-on pose, the stream's own estimate, the depth-blind stream's estimate and every particle
the depth-blind stream keeps after the frame. Logged per frame, as shares of the model's best
attainable score ``S_max``: ``acted_s``, ``own_s``, ``blind_s``, the particles' best ``best_s``
and 95th percentile ``p95_s``; with the depth agreement (5 cm + 5 %, on the stream's stride) at
the acted-on pose (``acted_rel``) and at the stream's estimate (``own_rel``).

The idea: in a look-alike wrong place the depth fixes a pose whose patches fit worse than where
the patches alone lead (the depth-blind stream's best particle), while in the right room the
refined pose is near the true one, whose patches fit best. The check needs the depth-blind stream
to have found that better place, not to have converged on it.

``--report`` judges "refinement ok, ``acted_rel`` >= tau_pose and the margin ``acted_s -
best_s`` >= -delta" (this frame's margin, some frame's so far, or the mean over the frames so far;
and the variant on the stream's own, unrefined estimate) per (delta, tau_pose), and per image
width at the choice made on the development split (:func:`choose`). ``--inject SHARE``: the
depth-blind stream replaces ``SHARE`` of its capacity by random particles after every frame it is
not localized (logged to ``frames_SPLIT_injectSHARE.csv``); ``--warm``: each refinement starts
from the previous refined pose (``frames_SPLIT_warm.csv``). ``--seeds`` with
``--report``: only those seeds' rows.

    JAX_PLATFORMS=cpu python experiments/sg2loc_stream_margin.py --run --seeds 5100-5123
    python experiments/sg2loc_stream_margin.py --report > \\
        experiments/results/sg2loc_stream_margin/report_dev.txt
    JAX_PLATFORMS=cpu python experiments/sg2loc_stream_margin.py --split kinect --run \\
        --seeds 7100-7147
    python experiments/sg2loc_stream_margin.py --split kinect --report > \\
        experiments/results/sg2loc_stream_margin/report_kinect.txt
"""

from __future__ import annotations

import argparse
import csv
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from sg2loc_stream_refine import refine_estimates, refine_stride  # noqa: E402
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

OUT = Path(__file__).resolve().parents[1] / "experiments" / "results" / "sg2loc_stream_margin"
FIELDS = ["seed", "kind", "frame", "width", "pos", "rot", "acted_pos", "acted_rot", "status"]
FIELDS += ["acted_rel", "own_rel", "acted_s", "own_s", "blind_s", "best_s", "p95_s"]
FIELDS += ["stream_seconds", "blind_seconds", "score_seconds", "refine_seconds", "steps"]
#: The refinement's (rounds, max_steps): as cheap as checked well in sg2loc_stream_refine.py.
BUDGET = (4, 10)
DELTAS = (0.0, 0.01, 0.02, 0.05, 0.1, 0.2)
TAUS = (0.8, 0.9, 0.95)


def make_scorer():
    """A jitted ``score(state, poses, patches, depth, rgb, tilt) -> (M,) S / S_max`` of poses (M, 4)
    under the observation model of an online stream's ``state``, against one frame given as
    :func:`jaxloc.sg2loc.online.update` takes it (rows-by-cols patches flattened)."""
    import equinox as eqx
    import jax.numpy as jnp

    from jaxloc.sg2loc._filter import _score_poses
    from jaxloc.sg2loc._scores import match_patches
    from jaxloc.sg2loc._sequence import Frame

    @eqx.filter_jit
    def score(state, poses, patches, depth, rgb, tilt):
        config = state.config
        observation = config.observation
        rows, cols = state.pixels
        h, w = config.grid.shape
        frame = Frame(
            index=state.index,
            motion=jnp.zeros(4, jnp.float32),
            patch_embeddings=patches,
            depth=depth[rows, cols],
            rgb=rgb[rows, cols].reshape(h, w, 3),
            tilt=tilt,
        )
        scene = state.scene
        match = match_patches(patches, scene.embeddings, scene.object_valid)
        scores = _score_poses(poses, frame, scene, config, match)
        total = scores.semantic
        if observation.use_color:
            total = total + observation.lambda_color * scores.color
        return total / observation.max_total()

    return score


def stream_and_score(
    seed: int, kind: str, condition: dict, shared, score, inject: float, warm: bool
) -> list[dict]:
    """The rows of one sequence (see the module docstring); ``inject``: the share of the capacity
    the depth-blind stream replaces by random particles after each frame it is not localized;
    ``warm``: the refinements start from the previous refined pose (``refine_estimates``)."""
    import dataclasses

    import jax
    import jax.numpy as jnp

    from jaxloc.sg2loc import depth_agreement, online
    from jaxloc.sg2loc.refine import RefineConfig

    episode = episode_of(seed, kind, condition)
    scene, sequence = shared.scene(episode.room), episode.sequence
    config = sg2loc_config(condition)
    stride = config.strides[0]
    T = sequence.num_frames
    seconds, poses, blind_states = {}, {}, []
    for name, c in (("stream", condition), ("blind", dict(condition, use_depth=0))):
        stream_config = sg2loc_config(c)
        if name == "blind" and inject > 0:
            count = round(inject * stream_config.capacity)
            stream_config = dataclasses.replace(
                stream_config, relocalize_after=1, relocalize_count=count
            )
        if sequence.rgb is None:
            observation = dataclasses.replace(stream_config.observation, use_color=False)
            stream_config = dataclasses.replace(stream_config, observation=observation)
        start = time.perf_counter()
        state = online.init(
            jax.random.key(seed),
            scene,
            sequence.camera,
            stream_config,
            patch_shape=tuple(sequence.patch_shape),
        )
        estimates = []
        for t in range(T):
            motion = np.zeros(4, np.float32) if t == 0 else sequence.ego_motion[t - 1]
            state, estimate = online.update(
                state,
                sequence.patch_embeddings[t],
                motion,
                depth=sequence.depth[t],
                rgb=None if sequence.rgb is None else sequence.rgb[t],
                tilt=sequence.tilt[t],
            )
            estimates.append(np.asarray(estimate.pose))
            if name == "blind":
                blind_states.append(state)
        poses[name] = np.stack(estimates)
        seconds[name] = time.perf_counter() - start
    rounds, steps = BUDGET
    refine_config = RefineConfig(
        depth_stride=refine_stride(condition["width"]), rounds=rounds, max_steps=steps
    )
    start = time.perf_counter()
    acted, results = refine_estimates(scene, sequence, poses["stream"], refine_config, warm)
    seconds["refine"] = time.perf_counter() - start
    start = time.perf_counter()
    shares = []
    height, width = sequence.camera.height, sequence.camera.width
    for t, state in enumerate(blind_states):
        particles = state.particles
        candidates = jnp.concatenate(
            [jnp.asarray(np.stack([acted[t], poses["stream"][t], poses["blind"][t]])),
             particles.poses]
        )  # fmt: skip
        rgb = np.zeros((height, width, 3), np.float32) if sequence.rgb is None else sequence.rgb[t]
        s = np.asarray(
            score(
                state,
                candidates,
                jnp.asarray(sequence.patch_embeddings[t].reshape(-1, scene.embeddings.shape[1])),
                jnp.asarray(sequence.depth[t]),
                jnp.asarray(rgb),
                jnp.asarray(sequence.tilt[t]),
            )
        )
        kept = s[3:][np.asarray(particles.active)]
        shares.append((*s[:3], kept.max(), np.percentile(kept, 95)))
    seconds["score"] = time.perf_counter() - start
    rel = {
        name: np.asarray(depth_agreement(scene, sequence, p, stride))
        for name, p in (("acted", acted), ("own", poses["stream"]))
    }
    (pos, rot), (acted_pos, acted_rot) = (pose_errors(episode, p) for p in (poses["stream"], acted))
    names = ("acted_s", "own_s", "blind_s", "best_s", "p95_s")
    return [
        {
            **frame_row(seed, kind, t, condition, pos, rot),
            "acted_pos": round(float(acted_pos[t]), 4),
            "acted_rot": round(float(acted_rot[t]), 3),
            "status": int(results[t].status),
            "steps": int(results[t].steps),
            **{f"{name}_rel": round(float(v[t]), 4) for name, v in rel.items()},
            **{name: round(float(v), 4) for name, v in zip(names, shares[t], strict=True)},
            **{f"{name}_seconds": round(s, 2) for name, s in seconds.items()},
        }
        for t in range(T)
    ]


def frames_file(split: str, inject: float, warm: bool) -> Path:
    """The log of ``split`` with the depth-blind stream's injection share ``inject`` and warm
    started refinements or not."""
    suffix = (f"_inject{inject:g}" if inject else "") + ("_warm" if warm else "")
    return OUT / f"frames_{split}{suffix}.csv"


def run(seeds, split: str, inject: float, warm: bool) -> None:
    path = frames_file(split, inject, warm)
    score = make_scorer()
    for seed, kind, condition, shared in pending_sequences(seeds, split, path, depth_only=True):
        rows = stream_and_score(seed, kind, condition, shared, score, inject, warm)
        append_rows(path, FIELDS, rows)
        r = rows[0]
        print(
            f"{seed} {kind} {condition['width']}px: stream {r['stream_seconds']:.0f} s, "
            f"blind {r['blind_seconds']:.0f} s, scores {r['score_seconds']:.0f} s, "
            f"refinement {r['refine_seconds']:.0f} s",
            flush=True,
        )


def load(split: str, inject: float = 0.0, warm: bool = False, seeds=None) -> dict:
    """The log of ``split``, ``inject`` and ``warm`` (only the rows of ``seeds``, if given; a
    column the log does not hold is NaN)."""
    with frames_file(split, inject, warm).open() as f:
        rows = [r for r in csv.DictReader(f) if seeds is None or int(r["seed"]) in seeds]
    return {
        k: np.array([r.get(k, "nan") for r in rows], object if k == "kind" else float)
        for k in FIELDS
    }


def report(split: str, inject: float, warm: bool, seeds=None) -> str:
    data = load(split, inject, warm, seeds)
    acted = dict(data, pos=data["acted_pos"], rot=data["acted_rot"])
    right, ok = data["kind"] == "right", data["status"] == 0
    every = np.ones(len(right), bool)
    episodes = list(zip(data["seed"], data["kind"], strict=True))
    seeds = sorted({int(s) for s in data["seed"]})
    good = right & (data["acted_pos"] < 0.25) & (data["acted_rot"] < 5.0)
    lines = [
        f"{len(seeds)} conditions whose filter scores depth ({', '.join(map(str, seeds))}), "
        f"{len(right)} frames, {(~right).sum()} in look-alike wrong places; {good.sum()} "
        "right-room frames with the acted-on pose within 0.25 m / 5 deg.",
        "",
        "Margin acted_s - best_s (shares of S_max), quartiles: right-room good frames "
        + quartiles(data["acted_s"][good] - data["best_s"][good])
        + "; wrong-place frames "
        + quartiles(data["acted_s"][~right] - data["best_s"][~right])
        + ".",
        "",
        "Seconds per sequence (10 frames, compilation included), median: stream "
        f"{np.median(data['stream_seconds']):.1f}, depth-blind stream "
        f"{np.median(data['blind_seconds']):.1f}, the scores {np.median(data['score_seconds']):.1f}"
        f", refinement {np.median(data['refine_seconds']):.1f}"
        + (
            f"; optimiser steps per refinement, median {np.median(data['steps']):.0f}."
            if np.isfinite(data["steps"]).all()
            else "."
        ),
        "",
        "Flagged: the refinement is ok, the depth agrees at the refined pose (>= tau_pose) and its "
        "depth-blind score is within delta of the depth-blind stream's best particle (now, at "
        "some frame so far, or on average over the frames so far):",
        "",
        "| delta | tau_pose | when | flagged | precision (within 0.5 m / 10 deg) | recall of good "
        "| wrong-place frames flagged |",
        "|---|---|---|---|---|---|---|",
    ]
    for delta in (*DELTAS, np.inf):
        for tau_pose in TAUS:
            for when, place in confirmations(data, episodes, delta).items():
                flagged = place & ok & (data["acted_rel"] >= tau_pose)
                j = judge(acted, flagged, every)
                lines.append(f"| {delta:g} | {tau_pose:.2f} | {when} | {judged_cells(j)}")
    lines += [
        "",
        "Without the refinement: the stream's own estimate, its depth agreement (>= tau_pose) and "
        "its depth-blind score within delta of the best particle (now):",
        "",
        "| delta | tau_pose | flagged | precision | recall of good | wrong flagged |",
        "|---|---|---|---|---|---|",
    ]
    for delta in (*DELTAS, np.inf):
        for tau_pose in TAUS:
            flagged = (data["own_s"] >= data["best_s"] - delta) & (data["own_rel"] >= tau_pose)
            j = judge(data, flagged, every)
            lines.append(f"| {delta:g} | {tau_pose:.2f} | {judged_cells(j)}")
    delta, tau_pose, when = choose(inject, warm)
    flagged = confirmations(data, episodes, delta)[when] & ok & (data["acted_rel"] >= tau_pose)
    whole = judge(acted, flagged, every)
    lines += [
        "",
        f"Chosen on the development split (see choose()): delta {delta:g}, tau_pose {tau_pose}, "
        f"{when}: {whole['flagged']} flagged, precision {whole['precision']:.3f}, recall of good "
        f"{whole['recall']:.3f}, wrong-place frames flagged {whole['false_accept']:.3f}. Per image "
        "width:",
        "",
        "| width | conditions | good | flagged | precision | recall of good | wrong flagged |",
        "|---|---|---|---|---|---|---|",
    ]
    for width in sorted(set(data["width"])):
        at = data["width"] == width
        j, conditions = judge(acted, flagged, at), len(set(data["seed"][at]))
        lines.append(f"| {width:.0f} | {conditions} | {j['good']} | {judged_cells(j)}")
    return "\n".join(lines)


def choose(inject: float, warm: bool) -> tuple[float, float, str]:
    """(delta, tau_pose, when) chosen on the development split: the row of the report's grid with
    the most recall of the good frames whose precision is >= 0.95 and whose share of wrong places
    flagged is <= 0.05 on the whole split and on each half of its conditions (alternate seeds)."""
    data = load("dev", inject, warm)
    acted = dict(data, pos=data["acted_pos"], rot=data["acted_rot"])
    episodes = list(zip(data["seed"], data["kind"], strict=True))
    seeds = sorted(set(data["seed"]))
    parts = [np.ones(len(data["seed"]), bool)]
    parts += [np.isin(data["seed"], seeds[i::2]) for i in range(2)]
    best, chosen = -1.0, None
    for delta in DELTAS:
        for tau_pose in TAUS:
            for when, place in confirmations(data, episodes, delta).items():
                flagged = place & (data["status"] == 0) & (data["acted_rel"] >= tau_pose)
                judged = [judge(acted, flagged, part) for part in parts]
                if all(j["precision"] >= 0.95 and j["false_accept"] <= 0.05 for j in judged):
                    if judged[0]["recall"] > best:
                        best, chosen = judged[0]["recall"], (delta, tau_pose, when)
    return chosen


def confirmations(data: dict[str, np.ndarray], episodes: list, delta: float) -> dict:
    """Per frame, by name: the margin ``acted_s - best_s`` >= -delta at this frame ("now"), at
    some frame so far ("any so far"), or on average over the frames so far ("mean so far")."""
    margin = data["acted_s"] - data["best_s"]
    return {
        "now": margin >= -delta,
        "any so far": latched(episodes, data["frame"], margin >= -delta),
        "mean so far": running_mean(episodes, data["frame"], margin) >= -delta,
    }


def running_mean(episodes: list, frames, values: np.ndarray) -> np.ndarray:
    """Per row: the mean of ``values`` over this and the earlier frames of the row's sequence."""
    out, sums = np.zeros(len(values)), {}
    for i in sorted(range(len(values)), key=lambda i: frames[i]):
        total, count = sums.get(episodes[i], (0.0, 0))
        sums[episodes[i]] = (total + float(values[i]), count + 1)
        out[i] = sums[episodes[i]][0] / sums[episodes[i]][1]
    return out


def quartiles(values: np.ndarray) -> str:
    q = np.percentile(values, [25, 50, 75]) if len(values) else [np.nan] * 3
    return " / ".join(f"{v:+.3f}" for v in q)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", action="store_true", help="run the seeds into frames_SPLIT.csv")
    parser.add_argument("--split", choices=sorted(SPLITS), default="dev")
    parser.add_argument("--seeds", type=parse_seeds, default=None, help="e.g. 5100-5123")
    parser.add_argument("--report", action="store_true", help="the check's tables")
    parser.add_argument(
        "--inject",
        type=float,
        default=0.0,
        help="share of the capacity the depth-blind stream replaces by random particles after "
        "each frame it is not localized (default 0: none)",
    )
    parser.add_argument(
        "--warm", action="store_true", help="start each refinement from the previous refined pose"
    )
    args = parser.parse_args(argv)
    if args.run:
        run(args.seeds, args.split, args.inject, args.warm)
    if args.report:
        print(report(args.split, args.inject, args.warm, args.seeds))


if __name__ == "__main__":
    main()
