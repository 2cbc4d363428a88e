"""``jaxloc build-scene-graph``: a map (``save_scene`` .npz) from a ScanNet, 3RScan or generic
labelled reconstruction."""

from __future__ import annotations

import argparse
from pathlib import Path

from jaxloc.cli._errors import InputError, reading
from jaxloc.cli._options import at_least, command, given

DESCRIPTION = """\
Build a map (a scene graph) from a ScanNet / 3RScan / labelled reconstruction.

--format scannet   SCAN is a ScanNet v2 scan folder <scene>/ (<scene>_vh_clean_2.ply,
                   _vh_clean_2.0.010000.segs.json, .aggregation.json) with
                   scannetv2-labels.combined.tsv in SCAN, its parent, or --label-table
--format 3rscan    SCAN is a 3RScan scan folder (labels.instances.annotated.v2.ply, semseg.v2.json)
--format generic   SCAN is a PLY mesh or point cloud with a per-vertex instance id (objectId,
                   instance or instance_id); --objects FILE lists "object_id class_id [label]"

Each object (the floor and walls too) gets a mesh decimated to about --target-vertices vertices
(a point cloud's: convex hulls), a class, a colour and an embedding: --embeddings FILE, lines
"key e_1 ... e_d" (label name or class id; object id with --embeddings-by object) or a .npy (K, d),
else one-hot per class (printed). Class embeddings are what label images become (localize-camera).
"""

EPILOG = """\
examples:
  jaxloc build-scene-graph scans/scene0000_00 scene0000_00.npz --format scannet
  jaxloc build-scene-graph 3RScan/<scan_id> room.npz --format 3rscan --embeddings clip.txt
  jaxloc build-scene-graph cloud.ply room.npz --format generic --objects objects.txt
"""


def add_parser(commands) -> None:
    """Register ``build-scene-graph`` on the ``jaxloc`` subcommand parsers."""
    parser = command(commands, "build-scene-graph", DESCRIPTION, EPILOG)
    add = parser.add_argument
    add("scan", type=Path, metavar="SCAN", help="scan folder (or PLY: generic)")
    add("out", type=Path, metavar="OUT.npz", help="the map file to write")
    add("--format", required=True, choices=("scannet", "3rscan", "generic"))
    add("--objects", type=Path, help="generic: 'object_id class_id [label]' file")
    add("--instance-property", help="generic: the per-vertex instance property")
    add("--label-table", type=Path, help="scannet: scannetv2-labels.combined.tsv")
    add("--label-column", help="scannet: class-id column (default nyu40id)")
    add("--embeddings", type=Path, help="embedding table (.txt or .npy)")
    add("--embeddings-by", choices=("label", "object"), help="table keys (default label)")
    target = "vertices per object, >= 4 (default jaxloc.mapping's DEFAULT_TARGET_VERTICES)"
    add("--target-vertices", type=at_least(4), help=target)


def run_build_scene_graph(args: argparse.Namespace) -> int:
    import numpy as np

    from jaxloc import io
    from jaxloc.mapping import class_embeddings, onehot_classes, scene_graph_from_reconstruction

    if args.format == "generic" and args.objects is None:
        raise InputError("--format generic needs --objects FILE")
    with reading():
        if args.format == "scannet":
            column = given(label_column=args.label_column)
            recon = io.read_scannet(args.scan, args.label_table, **column)
        elif args.format == "3rscan":
            recon = io.read_3rscan(args.scan)
        else:
            recon = io.read_labelled_ply(args.scan, args.objects, args.instance_property)
        table = None
        if args.embeddings is not None:
            table = io.read_embedding_table(args.embeddings, **given(by=args.embeddings_by))
        vertices = given(target_vertices=args.target_vertices)
        scene = scene_graph_from_reconstruction(recon, table, **vertices)
        classes = class_embeddings(recon, table)
    io.save_scene(scene, args.out, classes)
    labels = np.asarray(scene.labels)[: scene.num_objects]
    print(
        f"{scene.num_objects} objects ({len(np.unique(labels))} classes), "
        f"{scene.num_triangles} triangles, {scene.storage_mb():.3f} MB -> "
        f"{args.out}"
    )
    if table is None:
        classes = " ".join(str(c) for c in onehot_classes(labels))
        print(f"embeddings: one-hot per class, dimension i = class id {classes}")
    else:
        print(f"embeddings: {scene.embeddings.shape[1]}-d from {args.embeddings}")
    if classes is None:
        print("no class embeddings (a table by object): label images cannot be used as queries")
    return 0
