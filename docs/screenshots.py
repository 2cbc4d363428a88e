"""The Rerun screenshots of the docs (docs/pages/images/rerun_*.png), taken in the Rerun web viewer
in headless Chromium: a synthetic drive recorded as a ROS 2 MCAP bag and localized by
``jaxloc localize-lidar``, and the SG2Loc demo, each written with ``--rerun``.

Needs what the docs do not: Chromium (Debian's ``chromium``) and Playwright (``pip install
playwright``; it drives the system Chromium, no browser download). Run from the repository root:

    python docs/screenshots.py [--out docs/pages/images]

The bag is written with the tests' ROS helpers (``tests/_rosbag_fixtures.py``).
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
CHROMIUM = "/usr/bin/chromium"
FIRST_STAMP = 1_700_000_000_000_000_000  # ns
VIEWPORT = {"width": 1600, "height": 1000}


def jaxloc(*args) -> None:
    subprocess.run([Path(sys.executable).with_name("jaxloc"), *map(str, args)], check=True)


def drive_recording(folder: Path) -> Path:
    """A 10-scan drive through a synthetic city block, as a ROS 2 MCAP bag, localized with
    ``--accumulate 3`` against the block's map; returns the ``.rrd``."""
    sys.path.insert(0, str(REPO / "tests"))
    from _helipr_fixtures import tum_line
    from _rosbag_fixtures import write_drive

    from jaxloc import io, m2loc
    from jaxloc.io.poses import format_ns_as_seconds
    from jaxloc.synthetic.lidar_scans import make_lidar_sequence
    from jaxloc.synthetic.outdoor import make_outdoor_world

    world = make_outdoor_world("dense", seed=0, blocks=1, bridge_length=0)
    triplet_map = m2loc.build_map(world.points, world.labels, m2loc.m2loc_config(3),
                                  world.road_normals)  # fmt: skip
    io.save_triplet_map(triplet_map, folder / "block.npz")
    scans = make_lidar_sequence(world, (60.0, 0.0), (150.0, 0.0), num_scans=10)
    stamps = [FIRST_STAMP + 100_000_000 * i for i in range(len(scans.points))]
    write_drive(folder / "drive.mcap", "mcap", scans, stamps)
    poses = zip(stamps, scans.T_map_scan, strict=True)
    lines = [tum_line(format_ns_as_seconds(t), p) for t, p in poses]
    (folder / "gt.tum").write_text("\n".join(lines) + "\n")
    jaxloc("localize-lidar", folder / "block.npz", folder / "drive.mcap", "--accumulate", 3,
           "--gt", folder / "gt.tum", "--poses-out", folder / "est.mcap",
           "--rerun", folder / "drive.rrd")  # fmt: skip
    return folder / "drive.rrd"


def demo_recording(folder: Path) -> Path:
    """The SG2Loc demo at 320x180 and 1,000 particles; returns the ``.rrd``."""
    jaxloc("demo", "--width", 320, "--height", 180, "--particles", 1000, "--strides", "10,6,4",
           "--out", folder / "demo.png", "--rerun", folder / "demo.rrd")  # fmt: skip
    return folder / "demo.rrd"


def screenshot(rrd: Path, out: Path, wait_s: float = 30.0) -> None:
    """Serve ``rrd`` to the Rerun web viewer and save what headless Chromium shows."""
    from playwright.sync_api import sync_playwright

    rerun = Path(sys.executable).with_name("rerun")
    server = subprocess.Popen([rerun, "--serve-web", "--renderer", "webgl", rrd],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                              start_new_session=True)  # fmt: skip
    try:
        time.sleep(5)
        flags = ["--no-sandbox", "--no-first-run", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", "--disable-quic",
                 "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]  # fmt: skip
        with sync_playwright() as playwright:
            browser = playwright.chromium.launch(executable_path=CHROMIUM, args=flags)
            page = browser.new_page(viewport=VIEWPORT)
            page.goto("http://127.0.0.1:9090/?url=rerun%2Bhttp%3A%2F%2Flocalhost%3A9876%2Fproxy")
            time.sleep(wait_s)  # the viewer streams the recording and renders in software
            page.screenshot(path=str(out))
            browser.close()
    finally:  # the entry point starts the viewer's binary: stop the whole process group
        os.killpg(server.pid, signal.SIGTERM)
        server.wait()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=REPO / "docs" / "pages" / "images")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        screenshot(drive_recording(folder), args.out / "rerun_drive.png")
        screenshot(demo_recording(folder), args.out / "rerun_demo.png")
    print(f"wrote {args.out / 'rerun_drive.png'} and {args.out / 'rerun_demo.png'}")


if __name__ == "__main__":
    main()
