"""``jaxloc build-scene-graph``: a map (``save_scene`` .npz) from a ScanNet, 3RScan or generic
labelled reconstruction."""

from __future__ import annotations

import argparse
from pathlib import Path

from jaxloc.cli._errors import InputError
from jaxloc.cli._options import at_least

DESCRIPTION = """\
Build a scene graph (one coarse mesh, class, colour and embedding per object; the floor and the
walls too) from a labelled reconstruction and save it with jaxloc.save_scene.

--format scannet   SCAN is a ScanNet v2 scan folder <scene>/ with
                     <scene>_vh_clean_2.ply                   mesh with vertex colours
                     <scene>_vh_clean_2.0.010000.segs.json    segIndices per vertex
                     <scene>.aggregation.json                 segGroups: objects, labels, segments
                   and scannetv2-labels.combined.tsv in SCAN, its parent, or --label-table.
--format 3rscan    SCAN is a 3RScan scan folder with labels.instances.annotated.v2.ply (per-vertex
                   objectId, NYU40) and semseg.v2.json.
--format generic   SCAN is a PLY mesh or point cloud with a per-vertex instance id (objectId,
                   instance or instance_id) and --objects FILE lists "object_id class_id [label]".

Each object's mesh is reduced by quadric decimation to about --target-vertices vertices (a point
cloud's objects become their convex hulls). Embeddings: --embeddings FILE, text lines
"key e_1 ... e_d" (key = label name or class id, or object id with --embeddings-by object) or a
.npy (K, d) indexed by class id / object id; without it, one-hot per class (dimension i = the i-th
smallest class id, listed in the output). The map also stores one embedding per class (one-hot,
or the mean of the class's objects' vectors with a table by label), the space that query patch
embeddings made from label images live in (localize-camera --labels).
"""

EPILOG = """\
examples:
  jaxloc build-scene-graph scans/scene0000_00 scene0000_00.npz --format scannet
  jaxloc build-scene-graph 3RScan/<scan_id> room.npz --format 3rscan --embeddings clip.txt
  jaxloc build-scene-graph cloud.ply room.npz --format generic --objects objects.txt

exit status: 0 on success, 2 on missing or malformed files (one-line message; nothing written).
"""


def add_parser(commands) -> None:
    """Register ``build-scene-graph`` on the ``jaxloc`` subcommand parsers."""
    parser = commands.add_parser(
        "build-scene-graph",
        help="build a map from a ScanNet / 3RScan / labelled reconstruction",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("scan", type=Path, metavar="SCAN", help="scan folder (or PLY: generic)")
    parser.add_argument("out", type=Path, metavar="OUT.npz", help="the map file to write")
    parser.add_argument("--format", required=True, choices=("scannet", "3rscan", "generic"))
    parser.add_argument("--objects", type=Path, help="generic: 'object_id class_id [label]' file")
    parser.add_argument("--instance-property", help="generic: the per-vertex instance property")
    parser.add_argument("--label-table", type=Path, help="scannet: scannetv2-labels.combined.tsv")
    parser.add_argument(
        "--label-column", default="nyu40id", help="scannet: class-id column (default nyu40id)"
    )
    parser.add_argument("--embeddings", type=Path, help="embedding table (.txt or .npy)")
    parser.add_argument(
        "--embeddings-by", choices=("label", "object"), default="label", help="table keys"
    )
    parser.add_argument(
        "--target-vertices",
        type=at_least(4),
        default=860,
        help="vertices per object, >= 4 (default 860)",
    )


def run_build_scene_graph(args: argparse.Namespace) -> int:
    import numpy as np

    from jaxloc.io import (
        read_3rscan,
        read_embedding_table,
        read_labelled_ply,
        read_scannet,
        save_scene,
    )
    from jaxloc.mapping import class_embeddings, onehot_classes, scene_graph_from_reconstruction

    try:
        if args.format == "scannet":
            recon = read_scannet(args.scan, args.label_table, args.label_column)
        elif args.format == "3rscan":
            recon = read_3rscan(args.scan)
        else:
            if args.objects is None:
                raise InputError("--format generic needs --objects FILE")
            recon = read_labelled_ply(args.scan, args.objects, args.instance_property)
        table = None
        if args.embeddings is not None:
            table = read_embedding_table(args.embeddings, args.embeddings_by)
        scene = scene_graph_from_reconstruction(recon, table, args.target_vertices)
        classes = class_embeddings(recon, table)
    except ValueError as error:
        raise InputError(str(error)) from None
    save_scene(scene, args.out, classes)
    labels = np.asarray(scene.labels)[: scene.num_objects]
    print(
        f"{scene.num_objects} objects ({len(np.unique(labels))} classes), "
        f"{scene.num_triangles} triangles, {scene.storage_mb():.3f} MB -> {args.out}"
    )
    if table is None:
        classes = " ".join(str(c) for c in onehot_classes(labels))
        print(f"embeddings: one-hot per class, dimension i = class id {classes}")
    else:
        print(f"embeddings: {scene.embeddings.shape[1]}-d from {args.embeddings}")
    if classes is None:
        print("no class embeddings (a table by object): label images cannot be used as queries")
    return 0
