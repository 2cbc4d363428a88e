"""The Embree engine as a named XLA:CPU custom call (jaxloc.raycasting._host_target): a program that
casts rays with it is written to JAX's persistent compilation cache and a fresh process loads it
and gets the same hits (inside a loop and a vmap, where a cached program once passed the results in
the wrong form); a failing call gives invalid results and a logged error, never garbage."""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from jaxloc import raycast
from jaxloc.raycasting import embree, engines

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
    with caplog.at_level(logging.ERROR, logger="jaxloc"):
        hits = raycast(scene, *rays, engine="embree", differentiable=False)
    assert not np.asarray(hits.hit).any()
    assert np.all(np.asarray(hits.triangle_id) == -1)
    assert "jaxloc_embree_nearest failed" in caplog.text and "the engine broke" in caplog.text
