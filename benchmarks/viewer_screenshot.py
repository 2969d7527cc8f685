"""Open a recording in the native Rerun viewer on a virtual display and save what a reviewer sees.

    python benchmarks/viewer_screenshot.py RECORDING.rrd OUT.png [--size 1600x1000] [--wait 25]

Needs Xvfb, ImageMagick's ``import`` and Mesa's Vulkan driver (Debian: ``apt-get install xvfb imagemagick
mesa-vulkan-drivers``), and ``ffmpeg`` for the viewer to decode H.264 video.  The viewer draws with wgpu on
Mesa's software Vulkan driver (lavapipe): its GL path on llvmpipe crashes, and the X Composite extension is
switched off, which lavapipe's presentation does not survive.  Prints the share of the screenshot's pixels
that are not the viewer's background, so a caller can tell an empty window from a drawn report.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np


def free_display() -> int:
    for n in range(90, 140):
        if not Path(f"/tmp/.X11-unix/X{n}").exists() and not Path(f"/tmp/.X{n}-lock").exists():
            return n
    raise SystemExit("no free X display number between :90 and :139")


def screenshot(rrd: Path, out: Path, size: str = "1600x1000", wait: float = 25.0) -> float:
    """Save the viewer's window on ``rrd`` as ``out``; returns the share of non-background pixels."""
    for tool in ("Xvfb", "import"):
        if shutil.which(tool) is None:
            raise SystemExit(f"{tool} not found: apt-get install xvfb imagemagick mesa-vulkan-drivers")
    viewer = shutil.which("rerun") or str(Path(sys.executable).with_name("rerun"))
    display = f":{free_display()}"
    xvfb = subprocess.Popen(["Xvfb", display, "-screen", "0", f"{size}x24", "-extension", "Composite", "-nolisten",
                             "tcp"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    env = {**os.environ, "DISPLAY": display, "WGPU_BACKEND": "vulkan", "WAYLAND_DISPLAY": ""}
    icd = Path("/usr/share/vulkan/icd.d/lvp_icd.x86_64.json")
    if icd.exists():
        env["VK_ICD_FILENAMES"] = str(icd)
    try:
        time.sleep(1.5)
        width, height = size.split("x")
        app = subprocess.Popen([viewer, str(rrd), "--window-size", f"{width}x{height}"], env=env,
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            time.sleep(wait)
            if app.poll() is not None:
                raise SystemExit(f"the viewer exited with status {app.returncode} before the screenshot")
            out.parent.mkdir(parents=True, exist_ok=True)
            subprocess.run(["import", "-display", display, "-window", "root", str(out)], check=True, env=env)
        finally:
            app.terminate()
            try:
                app.wait(10)
            except subprocess.TimeoutExpired:
                app.kill()
    finally:
        xvfb.terminate()
        xvfb.wait(10)
    return drawn_share(out)


def drawn_share(png: Path) -> float:
    """Share of pixels that differ from the image's most common colour (the background)."""
    import cv2

    img = cv2.imread(str(png))
    flat = img.reshape(-1, 3)
    colours, counts = np.unique(flat, axis=0, return_counts=True)
    background = colours[np.argmax(counts)]
    return float((np.abs(flat.astype(int) - background).sum(1) > 30).mean())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("rrd", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--size", default="1600x1000")
    ap.add_argument("--wait", type=float, default=25.0, help="seconds to let the viewer load and draw")
    args = ap.parse_args()
    share = screenshot(args.rrd, args.out, args.size, args.wait)
    print(f"{args.out}: {100 * share:.1f}% of the pixels drawn")


if __name__ == "__main__":
    main()
