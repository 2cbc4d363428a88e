"""Multi-device sharding (:mod:`jaxloc.sharding`) on 4 fake CPU devices, single-device peers.

``--xla_force_host_platform_device_count`` only takes effect before jax is imported, and this
pytest process has imported it already, so ``tests/_sharding_check.py`` runs the sharded and the
single-device computations in a subprocess and prints the measured differences as JSON; the
assertions are here. The in-process tests check the helpers' argument validation on the one
device this process has.
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import _tiny_world as tiny
import jax
import numpy as np
import pytest

from jaxloc import sg2loc, sharding
from jaxloc.sg2loc import sharded
from jaxloc.sg2loc._particles import ParticleState

SCRIPT = Path(__file__).with_name("_sharding_check.py")
#: The package of each optional engine.
PACKAGES = {"embree": "embreex", "warp": "warp"}


@pytest.fixture(scope="module")
def measured() -> dict:
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    env["JAX_PLATFORMS"] = "cpu"
    done = subprocess.run(
        [sys.executable, str(SCRIPT)], capture_output=True, text=True, env=env, timeout=1800
    )
    assert done.returncode == 0, done.stderr[-4000:]
    line = [x for x in done.stdout.splitlines() if x.startswith("RESULT ")][-1]
    return json.loads(line.removeprefix("RESULT "))


def test_runs_on_four_devices_and_keeps_the_particles_split(measured):
    assert measured["devices"] == 4
    assert measured["state_devices"] == 4
    split = str(jax.sharding.PartitionSpec(sharding.AXIS))
    assert measured["state_spec"] == split
    assert measured["batch_spec"] == split


def test_sharded_particles_equal_the_single_device_pass(measured):
    # discrete outputs identical; continuous ones equal up to the float32 reduction order
    assert measured["pass_counts_equal"] and measured["pass_active_equal"]
    assert not measured["pass_nan"]
    assert measured["pass_mle_diff"] <= 1e-5
    assert measured["pass_poses_diff"] <= 1e-5
    assert measured["pass_log_weights_diff"] <= 1e-4


def test_sharded_sequences_equal_each_sequence_alone(measured):
    assert measured["batch_counts_equal"]
    assert measured["batch_mle_diff"] <= 1e-5


def test_localize_with_a_mesh_equals_one_device(measured):
    # the user API unchanged but for ``mesh=``: same particle counts, same per-round MLE
    assert measured["localize_counts_equal"]
    assert not measured["localize_nan"]
    assert measured["localize_poses_diff"] <= 1e-5
    assert measured["localize_particles_devices"] == 4
    # with a progress bar (a host callback in the scan): the same counts and poses, still sharded
    assert measured["progress_counts_equal"]
    assert measured["progress_poses_diff"] <= 1e-5
    assert measured["progress_particles_devices"] == 4


def test_every_engine_and_the_chunk_loop_run_sharded_like_one_device(measured):
    """Each installed engine, and chunks of 2 particles per device (a loop per shard), give the
    single-device pass on 4 devices: the same discrete results, close poses."""
    expected = {"jax/None", "auto/2"} | {
        f"{e}/None" for e in ("embree", "warp") if importlib.util.find_spec(PACKAGES[e])
    }
    assert set(measured["engines"]) == expected
    for name, checks in measured["engines"].items():
        assert checks["state_devices"] == 4, name
        assert checks["pass_counts_equal"] and checks["pass_active_equal"], name
        assert not checks["pass_nan"], name
        assert checks["pass_mle_diff"] <= 1e-5 and checks["pass_poses_diff"] <= 1e-5, name
        assert checks["pass_log_weights_diff"] <= 1e-4, name


def test_each_device_calls_the_engine_on_its_own_shard(measured):
    """A sharded step with Embree calls it once per device, each time with one shard's rays
    (16 particles / 4 devices, each particle's grid rays: Embree's rays are not padded to the
    "jax" engine's packets), not with all of them."""
    if "embree_rays_per_call" not in measured:
        pytest.skip("embreex not installed")
    per_particle = measured["rays_per_particle"]
    assert measured["embree_rays_per_call"] == [tiny.CAPACITY // 4 * per_particle] * 4


def test_sharded_queries_equal_localize_scan(measured):
    assert measured["queries_valid_equal"] and measured["queries_inliers_equal"]
    assert measured["queries_pose_diff"] <= 1e-3  # metres / rotation entries, float32 solver
    assert measured["queries_num_valid"] >= 1
    # localize_scans(config=) runs the map with that config's query settings, as localize_scan
    assert measured["queries_config_equal"] and measured["queries_config_changed"]


def test_same_key_is_bit_identical_in_another_process(measured):
    # the subprocess ran the single-device pass with the same key and inputs: same bytes here
    scene = tiny.scene()
    state, info = tiny.RUN_PASS(
        jax.random.key(2), tiny.initial_state(scene), tiny.frames(tiny.CHUNK), scene,
        tiny.step_config(scene),
    )  # fmt: skip
    assert digest((state, info)) == measured["single_digest"]


def digest(tree) -> str:
    h = hashlib.sha256()
    for leaf in jax.tree.leaves(tree):
        h.update(np.asarray(leaf).tobytes())
    return h.hexdigest()


def test_helpers_validate_their_arguments():
    mesh = sharding.device_mesh()
    assert mesh.axis_names == (sharding.AXIS,)
    state = ParticleState(np.zeros((6, 4), np.float32), np.zeros(6, np.float32), np.ones(6, bool))
    placed = sharded.shard_particles(state, mesh)
    assert placed.poses.sharding.spec == jax.sharding.PartitionSpec(sharding.AXIS)
    with pytest.raises(TypeError, match="ParticleState"):
        sharded.shard_particles(np.zeros((6, 4)), mesh)
    with pytest.raises(ValueError, match="leading batch axis"):
        sharding.shard_batch({"x": np.float32(1.0)}, mesh)
    with pytest.raises(ValueError, match="at least one device"):
        sharding.device_mesh([])
    replicated = sharding.replicate({"x": np.ones(3)}, mesh)
    assert replicated["x"].sharding.is_fully_replicated


def test_uneven_split_names_the_size_to_pad_to():
    four_devices = SimpleNamespace(devices=np.empty(4, object))  # only the size is read
    with pytest.raises(ValueError, match=r"capacity \(6\) must be a multiple of the mesh's 4"):
        sharding.check_divisible(6, four_devices, "the particle capacity")
    with pytest.raises(ValueError, match="pad it up to 8"):
        sharding.check_divisible(6, four_devices, "the batch size")


def test_localize_rejects_a_capacity_that_does_not_split():
    three_devices = SimpleNamespace(devices=np.empty(3, object))  # only the size is read
    config = sg2loc.SG2LocConfig(capacity=tiny.CAPACITY, strides=(8,))
    with pytest.raises(ValueError, match=r"SG2LocConfig.capacity \(16\) .* pad it up to 18"):
        sg2loc.localize(
            jax.random.key(0), tiny.scene(), tiny.sequence(2), config, mesh=three_devices
        )
