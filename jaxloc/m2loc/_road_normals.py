"""Road-surface-normal (RSN) cells: the roll/pitch prior of M2Loc's pose estimate."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


class RoadNormals(NamedTuple):
    """Road-surface-normal (RSN) cells: ``xy`` (M, 2) cell centres (map frame, metres),
    ``normals`` (M, 3) unit normals, ``std_deg`` (M,) normal standard deviation in degrees."""

    xy: np.ndarray
    normals: np.ndarray
    std_deg: np.ndarray
