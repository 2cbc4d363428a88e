"""Host functions as named XLA:CPU FFI targets (jaxloc.raycasting._host_target): a toy target sees
every buffer's shape and dtype, vmapped calls with their batch axes in front, inside loops and
branches; a program that casts rays with the Embree target is written to JAX's persistent
compilation cache and a fresh process loads it and gets the same hits (inside a loop and a vmap,
where a cached program of XLA's older custom-call convention once received its results in the
wrong form); a failing call gives invalid results and a logged error, never garbage."""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxloc import raycast
from jaxloc.raycasting import embree, engines
from jaxloc.raycasting._host_target import FAILED_INT, host_call, register_host_target

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.skipif(not engines.is_installed("embree"), reason="embreex not installed")

#: Casts a random scene's rays through the Embree target (both paths) in a lax.map over chunks
#: and a vmap, with the compilation cache in argv[1]; reports the hits and the cache hits.
SCRIPT = """
import json, os, sys
sys.path.insert(0, "tests")
import jax, jax.numpy as jnp
import jaxloc
from conftest import random_rays, random_scene  # sets the test session's cache: undone below
from jaxloc import raycast

os.environ.pop("JAXLOC_NO_CACHE")
assert jaxloc.enable_compilation_cache(sys.argv[1]) is not None
hits = []
jax.monitoring.register_event_listener(
    lambda event, **kw: hits.append(event) if event.endswith("cache_hits") else None
)
scene = random_scene(0)
origins, directions = (jnp.asarray(a[:2048]).reshape(4, 512, 3) for a in random_rays(scene, 1))

@jax.jit
def cast_chunks(scene, origins, directions):
    def chunk(rays):
        o, d = rays
        exact = raycast(scene, o, d, engine="embree")
        fast = jax.vmap(lambda a, b: raycast(scene, a, b, engine="embree", differentiable=False))(
            o.reshape(2, -1, 3), d.reshape(2, -1, 3)
        )
        return exact.triangle_id, fast.triangle_id.reshape(-1), fast.t.reshape(-1)
    return jax.lax.map(chunk, (origins, directions))

exact, fast, t = cast_chunks(scene, origins, directions)
print(json.dumps({"exact": exact.tolist(), "fast": fast.tolist(),
                  "t": jnp.where(fast >= 0, t, 0.0).tolist(), "hits": len(hits)}))
"""


#: The shapes the toy target saw, call by call.
SEEN: list = []


def _toy(inputs: list, outputs: list) -> None:
    """outputs: (x * 2 + sum(y) over its last axis, the count of x's last axis as int32)."""
    x, y, fail = inputs
    SEEN.append([(a.shape, a.dtype.name) for a in inputs])
    if fail.any():
        raise ValueError("asked to fail")
    outputs[0][...] = x * 2 + y.sum(axis=-1, keepdims=True)
    outputs[1][...] = x.shape[-1]


assert register_host_target("jaxloc_test_toy", _toy)


def toy(x, y, fail):
    results = (jax.ShapeDtypeStruct(x.shape, x.dtype), jax.ShapeDtypeStruct((), jnp.int32))
    return host_call("jaxloc_test_toy", results, x, y, fail)


def test_a_target_sees_the_shapes_and_batch_axes_it_is_called_with():
    x, y = jnp.arange(5.0), jnp.ones(3, jnp.int32)
    SEEN.clear()
    doubled, count = jax.jit(toy)(x, y, False)
    np.testing.assert_array_equal(doubled, np.arange(5.0) * 2 + 3)
    assert int(count) == 5 and count.dtype == jnp.int32
    assert SEEN == [[((5,), "float32"), ((3,), "int32"), ((), "bool")]]

    xs, ys = jnp.stack([x, x + 1]), jnp.stack([y, 2 * y, 3 * y])
    SEEN.clear()
    batched = jax.jit(jax.vmap(jax.vmap(toy, (None, 0, None)), (0, None, None)))(xs, ys, False)
    expected = xs[:, None, :] * 2 + ys.sum(-1)[None, :, None]
    np.testing.assert_array_equal(batched[0], expected)
    assert np.all(np.asarray(batched[1]) == 5) and batched[1].shape == (2, 3)
    # One call for the whole batch, every operand with both batch axes (size 1 where unbatched).
    assert SEEN == [[((2, 1, 5), "float32"), ((1, 3, 3), "int32"), ((1, 1), "bool")]]

    def loop(x):
        def body(carry, _):
            carry = jax.lax.cond(carry[0] < 100, lambda c: toy(c, y, False)[0], lambda c: c, carry)
            return carry, carry[0]

        return jax.lax.scan(body, x, length=4)[1]

    np.testing.assert_array_equal(jax.jit(loop)(x), [3.0, 9.0, 21.0, 45.0])


def test_a_failed_call_gives_nan_and_failed_integers_in_its_own_batch_element(caplog):
    x, y = jnp.arange(3.0), jnp.ones(2, jnp.int32)
    with caplog.at_level(logging.ERROR, logger="jaxloc"):
        doubled, count = jax.jit(toy)(x, y, True)
    assert np.isnan(np.asarray(doubled)).all() and int(count) == FAILED_INT
    assert "jaxloc_test_toy failed" in caplog.text and "asked to fail" in caplog.text
    # A vmapped call is one call: a failure anywhere invalidates the whole batch, never garbage.
    doubled, count = jax.jit(jax.vmap(toy, (None, None, 0)))(x, y, jnp.array([False, True]))
    assert np.isnan(np.asarray(doubled)).all() and np.all(np.asarray(count) == FAILED_INT)


def _run(folder: Path) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("JAX_COMPILATION", "JAXLOC_"))}
    done = subprocess.run(
        [sys.executable, "-c", SCRIPT, str(folder)], env=env, capture_output=True, text=True,
        cwd=ROOT, timeout=300,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_a_program_calling_embree_is_cached_and_loads_in_a_fresh_process(tmp_path):
    folder = tmp_path / "xla"
    first = _run(folder)
    assert any(folder.glob("jit_cast_chunks-*")), "the program was not written to the cache"
    second = _run(folder)
    assert second["hits"] >= 1
    assert second["exact"] == first["exact"] and second["fast"] == first["fast"]
    np.testing.assert_array_equal(second["t"], first["t"])
    exact, fast = np.asarray(first["exact"]), np.asarray(first["fast"])
    np.testing.assert_array_equal(exact, fast)
    assert 0.3 < (exact >= 0).mean() < 0.95


def test_a_failing_call_gives_invalid_results_and_logs_the_error(scene, rays, monkeypatch, caplog):
    def broken(*args, **kwargs):
        raise RuntimeError("the engine broke")

    monkeypatch.setattr(embree, "_embree_host", broken)
    monkeypatch.setattr(embree, "_target", embree.python_target)  # the Python implementation
    with caplog.at_level(logging.ERROR, logger="jaxloc"):
        hits = raycast(scene, *rays, engine="embree", differentiable=False)
    assert not np.asarray(hits.hit).any()
    assert np.all(np.asarray(hits.triangle_id) == -1)
    assert f"{embree.python_target()} failed" in caplog.text and "the engine broke" in caplog.text
