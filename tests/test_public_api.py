"""The public surface: small curated packages, every name documented, no name that shadows
Python's, and every name of jaxloc 0.2 still working for one release with a DeprecationWarning."""

from __future__ import annotations

import builtins
import collections.abc
import importlib
import inspect
import pathlib
import subprocess
import sys
import warnings

import pytest

PACKAGES = ["jaxloc", "jaxloc.io", "jaxloc.m2loc", "jaxloc.sg2loc", "jaxloc.mapping"]
ROOT = pathlib.Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("package, most", [("jaxloc.m2loc", 35), ("jaxloc.io", 45)])
def test_the_method_packages_stay_small(package, most):
    assert len(importlib.import_module(package).__all__) <= most


@pytest.mark.parametrize("package", PACKAGES)
def test_every_public_name_resolves_and_is_documented(package):
    module = importlib.import_module(package)
    undocumented = []
    for name in module.__all__:
        value = getattr(module, name)
        if (inspect.isclass(value) or inspect.isfunction(value)) and not inspect.getdoc(value):
            undocumented.append(name)
    assert not undocumented


@pytest.mark.parametrize("package", PACKAGES)
def test_no_public_name_shadows_python(package):
    """A reader never meets ``filter`` or ``Sequence`` that is not Python's."""
    taken = set(dir(builtins)) | set(collections.abc.__all__)
    assert not taken & set(importlib.import_module(package).__all__)


@pytest.mark.parametrize("package", PACKAGES)
def test_old_names_warn_and_resolve_to_their_new_place(package):
    module = importlib.import_module(package)
    moved = getattr(module.__getattr__, "deprecated", {}) if hasattr(module, "__getattr__") else {}
    for old, source in moved.items():
        where, _, attribute = source.partition(":")
        home = importlib.import_module(where)
        expected = getattr(home, attribute, None)
        if expected is None:
            expected = importlib.import_module(f"{where}.{attribute}")
        with pytest.warns(DeprecationWarning, match=f"{package}.{old} is deprecated"):
            assert getattr(module, old) is expected, old
    assert package not in ("jaxloc.io", "jaxloc.m2loc", "jaxloc.sg2loc") or moved


def test_renamed_reader_names_still_work_in_their_modules():
    from jaxloc.io import meshes, read_meshes

    with pytest.warns(DeprecationWarning, match="use jaxloc.io.meshes.read_meshes"):
        assert meshes.load_meshes is read_meshes
    from jaxloc.io import TRIPLET_MAP_FORMAT_VERSION, lidar_map

    with pytest.warns(DeprecationWarning, match="lidar_map.TRIPLET_MAP_FORMAT_VERSION"):
        assert lidar_map.FORMAT_VERSION == TRIPLET_MAP_FORMAT_VERSION


def test_old_module_paths_import_with_a_warning():
    """``import jaxloc.sg2loc.filter`` (a stage module of 0.2) imports the private module, in a
    fresh interpreter so that no earlier import hides the warning."""
    code = (
        "import warnings\n"
        "warnings.simplefilter('error')\n"
        "try:\n"
        "    from jaxloc.sg2loc.filter import StepConfig\n"
        "except DeprecationWarning as w:\n"
        "    print('warned:', w)\n"
        "warnings.simplefilter('ignore')\n"
        "from jaxloc.sg2loc.filter import StepConfig\n"
        "import jaxloc.sg2loc\n"
        "assert StepConfig is jaxloc.sg2loc.StepConfig\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True
    )
    assert "warned: jaxloc.sg2loc.filter is deprecated" in done.stdout


def test_no_test_hooks_in_the_library():
    hits = [
        str(path.relative_to(ROOT))
        for path in (ROOT / "jaxloc").rglob("*.py")
        if "TRACE_COUNTS" in path.read_text()
    ]
    assert not hits


def test_the_stream_and_the_rounds_share_one_config():
    """``online.init`` takes an SG2LocConfig; ``OnlineConfig`` only remains as a warning."""
    from jaxloc.sg2loc import SG2LocConfig, online

    assert "SG2LocConfig" in str(inspect.signature(online.init).parameters["config"].annotation)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        config, patch_shape = online.OnlineConfig(stride=10, patch_shape=(3, 4)).as_sg2loc()
    assert any(issubclass(w.category, DeprecationWarning) for w in caught)
    assert isinstance(config, SG2LocConfig) and config.strides == (10,) and patch_shape == (3, 4)
