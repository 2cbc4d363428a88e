"""Synthetic worlds and loaders: :mod:`jaxloc.datasets.indoor` (SG2Loc rooms and query sequences),
:mod:`jaxloc.datasets.outdoor` (M2Loc semantic instance maps and LiDAR queries), and real camera
data: :mod:`jaxloc.datasets.reconstruction` (ScanNet / 3RScan / generic labelled scans),
:mod:`jaxloc.datasets.scene_builder` (their scene graphs) and
:mod:`jaxloc.datasets.camera_folder` (query sequences from a ScanNet-export folder)."""
