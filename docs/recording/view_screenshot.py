"""A screenshot of rerun's viewer showing a .rrd file, on a machine without a display or GPU: rerun serves
its web viewer, headless Chromium renders it with SwiftShader (WebGL on the CPU) and saves the page.

    condground view --dataset.repo_id=local/PickPlaceFixedBin-v0 --dataset.root=DIR --episode=0 --output=ep0.rrd
    python docs/recording/view_screenshot.py ep0.rrd docs/images/condground-view.png

Rerun's analytics are switched off first (`rerun analytics disable`, in a private config folder), and
nothing is fetched from the network: the viewer comes with the rerun-sdk wheel.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("rrd", type=Path)
    parser.add_argument("png", type=Path)
    parser.add_argument("--wait", type=float, default=60, help="seconds for the viewer to load the recording")
    parser.add_argument("--size", default="1600,900")
    parser.add_argument("--port", type=int, default=9097)
    args = parser.parse_args()
    if not args.rrd.is_file():
        raise SystemExit(f"{args.rrd}: no such .rrd file")
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    rerun = Path(sys.executable).with_name("rerun")
    with tempfile.TemporaryDirectory() as config:
        env = {**os.environ, "XDG_CONFIG_HOME": config}
        subprocess.run([str(rerun), "analytics", "disable"], env=env, capture_output=True, timeout=60)
        server = subprocess.Popen(
            [str(rerun), "--serve-web", f"--web-viewer-port={args.port}", f"--port={args.port + 1}", str(args.rrd)],
            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )  # fmt: skip
        options = webdriver.ChromeOptions()
        for flag in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--use-angle=swiftshader",
                     "--enable-unsafe-swiftshader", f"--window-size={args.size}"):  # fmt: skip
            options.add_argument(flag)
        options.binary_location = shutil.which("chromium") or "/usr/bin/chromium"
        driver = webdriver.Chrome(options=options, service=Service(shutil.which("chromedriver")))
        try:
            time.sleep(3)
            proxy = f"rerun%2Bhttp%3A%2F%2F127.0.0.1%3A{args.port + 1}%2Fproxy"
            driver.get(f"http://127.0.0.1:{args.port}/?url={proxy}")
            time.sleep(args.wait)
            args.png.parent.mkdir(parents=True, exist_ok=True)
            driver.save_screenshot(str(args.png))
        finally:
            driver.quit()
            server.terminate()
            server.wait(timeout=30)
    print(f"wrote {args.png}")


if __name__ == "__main__":
    main()
