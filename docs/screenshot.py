"""A screenshot of a recording as the grower sees it: rerun's web viewer, in headless Chromium with software WebGL.

    python docs/screenshot.py out/demo/flight.rrd --out docs/images/viewer.jpg

Needs Chromium (Debian: ``apt-get install chromium``) and Playwright's Python package (``pip install playwright``;
no browser download: it drives the system's Chromium). The viewer is served by ``rerun --serve-web`` on loopback;
both processes are stopped before the script exits. Regenerate the README's picture whenever the view changes.
Map tiles need the internet: offline, the map panel shows the apples and rows on a blank background.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

log = logging.getLogger("screenshot")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def screenshot(rrd: Path, out: Path, width: int = 1600, height: int = 900, wait_s: float = 60.0,
               chromium: str = "/usr/bin/chromium") -> Path:
    from playwright.sync_api import sync_playwright

    if not Path(rrd).is_file():
        raise FileNotFoundError(f"{rrd}: no such recording")
    web, grpc = free_port(), free_port()
    viewer = subprocess.Popen([sys.executable, "-m", "rerun", "--serve-web", "--bind", "127.0.0.1", "--web-viewer-port",
                               str(web), "--port", str(grpc), str(rrd)],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        time.sleep(3.0)
        if viewer.poll() is not None:
            raise RuntimeError(f"rerun --serve-web exited with {viewer.returncode}")
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=chromium, args=[
                "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist",
                "--disable-background-networking", "--disable-component-update", "--disable-sync"])
            try:
                page = browser.new_page(viewport={"width": width, "height": height})
                page.goto(f"http://127.0.0.1:{web}/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A{grpc}%2Fproxy")
                t0 = time.monotonic()
                while time.monotonic() - t0 < wait_s:  # the recording streams in, then the viewer settles on its end
                    time.sleep(5.0)
                    log.info("waiting for the viewer: %.0f of %.0f s", time.monotonic() - t0, wait_s)
                out.parent.mkdir(parents=True, exist_ok=True)
                if out.suffix.lower() in (".jpg", ".jpeg"):  # a quarter of the PNG's size, for the README
                    page.screenshot(path=str(out), type="jpeg", quality=85)
                else:
                    page.screenshot(path=str(out))
            finally:
                browser.close()
    finally:
        # `python -m rerun` runs the viewer binary as its child: stop the whole process group the wrapper leads
        os.killpg(viewer.pid, signal.SIGTERM)
        try:
            viewer.wait(10)
        except subprocess.TimeoutExpired:
            os.killpg(viewer.pid, signal.SIGKILL)
            viewer.wait()
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python docs/screenshot.py", description=__doc__.split("\n\n")[0])
    ap.add_argument("rrd", type=Path, help="the recording (e.g. out/demo/flight.rrd)")
    ap.add_argument("--out", type=Path, default=Path("docs/images/viewer.jpg"), help="the picture to write (.png or .jpg)")
    ap.add_argument("--width", type=int, default=1600)
    ap.add_argument("--height", type=int, default=900)
    ap.add_argument("--wait-s", type=float, default=60.0, help="seconds to let the viewer load and draw")
    ap.add_argument("--chromium", default="/usr/bin/chromium")
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    try:
        print(screenshot(a.rrd, a.out, a.width, a.height, a.wait_s, a.chromium))
    except (FileNotFoundError, RuntimeError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
