"""Synthetic worlds and loaders: :mod:`jaxloc.datasets.indoor` (SG2Loc rooms and query sequences)
and :mod:`jaxloc.datasets.outdoor` (M2Loc semantic instance maps and LiDAR queries)."""
