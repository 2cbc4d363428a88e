"""Saved described maps: exact round trip, validation of every kind of bad file, no pickle, and
the M2Loc default configuration."""

from __future__ import annotations

import contextlib
import io
import json
import zipfile

import jax
import numpy as np
import pytest

from jaxloc.io import TRIPLET_MAP_FORMAT_VERSION, MapFormatError, load_triplet_map, save_triplet_map
from jaxloc.m2loc import build_map, m2loc_config, tripletloc_config
from jaxloc.synthetic.outdoor import make_outdoor_world


@pytest.fixture(scope="module")
def world():
    return make_outdoor_world("sparse", seed=3, blocks=1, bridge_length=0)


@pytest.fixture(scope="module", params=["m2loc", "tripletloc"])
def described(world, request):
    config = m2loc_config(2, top_k=7) if request.param == "m2loc" else tripletloc_config()
    normals = world.road_normals if request.param == "m2loc" else None
    return build_map(world.points, world.labels, config, normals)


def arrays_of(path) -> dict[str, np.ndarray]:
    with np.load(path, allow_pickle=False) as data:
        return {key: data[key] for key in data.files}


def write_arrays(path, arrays) -> None:
    np.savez(path, **arrays)


def test_round_trip_is_exact(described, tmp_path):
    path = tmp_path / "map.npz"
    save_triplet_map(described, path)
    loaded = load_triplet_map(path)
    assert loaded.config == described.config
    assert loaded.has_rsn == described.has_rsn
    for saved, back in zip(jax.tree.leaves(described), jax.tree.leaves(loaded), strict=True):
        assert np.asarray(saved).dtype == np.asarray(back).dtype
        np.testing.assert_array_equal(np.asarray(saved), np.asarray(back))
    assert not list(tmp_path.glob("*.tmp"))  # the atomic write left no temporary file


def test_default_configuration_is_m2loc_with_three_scales(world):
    triplet_map = build_map(world.points, world.labels)
    assert triplet_map.config == m2loc_config(3)
    assert len(triplet_map.descriptors) == 3


@pytest.fixture(scope="module")
def good_file(described, tmp_path_factory):
    path = tmp_path_factory.mktemp("good") / "map.npz"
    save_triplet_map(described, path)
    return path


def _edited(good_file, **changes) -> dict[str, np.ndarray]:
    arrays = arrays_of(good_file)
    for key, value in changes.items():
        if value is None:
            del arrays[key]
        else:
            arrays[key] = value
    return arrays


def bad_files(good_file) -> dict[str, tuple[dict | bytes, str]]:
    arrays = arrays_of(good_file)
    nan_points = arrays["points"].copy()
    nan_points[0, 1] = np.nan
    config = json.loads(str(arrays["config"]))
    config["surprise"] = 1
    bad_k = json.loads(str(arrays["config"]))
    bad_k["top_k"] = 0
    scaled = arrays["descriptors"].copy()
    scaled[0] *= 2.0
    return {
        "truncated": (good_file.read_bytes()[:2000], "not a readable jaxloc map"),
        "not a zip": (b"hello", "not a readable jaxloc map"),
        "wrong version": (
            _edited(good_file, version=np.array(TRIPLET_MAP_FORMAT_VERSION + 1)),
            "format version",
        ),
        "foreign npz": (_edited(good_file, format=np.array("something else")), "not a jaxloc"),
        "NaN point": (_edited(good_file, points=nan_points), "'points' contains NaN"),
        "wrong point shape": (
            _edited(good_file, points=arrays["points"][:, :2].copy()),
            "'points' has shape",
        ),
        "wrong dtype": (
            _edited(good_file, classes=arrays["classes"].astype(np.int64)),
            "'classes' has dtype",
        ),
        "missing array": (_edited(good_file, valid=None), "missing array 'valid'"),
        "descriptors of another size": (
            _edited(good_file, descriptors=arrays["descriptors"][:, :-1].copy()),
            "'descriptors' is not",
        ),
        "descriptors not unit": (_edited(good_file, descriptors=scaled), "not unit vectors"),
        "class out of range": (
            _edited(good_file, classes=np.full_like(arrays["classes"], 7)),
            "class positions out of range",
        ),
        "unknown config field": (
            _edited(good_file, config=np.array(json.dumps(config))),
            "unknown TripletConfig fields",
        ),
        "invalid config value": (
            _edited(good_file, config=np.array(json.dumps(bad_k))),
            "bad configuration",
        ),
        "config not JSON": (_edited(good_file, config=np.array("{")), "bad configuration"),
    }


def test_bad_files_raise_map_format_error(good_file, tmp_path):
    for name, (content, message) in bad_files(good_file).items():
        path = tmp_path / f"{name.replace(' ', '_')}.npz"
        if isinstance(content, bytes):
            path.write_bytes(content)
        else:
            write_arrays(path, content)
        with pytest.raises(MapFormatError, match=message):
            load_triplet_map(path)


def test_a_pickled_array_is_never_loaded(good_file, tmp_path):
    """An object array (loading it would unpickle, i.e. run code) is refused."""
    path = tmp_path / "pickled.npz"
    arrays = arrays_of(good_file)
    buffer = io.BytesIO()
    np.save(buffer, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with zipfile.ZipFile(path, "w") as archive:
        for key, value in arrays.items():
            item = io.BytesIO()
            np.save(item, value)
            archive.writestr(f"{key}.npy", item.getvalue())
        archive.writestr("evil.npy", buffer.getvalue())
    with pytest.raises(MapFormatError, match="not a readable"):
        load_triplet_map(path)


def test_missing_file_is_file_not_found(tmp_path):
    with pytest.raises(FileNotFoundError):
        load_triplet_map(tmp_path / "absent.npz")


def test_failed_save_leaves_the_old_file(described, good_file, tmp_path, monkeypatch):
    path = tmp_path / "map.npz"
    path.write_bytes(good_file.read_bytes())

    def broken(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(np, "savez_compressed", broken)
    with pytest.raises(OSError, match="disk full"):
        save_triplet_map(described, path)
    assert path.read_bytes() == good_file.read_bytes()
    assert not list(tmp_path.glob("*.tmp"))


def test_a_described_folder_is_kept_in_the_cache(world, tmp_path, monkeypatch):
    """With the compilation cache on, an instance-map folder is described once: the next
    open_triplet_map of the same instances and settings loads the kept map (identical arrays,
    no description), other settings get their own entry, a damaged entry is described again,
    and with the cache off nothing is kept."""
    import jaxloc.m2loc._map as map_module
    from jaxloc import compilation_cache
    from jaxloc.io import open_triplet_map, write_instance_maps
    from jaxloc.m2loc import Instances

    folder = tmp_path / "map"
    sizes = np.ones(len(world.points))
    write_instance_maps(folder, Instances(world.points, world.labels, sizes), world.road_normals)
    monkeypatch.delenv("JAXLOC_NO_CACHE", raising=False)
    monkeypatch.setitem(compilation_cache._PROGRAMS, "folder", tmp_path / "cache")
    config = m2loc_config(2, top_k=7)
    first = open_triplet_map(folder, config)
    kept = sorted((tmp_path / "cache" / "maps").glob("*.npz"))
    assert len(kept) == 1

    def no_description(*args, **kwargs):
        raise AssertionError("the kept map was described again")

    with monkeypatch.context() as patched:
        patched.setattr(map_module, "describe_map", no_description)
        second = open_triplet_map(folder, config)
    assert second.config == first.config
    for a, b in zip(jax.tree.leaves(first), jax.tree.leaves(second), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    open_triplet_map(folder, m2loc_config(2, top_k=7, verify_radius=2.0))
    assert len(list((tmp_path / "cache" / "maps").glob("*.npz"))) == 2
    kept[0].write_bytes(b"not a map")
    third = open_triplet_map(folder, config)
    np.testing.assert_array_equal(np.asarray(third.descriptors[0]), first.descriptors[0])
    assert load_triplet_map(kept[0]).config == first.config  # written again, whole
    monkeypatch.setenv("JAXLOC_NO_CACHE", "1")
    open_triplet_map(folder, m2loc_config(2, top_k=5))
    assert len(list((tmp_path / "cache" / "maps").glob("*.npz"))) == 2


def shapes_and_static(triplet_map):
    """What a compiled query program depends on: the tree, the leaves' shapes and dtypes, and
    the static parts (as jaxloc.compilation_cache keys them)."""
    import equinox as eqx

    from jaxloc.compilation_cache import _is_dynamic

    dynamic, static = eqx.partition(triplet_map, _is_dynamic)
    leaves, treedef = jax.tree.flatten(dynamic)
    return str(treedef), [(tuple(x.shape), str(x.dtype)) for x in leaves], repr(static)


@pytest.mark.parametrize("case", ["m2loc", "tripletloc", "small"])
def test_the_map_spec_is_what_build_map_returns(world, case):
    from jaxloc.m2loc._map import triplet_map_spec

    points, labels, normals = world.points, world.labels, world.road_normals
    config = m2loc_config(2, top_k=7)
    if case == "tripletloc":
        config, normals = tripletloc_config(), None
    if case == "small":  # top_k clamped to the 5 vertices
        points, labels, config = points[:5], labels[:5], m2loc_config(1)
    with pytest.warns() if case == "small" else contextlib.nullcontext():
        built = build_map(points, labels, config, normals)
    spec = triplet_map_spec(points, labels, config, normals)
    assert shapes_and_static(spec) == shapes_and_static(built)
    twice = np.concatenate([points, points[:1]]), np.concatenate([labels, labels[:1]])
    with pytest.raises(ValueError, match="duplicate"):  # what build_map refuses, it refuses
        triplet_map_spec(*twice, config)


def test_query_programs_compile_while_the_folder_is_described(world, tmp_path, monkeypatch):
    """open_triplet_map(..., query_capacities) exports the query programs before the map is
    described and compiles them in the background, the query with XLA:CPU's legacy emitters (a
    small graph: 2 scales x 32 x top_k 7 associations); localize_scan then runs those programs
    (no export or compilation of its own) and gives what it gives without the cache."""
    from concurrent.futures import Future

    from jaxloc import compilation_cache
    from jaxloc.io import open_triplet_map, write_instance_maps
    from jaxloc.m2loc import Instances, localize_scan
    from jaxloc.m2loc._localization import query_capacity
    from jaxloc.synthetic.outdoor import make_query

    folder = tmp_path / "map"
    sizes = np.ones(len(world.points))
    write_instance_maps(folder, Instances(world.points, world.labels, sizes), world.road_normals)
    query = make_query(
        world.points, world.labels, world.road_normals, np.random.default_rng(4), max_kept=25
    )
    config = m2loc_config(2, top_k=7)
    expected = localize_scan(open_triplet_map(folder, config), None, query.points, query.labels)
    monkeypatch.delenv("JAXLOC_NO_CACHE", raising=False)
    monkeypatch.setitem(compilation_cache._PROGRAMS, "folder", tmp_path / "cache")
    calls = {"export": [], "compile": 0, "options": []}
    export, compile_ = compilation_cache._export, compilation_cache._compile

    def counted_export(fn, leaves):
        calls["export"].append(len(leaves))
        return export(fn, leaves)

    def counted_compile(exported, leaves, options):
        calls["compile"] += 1
        calls["options"].append(options)
        return compile_(exported, leaves, options)

    monkeypatch.setattr(compilation_cache, "_export", counted_export)
    monkeypatch.setattr(compilation_cache, "_compile", counted_compile)
    capacity = query_capacity(len(query.points), config)
    triplet_map = open_triplet_map(folder, config, query_capacities=(capacity,))
    query_programs = [
        key
        for key, value in compilation_cache._PROGRAMS.items()
        if isinstance(key, tuple) and isinstance(value, Future)
    ]
    assert len(query_programs) == 2  # describe_query and register_query, handed to the thread
    legacy = compilation_cache.legacy_emitter_options()  # the query's, not describe_query's
    assert sorted((dict(key[2:]) for key in query_programs), key=len) == [{}, legacy]
    exports, compiles = len(calls["export"]), calls["compile"]
    result = localize_scan(triplet_map, None, query.points, query.labels)
    assert (len(calls["export"]), calls["compile"]) == (exports, compiles)  # none of its own
    assert calls["options"].count(legacy) == 1
    assert all(not isinstance(compilation_cache._PROGRAMS[k], Future) for k in query_programs)
    assert result.valid == expected.valid and expected.valid  # a query that localizes
    np.testing.assert_allclose(result.pose, expected.pose, atol=1e-4)
    np.testing.assert_array_equal(result.inliers, expected.inliers)


def test_only_the_query_programs_of_small_graphs_compile_with_the_legacy_emitters(world):
    """The legacy emitters compile the query program ~40 % faster where it runs as fast (up to
    LEGACY_EMITTERS_MAX_ASSOCIATIONS associations); M2Loc's three scales keep XLA's defaults."""
    from jaxloc import compilation_cache
    from jaxloc.m2loc import _localization
    from jaxloc.m2loc._map import triplet_map_spec

    legacy = compilation_cache.legacy_emitter_options()
    assert legacy == {compilation_cache.LEGACY_EMITTER_OPTION: False}  # CPU, a known jaxlib
    for scales, capacity, options in ((1, 32, legacy), (1, 64, {}), (2, 32, {}), (3, 32, {})):
        spec = triplet_map_spec(world.points, world.labels, m2loc_config(scales))  # top_k 25
        assert _localization._register_options(spec, capacity) == options, (scales, capacity)
    few = triplet_map_spec(world.points[:10], world.labels[:10], m2loc_config(3))
    assert _localization._register_options(few, 32) == legacy  # top_k clamped to 10 vertices
