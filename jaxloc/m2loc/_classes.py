"""The semantic classes M2Loc / TripletLoc build graphs from (TripletLoc / Cylinder3D ids:
SemanticKITTI learning ids minus one)."""

from __future__ import annotations

TRUNK, POLE, TRAFFIC_SIGN = 15, 17, 18
#: The classes TripletLoc/M2Loc build graphs from.
GRAPH_CLASSES: tuple[int, ...] = (TRUNK, POLE, TRAFFIC_SIGN)
