"""``localize-lidar --json`` records against ``jaxloc.m2loc.localize_drive``'s result: the command
line is a shell around the library, so both must give the same flags, poses, cliques, fused
windows and tracking states."""

from __future__ import annotations

import contextlib
import io
import json

import numpy as np

from jaxloc.cli import main
from jaxloc.m2loc._drive import STATUS_NAMES


def cli_json(argv) -> list[dict]:
    """The per-scan records ``jaxloc <argv> --json`` prints (the command must succeed)."""
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        code = main([str(a) for a in argv])
    assert code == 0
    return json.loads(printed.getvalue())["scans"]


def assert_same(records: list[dict], result, track: bool) -> None:
    """The CLI's records and the library's result: flags, poses (within the JSON's rounding to
    1e-6), clique sizes, fused windows and tracking states."""
    assert len(records) == len(result.steps)
    for record, step, pose in zip(records, result.steps, result.poses, strict=True):
        assert record["valid"] == bool(step.result.valid)
        np.testing.assert_allclose(record["T_map_scan"], pose, atol=1e-6, rtol=0)
        assert record["clique_size"] == step.result.clique_size
        fused = 1 if step.fused is None else step.fused.members.shape[1]
        assert record.get("fused_scans", 1) == fused
        assert record.get("small_clique", False) == step.small_clique
        assert record.get("track") == (STATUS_NAMES[step.status] if track else None)
