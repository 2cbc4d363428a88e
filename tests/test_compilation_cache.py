"""jaxloc's compilation cache (jaxloc.compilation_cache) in fresh processes: used when enabled,
never when disabled, and a damaged entry only costs a compilation; traced programs kept on disk
(``cached_call``) are loaded instead of traced, and a damaged one is traced again. The command
line's ``--help`` imports no JAX."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from jaxloc import compilation_cache
from jaxloc.compilation_cache import FAST_COMPILATION_FLAG, prefer_fast_compilation

ROOT = Path(__file__).resolve().parents[1]

#: A process that enables the cache (unless JAXLOC_NO_CACHE), compiles two small programs and one
#: kept program, and reports the results, the persistent-cache hits and the traces.
SCRIPT = """
import json, sys
import equinox as eqx
import jax, jax.numpy as jnp
import jaxloc
from jaxloc.compilation_cache import cached_call

folder = jaxloc.enable_compilation_cache(sys.argv[1])
hits, traces = [], []
jax.monitoring.register_event_listener(
    lambda event, **kw: hits.append(event) if event.endswith("cache_hits") else None
)

class Scale(eqx.Module):
    factor: jax.Array
    power: int = eqx.field(static=True)

@eqx.filter_jit
def kept(scale, x):
    traces.append(1)
    return scale.factor * x**scale.power, jnp.cumsum(x)

f = jax.jit(lambda x: jnp.sin(x) * 2 + jnp.cumsum(x))
out = cached_call("kept", kept, tuple, Scale(jnp.float32(3.0), 2), jnp.arange(4.0))
print(json.dumps({
    "folder": None if folder is None else str(folder),
    "f": f(jnp.arange(4.0)).tolist(),
    "kept": [o.tolist() for o in out],
    "hits": len(hits),
    "traces": len(traces),
}))
"""


#: What the command line does before it imports jax.
QUIET = (
    "from jaxloc.compilation_cache import prefer_fast_compilation, quiet_xla_log\n"
    "prefer_fast_compilation()\nquiet_xla_log()\n"
)


def run(folder: Path, *, disabled: bool = False, quiet: bool = False) -> tuple[dict, str]:
    env = {
        k: v
        for k, v in os.environ.items()
        if not k.startswith(("JAX_COMPILATION", "JAXLOC_", "TF_CPP_MIN_LOG_LEVEL", "XLA_FLAGS"))
    }
    if disabled:
        env["JAXLOC_NO_CACHE"] = "1"
    done = subprocess.run(
        [sys.executable, "-c", (QUIET if quiet else "") + SCRIPT, str(folder)], env=env,
        capture_output=True, text=True, cwd=ROOT, timeout=300,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1]), done.stderr


EXPECTED_F = [0.0, 2.6829419136047363, 4.818594932556152, 6.28223991394043]
EXPECTED_KEPT = [[0.0, 3.0, 12.0, 27.0], [0.0, 1.0, 3.0, 6.0]]


@pytest.fixture(scope="module")
def warm(tmp_path_factory):
    """(folder, first run, second run) of the script with the cache on."""
    folder = tmp_path_factory.mktemp("cache") / "xla"
    return folder, run(folder)[0], run(folder)[0]


def test_the_cache_is_used_when_enabled(warm):
    folder, first, second = warm
    assert first["folder"] == str(folder) and any(folder.glob("*-cache"))
    assert first["f"] == second["f"] == EXPECTED_F
    assert first["kept"] == second["kept"] == EXPECTED_KEPT
    assert first["hits"] == 0 and second["hits"] >= 2  # the second process loads, not compiles
    assert first["traces"] == 1 and second["traces"] == 0  # the kept program is not traced again
    assert len(list((folder / "programs").glob("kept-*.jaxexport"))) == 1


def test_the_command_line_hides_the_spurious_aot_loader_errors(tmp_path):
    """jax-ml/jax#38445: on some CPUs every program loaded from the cache logs two E-level
    ``cpu_aot_loader`` lines although it loads fine; the command line's set-up hides them and the
    cache still serves the programs."""
    folder = tmp_path / "xla"
    run(folder, quiet=True)
    second, stderr = run(folder, quiet=True)
    assert second["hits"] >= 2 and second["traces"] == 0 and second["f"] == EXPECTED_F
    assert "cpu_aot_loader" not in stderr


def test_the_cache_is_never_used_when_disabled(tmp_path):
    folder = tmp_path / "xla"
    result, _ = run(folder, disabled=True)
    assert result["folder"] is None and result["hits"] == 0 and result["traces"] == 1
    assert result["f"] == EXPECTED_F and not folder.exists()


def test_damaged_entries_cost_only_a_compilation(tmp_path):
    """Every entry overwritten with garbage or truncated, a stray file in the folder, the kept
    program damaged: the next run warns, compiles and traces again, and gives the same results.
    (Entries are keyed with the folder's path, so the damage is done in place.)"""
    folder = tmp_path / "xla"
    run(folder)
    entries = sorted(p for p in folder.rglob("*") if p.is_file() and not p.name.endswith("-atime"))
    for index, entry in enumerate(entries):
        data = entry.read_bytes()
        entry.write_bytes(data[: len(data) // 3] if index % 2 else os.urandom(200))
    (folder / "notes.txt").write_text("not an entry")
    result, stderr = run(folder)
    assert result["f"] == EXPECTED_F and result["kept"] == EXPECTED_KEPT
    assert result["hits"] == 0 and result["traces"] == 1
    assert "Error reading persistent compilation cache entry" in stderr


def test_help_imports_no_jax():
    code = (
        "import sys\nfrom jaxloc.cli import main\n"
        "for argv in (['--help'], ['localize-lidar', '--help'], ['localize-camera', '--help']):\n"
        "    try:\n        main(argv)\n    except SystemExit:\n        pass\n"
        "assert 'jax' not in sys.modules, 'jax imported'\nprint('ok')"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert done.returncode == 0 and done.stdout.strip().endswith("ok"), done.stderr[-2000:]


def test_the_command_line_quiets_the_xla_log_before_its_checks_import_jax():
    """The demo's option checks import JAX (SSIM's window); the log level must be set before
    that, or every cached program logs the spurious lines (seen in `jaxloc demo` before)."""
    report = _command_environment(["demo", "--width", "160", "--height", "120"], {})
    assert report == {"log": "3", "xla_flags": FAST_COMPILATION_FLAG, "jax": True}


def _command_environment(argv: list[str], extra: dict) -> dict:
    """The log level and XLA flags the command ``argv`` runs with (the command replaced by a
    recorder, after the command line's set-up and checks), in an environment without either
    plus ``extra``."""
    code = (
        "import json, os, sys\nimport jaxloc.cli as cli\nseen = {}\n"
        "def record(args):\n"
        "    seen.update(log=os.environ.get('TF_CPP_MIN_LOG_LEVEL'),\n"
        "                xla_flags=os.environ.get('XLA_FLAGS'))\n    return 0\n"
        f"cli._COMMANDS[{argv[0]!r}] = record\n"
        f"cli.main({argv!r})\n"
        "print(json.dumps({**seen, 'jax': 'jax' in sys.modules}))"
    )
    env = {k: v for k, v in os.environ.items() if k not in ("TF_CPP_MIN_LOG_LEVEL", "XLA_FLAGS")}
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, env={**env, **extra}
    )
    assert done.returncode == 0, done.stderr[-2000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_fast_compilation_for_the_camera_commands_only_and_never_over_the_users_flags():
    """localize-camera compiles with the legacy emitters, localize-lidar keeps XLA's defaults
    (its three-scale query runs slower with them), and a user's XLA_FLAGS are left as they are."""
    camera = ["localize-camera", "map.npz", "seq"]
    assert _command_environment(camera, {})["xla_flags"] == FAST_COMPILATION_FLAG
    assert _command_environment(["localize-lidar", "map", "scan"], {})["xla_flags"] is None
    own = {"XLA_FLAGS": "--xla_cpu_enable_fast_math=false"}
    assert _command_environment(camera, own)["xla_flags"] == own["XLA_FLAGS"]


def test_fast_compilation_is_not_set_once_jax_is_imported_or_for_other_jaxlibs(monkeypatch):
    """Once jax is in, XLA's flags may already be parsed: nothing changes. A jaxlib outside the
    versions known to have the flag gets none (XLA aborts on an unknown flag)."""
    import jax  # noqa: F401 - imported, as in any test process

    monkeypatch.delenv("XLA_FLAGS", raising=False)
    assert not prefer_fast_compilation() and "XLA_FLAGS" not in os.environ
    monkeypatch.delitem(sys.modules, "jax")
    monkeypatch.setattr(compilation_cache, "FAST_COMPILATION_JAXLIB", ((0, 3), (0, 4)))
    assert not prefer_fast_compilation() and "XLA_FLAGS" not in os.environ
    monkeypatch.setattr(compilation_cache, "FAST_COMPILATION_JAXLIB", ((0, 0), (99, 0)))
    assert prefer_fast_compilation() and os.environ["XLA_FLAGS"] == FAST_COMPILATION_FLAG


def test_legacy_emitter_options_reach_the_compiler_only_where_xla_knows_them(tmp_path, monkeypatch):
    """cached_call hands its compiler_options to XLA (an unknown one is refused, a known one
    compiles the same values); legacy_emitter_options is empty for a jaxlib without the option."""
    import jax
    import jax.numpy as jnp

    from jaxloc.compilation_cache import cached_call, legacy_emitter_options

    monkeypatch.delenv("JAXLOC_NO_CACHE", raising=False)
    monkeypatch.setitem(compilation_cache._PROGRAMS, "folder", tmp_path / "cache")
    x = jnp.linspace(-2.0, 2.0, 7)

    def program(x):
        return jnp.tanh(x) * x + 1.0, jnp.argmax(x)

    expected = jax.jit(program)(x)
    got = cached_call("legacy", program, tuple, x, compiler_options=legacy_emitter_options())
    for value, reference in zip(got, expected, strict=True):
        np.testing.assert_allclose(value, reference, rtol=1e-6)
    with pytest.raises(Exception, match="xla_no_such_option"):
        cached_call("unknown", program, tuple, x, compiler_options={"xla_no_such_option": True})
    monkeypatch.setattr(compilation_cache, "FAST_COMPILATION_JAXLIB", ((0, 3), (0, 4)))
    assert legacy_emitter_options() == {}
