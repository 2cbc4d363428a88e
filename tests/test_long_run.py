"""Long runs stay on one compilation: chunked filter passes with a carried state and global frame
indices (what ``benchmarks/long_run.py`` does for 1000 frames; memory is measured there, not
asserted here). Query-level no-retrace of ``localize_scan``: tests/test_m2loc_pipeline.py.
"""

from __future__ import annotations

import _tiny_world as tiny
import jax
import numpy as np


def test_chunked_passes_over_many_frames_do_not_retrace():
    scene = tiny.scene()
    config = tiny.step_config(scene)
    state = tiny.initial_state(scene)
    other_scene = tiny.scene(seed=7)  # another map of the same capacity
    assert other_scene.capacity == scene.capacity
    before = tiny.TRACES["run_pass"]
    key = jax.random.key(11)
    estimates = []
    for chunk in range(6):
        frames = tiny.frames(tiny.CHUNK, seed=chunk, first_index=chunk * tiny.CHUNK)
        world = scene if chunk % 2 == 0 else other_scene
        state, info = tiny.RUN_PASS(jax.random.fold_in(key, chunk), state, frames, world, config)
        estimates.append(np.asarray(info.mle))
    # at most the first call compiles (zero if another module compiled the pass already)
    assert tiny.TRACES["run_pass"] - before <= 1
    assert tiny.TRACES["run_pass"] >= 1
    assert np.all(np.isfinite(np.concatenate(estimates)))
    assert int(np.sum(np.asarray(state.active))) >= 1
