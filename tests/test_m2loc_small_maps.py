"""Small maps (a user's first short recording) work with the default options: ``top_k`` (25) is
clamped to the vertex count with a warning from the API and a one-line note from the command
line, never an error. One 19-vertex map, localized through the API and through ``localize-lidar``
with the same configuration (one compilation for both)."""

from __future__ import annotations

import dataclasses
import json
import warnings

import numpy as np
import pytest

from jaxloc.cli import main
from jaxloc.io import load_triplet_map, save_triplet_map, write_instance_maps
from jaxloc.m2loc import (
    Instances,
    RoadNormals,
    SmallMapWarning,
    build_map,
    localization_errors,
    localize_scan,
    m2loc_config,
)
from jaxloc.synthetic.outdoor import make_outdoor_world, make_query

VERTICES = 19


@pytest.fixture(scope="module")
def small_world():
    """The 19 vertices of a dense world nearest one road cell (trunks and poles within ~18 m)
    and the road cells within 10 m."""
    world = make_outdoor_world("dense", seed=0, blocks=1, bridge_length=0)
    centre = world.road_normals.xy[len(world.road_normals.xy) // 2]
    keep = np.argsort(np.linalg.norm(world.points[:, :2] - centre, axis=1))[:VERTICES]
    near = np.linalg.norm(world.road_normals.xy - centre, axis=1) < 10.0
    rsn = world.road_normals
    normals = RoadNormals(rsn.xy[near], rsn.normals[near], rsn.std_deg[near])
    return world.points[keep], world.labels[keep], normals


@pytest.fixture(scope="module")
def queries(small_world):
    points, labels, normals = small_world
    rng = np.random.default_rng(1)
    return [
        make_query(points, labels, normals, rng, radius_range=(60.0, 60.0),
                   drop_range=(0.0, 0.2), jitter_range=(0.05, 0.15), spurious_range=(0.0, 0.1))
        for _ in range(3)
    ]  # fmt: skip


def test_build_map_clamps_top_k_with_a_warning(small_world, queries):
    points, labels, normals = small_world
    with pytest.warns(
        SmallMapWarning, match="top_k=25 exceeds the 19 map vertices; using top_k=19"
    ):
        small = build_map(points, labels, None, normals)
    assert small.config == dataclasses.replace(m2loc_config(3), top_k=VERTICES)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a config that fits: no warning
        build_map(points, labels, m2loc_config(3, top_k=VERTICES), normals)
    for query in queries:
        result = localize_scan(small, None, query.points, query.labels)
        rte, rre = localization_errors(result.pose, query.T_map_scan)
        assert result.valid and rte < 0.5 and rre < 2.0, (rte, rre)


def test_saved_map_with_a_large_top_k_loads_clamped(small_world, tmp_path):
    points, labels, normals = small_world
    small = build_map(points, labels, m2loc_config(3, top_k=VERTICES), normals)
    save_triplet_map(small, tmp_path / "m.npz")
    with np.load(tmp_path / "m.npz") as data:
        arrays = {key: data[key] for key in data.files}
    config = json.loads(str(arrays["config"]))
    config["top_k"] = 40  # as an older jaxloc could save it
    arrays["config"] = np.array(json.dumps(config))
    np.savez(tmp_path / "big_k.npz", **arrays)
    with pytest.warns(SmallMapWarning, match="top_k=40 exceeds the 19 map vertices"):
        loaded = load_triplet_map(tmp_path / "big_k.npz")
    assert loaded.config.top_k == VERTICES


def test_cli_localizes_in_a_19_vertex_map_with_a_note(small_world, queries, tmp_path, capsys):
    points, labels, normals = small_world
    write_instance_maps(tmp_path / "map", Instances(points, labels, np.ones(len(points))), normals)
    scans = []
    for index, query in enumerate(queries):
        rows = np.column_stack([query.labels, query.points])
        np.savetxt(tmp_path / f"q{index}.txt", rows, fmt="%d %.9f %.9f %.9f")
        scans.append(tmp_path / f"q{index}.txt")
    code = main(["localize-lidar", str(tmp_path / "map"), *map(str, scans), "--json"])
    out = capsys.readouterr()
    assert code == 0, out.err
    notes = [line for line in out.err.splitlines() if "note:" in line]
    assert len(notes) == 1 and notes[0].startswith("jaxloc localize-lidar: note: map ")
    assert notes[0].endswith("top_k=25 exceeds the 19 map vertices; using top_k=19")
    for record, query in zip(json.loads(out.out)["scans"], queries, strict=True):
        rte, rre = localization_errors(np.array(record["T_map_scan"]), query.T_map_scan)
        assert record["valid"] and rte < 0.5 and rre < 2.0, (rte, rre)
    # a saved map asked for more matches than it holds: clamped too, with a note
    save_triplet_map(build_map(points, labels, m2loc_config(3, top_k=VERTICES), normals),
                     tmp_path / "m.npz")  # fmt: skip
    code = main(["localize-lidar", str(tmp_path / "m.npz"), str(scans[0]), "-k", "50", "--json"])
    out = capsys.readouterr()
    assert code == 0, out.err
    assert "note: map " in out.err and "top_k=50 exceeds the 19 map vertices" in out.err
    assert json.loads(out.out)["scans"][0]["valid"]
