"""A drive through files, in Python and on the command line: the same results.

On the held-out drives of ``m2loc_drives.py`` (``--seed 7000``, 20 drives of 10 scans per real
map, at most 11 kept map vertices per scan, odometry noise 0.05 m / 0.5 deg rms per scan), each
drive is written to disk as a recording: one centroid file per scan (``class_id x y z``), a
ground-truth file and an odometry file (KITTI lines). Then, per drive,

* Python: ``jaxloc.io.open_lidar_recording(files, gt=...)`` and
  ``jaxloc.m2loc.localize_drive(map, recording.with_poses(odometry), accumulate=3)``;
* the command line: ``jaxloc localize-lidar MAP.npz FILES --gt ... --odometry ... --accumulate 3
  --json`` (in-process, ``jaxloc.cli.main``),

both on the map described once and saved (``open_triplet_map`` of the map folder). Reported per
map: scans whose valid flags differ, the largest difference of the poses (translation, metres, and
any matrix entry; the command line rounds to 1e-6), the success on each drive's last scan (valid,
RTE < 7.5 m, RRE < 10 deg, as ``m2loc_drives.py`` judges) and the wrong valid poses over every
scan of every drive.

    JAX_PLATFORMS=cpu python experiments/m2loc_drive_api.py
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
import tempfile
from pathlib import Path

import m2loc_drives as drives
import numpy as np
from _atomic import write_text_atomic

from jaxloc.cli import main as cli_main
from jaxloc.io import open_lidar_recording, open_triplet_map, save_triplet_map
from jaxloc.m2loc import localize_drive


def write_drive(folder: Path, drive, chain) -> tuple[list[Path], Path, Path]:
    """The drive's scans as centroid files, its true poses and odometry as KITTI files."""
    folder.mkdir(parents=True)
    paths = []
    for i, scan in enumerate(drive):
        paths.append(folder / f"{i:03d}.txt")
        rows = np.column_stack([scan.labels, scan.points])
        np.savetxt(paths[-1], rows, fmt=["%d", "%.9f", "%.9f", "%.9f"])
    gt, odometry = folder / "gt.txt", folder / "odometry.txt"
    truth = np.stack([scan.T_map_scan for scan in drive])
    np.savetxt(gt, truth[:, :3].reshape(-1, 12), fmt="%.17g")
    np.savetxt(odometry, np.asarray(chain)[:, :3].reshape(-1, 12), fmt="%.17g")
    return paths, gt, odometry


def command_line(saved: Path, paths, gt: Path, odometry: Path) -> list[dict]:
    argv = ["localize-lidar", saved, *paths, "--gt", gt, "--odometry", odometry]
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        code = cli_main([str(a) for a in [*argv, "--accumulate", "3", "--json", "--no-progress"]])
    if code != 0:
        raise SystemExit(f"localize-lidar exited {code}")
    return json.loads(printed.getvalue())["scans"]


def row_of_map(name: str, folder: Path, args: argparse.Namespace, work: Path) -> dict:
    all_maps = list(drives.maps())
    _, by_map, chains = drives.own_and_foreign_drives(
        all_maps, name, args.seed, args.drives, args.length, args.max_kept, (0.05, 0.5)
    )
    saved = work / f"{name}.npz"
    save_triplet_map(open_triplet_map(folder), saved)
    triplet_map = open_triplet_map(saved)
    flags_differ, translation, entry, last, wrong, scans = 0, 0.0, 0.0, [], 0, 0
    for d, (drive, chain) in enumerate(zip(by_map[name], chains[name], strict=True)):
        paths, gt, odometry = write_drive(work / name / f"drive{d:02d}", drive, chain)
        recording = open_lidar_recording(paths, gt=gt)
        result = localize_drive(triplet_map, recording.with_poses(odometry), accumulate=3)
        records = command_line(saved, paths, gt, odometry)
        for record, pose, valid in zip(records, result.poses, result.valid, strict=True):
            flags_differ += record["valid"] != bool(valid)
            gap = np.abs(np.asarray(record["T_map_scan"]) - pose)
            translation = max(translation, float(np.linalg.norm(gap[:3, 3])))
            entry = max(entry, float(gap.max()))
        judged = [
            drives.judge(pose, bool(valid), scan.T_map_scan)
            for pose, valid, scan in zip(result.poses, result.valid, drive, strict=True)
        ]
        last.append(judged[-1][0])
        wrong += sum(w for _, w, *_ in judged)
        scans += len(judged)
        print(name, d, [int(r["valid"]) for r in records], file=sys.stderr, flush=True)
    return {
        "map": name,
        "drives": len(last),
        "scans": scans,
        "flags_differ": flags_differ,
        "max_translation_gap_m": translation,
        "max_entry_gap": entry,
        "last_scan_success": float(np.mean(last)),
        "wrong_valid_poses": wrong,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seed", type=int, default=7000)
    parser.add_argument("--drives", type=int, default=20)
    parser.add_argument("--length", type=int, default=10)
    parser.add_argument("--max-kept", type=int, default=11)
    parser.add_argument("--maps", nargs="+", help="only these real maps (default: all)")
    parser.add_argument("--out", type=Path, default=drives.OUT / "drive_api.md")
    args = parser.parse_args()
    real = sorted(p for p in drives.DATA.iterdir() if p.is_dir()) if drives.DATA.exists() else []
    real = [p for p in real if args.maps is None or p.name in args.maps]
    if not real:
        raise SystemExit(f"no real maps in {drives.DATA}")
    with tempfile.TemporaryDirectory() as work:
        rows = [row_of_map(p.name, p, args, Path(work)) for p in real]
    lines = [
        f"# A drive through files: Python and the command line ({args.drives} drives of "
        f"{args.length} scans per map, seed {args.seed}, at most {args.max_kept} kept map "
        "vertices per scan, odometry noise 0.05 m / 0.5 deg rms per scan, --accumulate 3)",
        "",
        f"Command: `JAX_PLATFORMS=cpu python experiments/m2loc_drive_api.py --seed {args.seed} "
        f"--drives {args.drives} --length {args.length} --max-kept {args.max_kept}"
        + (f" --maps {' '.join(args.maps)}" if args.maps else "")
        + "`",
        "",
        "Python: `open_lidar_recording(files, gt=...)` + `localize_drive(map, "
        "recording.with_poses(odometry), accumulate=3)`; command line: `localize-lidar MAP.npz "
        "FILES --gt ... --odometry ... --accumulate 3 --json`. Gaps: the largest over every scan "
        "(the JSON rounds poses to 1e-6). Success: each drive's last scan valid, RTE < 7.5 m, "
        "RRE < 10 deg; wrong: valid poses beyond those bounds at any scan.",
        "",
        "| map | drives | scans | flags that differ | max translation gap (m) | max matrix entry "
        "gap | success (last scan) | wrong valid poses (every scan) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['map']} | {r['drives']} | {r['scans']} | {r['flags_differ']} | "
            f"{r['max_translation_gap_m']:.1e} | {r['max_entry_gap']:.1e} | "
            f"{r['last_scan_success']:.2f} | {r['wrong_valid_poses']} |"
        )
    write_text_atomic(args.out, "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
