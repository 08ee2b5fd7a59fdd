"""The browser app end to end in headless Chromium: time from upload to the drawn 3D view for two
photos and for a 10-second video, and the page's screenshots for docs/app.md.

    python benchmarks/app.py --screenshots docs/images/app --json app_timing.json

The video is made here from the LLFF fern photos of tests/data (each held for 40 frames at 24 fps:
10 s, six viewpoints, the rest near-duplicates that frame selection drops). The app runs with its
defaults (working size 256, the library's refinement, the full export) unless told otherwise.
"""

from __future__ import annotations

import argparse
import io
import json
import socket
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
FERN = ROOT / "tests" / "data" / "llff_fern" / "images_16"


def make_video(path: Path, seconds: float = 10.0, fps: int = 24) -> Path:
    import imageio.v2 as imageio

    photos = [imageio.imread(p)[..., :3] for p in sorted(FERN.glob("*.png"))]
    h, w = (s // 2 * 2 for s in photos[0].shape[:2])  # H.264 wants even sizes
    hold = round(seconds * fps / len(photos))
    frames = [p[:h, :w] for p in photos for _ in range(hold)]
    imageio.mimwrite(path, frames, fps=fps, codec="libx264", macro_block_size=1)  # imageio-ffmpeg
    return path


def save_small(png: bytes, path: Path) -> None:
    """A screenshot as an optimised palette PNG (a few hundred KB at most)."""
    from PIL import Image

    image = Image.open(io.BytesIO(png)).convert("RGB").quantize(colors=256, method=Image.Quantize.MEDIANCUT)
    path.parent.mkdir(parents=True, exist_ok=True)
    image.save(path, optimize=True)


def canvas_drawn(page, timeout: float = 120.0) -> bool:
    canvas = page.locator("#view3d canvas").first
    canvas.wait_for(timeout=timeout * 1000)
    deadline = time.monotonic() + timeout
    from PIL import Image

    while time.monotonic() < deadline:
        shot = np.asarray(Image.open(io.BytesIO(canvas.screenshot())).convert("RGB"))
        if shot.reshape(-1, 3).std(0).max() > 10:
            return True
        time.sleep(0.5)
    return False


def run_one(page, url: str, files: list[Path], shots: Path | None, tag: str) -> float:
    page.goto(url, timeout=60_000)
    page.locator("#start").wait_for(timeout=60_000)
    if shots is not None and tag == "photos":
        save_small(page.screenshot(), shots / "empty.png")
    tick = time.perf_counter()
    page.locator("#photos input[type=file]").set_input_files([str(f) for f in files])
    page.locator(f"#photos td.filename[aria-label='{files[-1].name}']").wait_for(timeout=60_000)
    page.locator("#start").click()
    if shots is not None and tag == "photos":
        time.sleep(8)  # into the run: the progress bar over the results
        save_small(page.screenshot(), shots / "running.png")
    page.locator("#status").get_by_text("Done.").wait_for(timeout=1_200_000)
    if not canvas_drawn(page):
        raise RuntimeError(f"{tag}: the 3D view stayed blank")
    seconds = time.perf_counter() - tick
    if shots is not None:
        time.sleep(2)
        save_small(page.screenshot(), shots / f"result_{tag}.png")
    return seconds


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--screenshots", type=Path, default=None, help="folder for the page's screenshots")
    parser.add_argument("--json", type=Path, default=None, help="write the timings here")
    parser.add_argument("--working-size", type=int, default=256)
    parser.add_argument("--chromium", default="/usr/bin/chromium")
    args = parser.parse_args()

    from playwright.sync_api import sync_playwright

    from surfsplat.app import AppConfig, build

    work = Path(tempfile.mkdtemp(prefix="surfsplat-app-bench-"))
    video = make_video(work / "fern_10s.mp4")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    config = AppConfig(port=port, working_size=args.working_size, sessions_dir=str(work / "sessions"))
    demo = build(config)
    demo.launch(server_name=config.host, server_port=port, prevent_thread_lock=True, ssr_mode=False, quiet=True)
    timings = {}
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(
                executable_path=args.chromium,
                args=["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"],
            )
            page = browser.new_page(viewport={"width": 1280, "height": 900})
            photos = [FERN / "IMG_4026.png", FERN / "IMG_4027.png"]
            timings["two photos"] = run_one(page, demo.local_url, photos, args.screenshots, "photos")
            print(f"two photos: {timings['two photos']:.1f} s from upload to the 3D view", flush=True)
            timings["10-second video"] = run_one(page, demo.local_url, [video], args.screenshots, "video")
            print(f"10-second video: {timings['10-second video']:.1f} s from upload to the 3D view", flush=True)
            if args.screenshots is not None:
                broken = work / "IMG_9999.png"
                broken.write_bytes(b"not a PNG")
                page.goto(demo.local_url)
                page.locator("#photos input[type=file]").set_input_files([str(photos[0]), str(broken)])
                page.locator("#photos td.filename[aria-label='IMG_9999.png']").wait_for(timeout=60_000)
                page.locator("#start").click()
                page.locator("#status").get_by_text("Cannot reconstruct").wait_for(timeout=120_000)
                save_small(page.screenshot(), args.screenshots / "error.png")
            browser.close()
    finally:
        demo.close()
    timings["working size"] = args.working_size
    if args.json is not None:
        args.json.write_text(json.dumps(timings, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
