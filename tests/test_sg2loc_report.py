"""The text of a camera localization report (:func:`jaxloc.sg2loc._report.format_report`)."""

from __future__ import annotations

import numpy as np

from jaxloc.sg2loc._report import format_report


def test_format_report_has_a_line_per_frame_and_the_refinement():
    report = {
        "frames": [0, 10],
        "poses": [[1.0, 2.0, 1.3, np.pi / 2], [1.5, 2.0, 1.3, 0.0]],
        "localized": [False, True],
        "position_error_m": [0.5, 0.05],
        "rotation_error_deg": [3.0, 1.0],
        "last_frame": {"median_pos_m": 0.05},
        "refined": {"ok": True, "status": 0, "T_world_cam": np.eye(4).tolist()},
        "figure": "run.png",
    }
    lines = format_report(report).splitlines()
    assert lines[0] == (
        "frame 0: NOT localized, x 1.000 y 2.000 z 1.300 m, yaw 90.0 deg | error 0.500 m, 3.00 deg"
    )
    assert lines[1].startswith("frame 10: localized") and "error 0.050 m, 1.00 deg" in lines[1]
    assert "localized: 1 of 2 frames" in lines
    assert "last frame: median_pos_m 0.050" in lines
    assert "refined last frame: ok True (status 0)" in lines and "T_world_cam =" in lines
    assert lines[-1] == "figure: run.png"
