"""Synthetic worlds, seeded and deterministic, for tests, demos and experiments.

* :mod:`~jaxloc.synthetic.indoor`: SG2Loc rooms (textured furniture, object embeddings, scene
  changes), camera trajectories and noisy query episodes.
* :mod:`~jaxloc.synthetic.outdoor`: M2Loc instance maps (roads, poles, trunks, signs, road
  normals) and scan-like queries cut from them.
* :mod:`~jaxloc.synthetic.lidar_scans`: labelled LiDAR scans of an outdoor world, written in the
  SemanticKITTI layout.
* :mod:`~jaxloc.synthetic.timing`: speed checks of raycasting, the SG2Loc filter and M2Loc
  queries on these worlds (what ``jaxloc bench`` prints).
"""
