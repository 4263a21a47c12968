"""A screenshot of `usvc serve`'s page with a photo localized: docs/img/serve_page.png.

    python scripts/serve_screenshot.py  # the miniature scene's map and one of its test photos

Starts `usvc serve` on the map (a free loopback port), opens the page in Debian's headless
Chromium (Selenium, /usr/bin/chromium and /usr/bin/chromedriver: `apt-get install chromium
chromium-driver`), types the focal length into the page's field, chooses the photo in its file
input, waits for the answer and the 3D view, and saves the window.
"""

from __future__ import annotations

import argparse
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

from selenium import webdriver
from selenium.webdriver.chrome.service import Service


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for_server(url: str, server: subprocess.Popen, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if server.poll() is not None:
            raise SystemExit(f"usvc serve exited with status {server.returncode}")
        try:
            with urllib.request.urlopen(url + "healthz", timeout=2):
                return
        except OSError:
            time.sleep(0.5)
    raise SystemExit(f"usvc serve did not answer within {timeout:g} s")


def wait_for(driver: webdriver.Chrome, script: str, timeout: float) -> object:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = driver.execute_script("return " + script)
        if value:
            return value
        time.sleep(0.2)
    raise SystemExit(f"the page did not get there within {timeout:g} s: {script}")


def browser(width: int, height: int, profile: str) -> webdriver.Chrome:
    options = webdriver.ChromeOptions()
    options.binary_location = "/usr/bin/chromium"
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--no-first-run",
                "--disable-background-networking", "--disable-component-update", "--disable-sync",
                "--enable-unsafe-swiftshader", "--hide-scrollbars", f"--window-size={width},{height}",
                f"--user-data-dir={profile}"):
        options.add_argument(arg)
    return webdriver.Chrome(service=Service("/usr/bin/chromedriver"), options=options)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--map", default="data/mini/map/map.pt", help="the map to serve (as 'mini')")
    ap.add_argument("--photo", default="data/mini/prepared/images/test/rgb/seq-03-frame-000000.color.png")
    ap.add_argument("--focal", default="260", help="typed into the page's focal field (px)")
    ap.add_argument("--out", default="docs/img/serve_page.png")
    ap.add_argument("--size", default="1280x1000", help="the browser window, WIDTHxHEIGHT")
    ap.add_argument("--timeout", type=float, default=300.0, help="seconds for the server to load and answer")
    args = ap.parse_args()
    width, height = (int(v) for v in args.size.split("x"))
    photo, out = Path(args.photo).resolve(), Path(args.out)
    port = free_port()
    url = f"http://127.0.0.1:{port}/"
    server = subprocess.Popen([sys.executable, "-m", "usvc.cli", "serve", "--map", f"mini={args.map}",
                               "--port", str(port), "--log-level", "warning"])
    try:
        wait_for_server(url, server, args.timeout)
        with tempfile.TemporaryDirectory(prefix="usvc-chromium-") as profile:
            driver = browser(width, height, profile)
            try:
                driver.get(url)
                wait_for(driver, "(document.getElementById('view').data || []).length >= 1", args.timeout)
                driver.find_element("id", "focal").send_keys(args.focal)
                driver.find_element("id", "file").send_keys(str(photo))
                wait_for(driver, "document.getElementById('pose-center').textContent || "
                         "document.getElementById('status').className === 'bad'", args.timeout)
                time.sleep(2.0)  # the 3D view's redraw
                out.parent.mkdir(parents=True, exist_ok=True)
                driver.save_screenshot(str(out))
                print(f"{out}: {driver.find_element('id', 'status').text}; "
                      f"centre {driver.find_element('id', 'pose-center').text}")
            finally:
                driver.quit()
    finally:
        server.terminate()
        server.wait(30)
    return 0


if __name__ == "__main__":
    sys.exit(main())
