"""`usvc serve`'s page (GET /) in a real headless browser: Debian's Chromium driven by Selenium
against a real uvicorn server on a loopback port. The page loads and lists the maps, a photo
chosen in its file input is localized, the pose it shows is the API's answer for the same photo,
the 3D view is drawn with the camera in it, /docs renders offline, and the browser logs no error.

Without Chromium, chromedriver or selenium the tests are skipped, except under CI (the variable CI
set), where they fail: .ci/run installs the browser.
"""

from __future__ import annotations

import json
import os
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import httpx
import numpy as np
import pytest
from test_localize_bad_input import CENTRED, exactly, tiny_map  # noqa: F401 (fixture)
from test_relocalizer import exact_coordinates, photo
from test_serve_scene import scene_folder

pytest.importorskip("fastapi")
uvicorn = pytest.importorskip("uvicorn")

from usvc.relocalize.relocalizer import Relocalizer  # noqa: E402
from usvc.serve import MapRegistry, ServeOptions  # noqa: E402
from usvc.serve.app import create_app  # noqa: E402

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")

CHROMIUM, CHROMEDRIVER = Path("/usr/bin/chromium"), Path("/usr/bin/chromedriver")
FOCAL = 130  # CENTRED's


def browser_missing() -> str:
    missing = [str(p) for p in (CHROMIUM, CHROMEDRIVER) if not p.is_file()]
    try:
        import selenium  # noqa: F401
    except ImportError:
        missing.append("selenium (pip install -e '.[test]')")
    return ", ".join(missing)


@pytest.fixture(scope="module")
def server(tiny_map: tuple[Path, Path], tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """A real uvicorn server in a thread of this process (so the network's replacement applies),
    on a free loopback port; its base URL. The map has SfM points and mapping cameras beside it."""
    points = exact_coordinates(15, 20, CENTRED).reshape(-1, 3)  # what the photo's camera sees
    map_path = scene_folder(tmp_path_factory.mktemp("room"), tiny_map, points, cameras=8)
    registry = MapRegistry()
    registry.add("room", Relocalizer(map_path, tiny_map[1]))
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    config = uvicorn.Config(create_app(registry, ServeOptions()), log_level="warning", lifespan="on")
    uv = uvicorn.Server(config)
    with pytest.MonkeyPatch.context() as mp:
        exactly(mp, CENTRED)  # poses are found: the network sees CENTRED's exact coordinates
        thread = threading.Thread(target=uv.run, kwargs={"sockets": [sock]}, daemon=True)
        thread.start()
        deadline = time.monotonic() + 30
        while not uv.started:
            assert thread.is_alive() and time.monotonic() < deadline, "the server did not start"
            time.sleep(0.05)
        yield f"http://127.0.0.1:{port}/"
        uv.should_exit = True
        thread.join(10)
    sock.close()


@pytest.fixture(scope="module")
def browser(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Any]:
    missing = browser_missing()
    if missing:
        message = f"no headless browser here: {missing} missing (apt-get install chromium chromium-driver)"
        if os.environ.get("CI"):
            pytest.fail(message + "; CI must run these tests")
        pytest.skip(message)
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM)
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--no-first-run",
                "--disable-background-networking", "--disable-component-update", "--disable-sync",
                "--enable-unsafe-swiftshader", "--window-size=1280,1000",
                f"--user-data-dir={tmp_path_factory.mktemp('chromium')}"):
        options.add_argument(arg)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = webdriver.Chrome(service=Service(str(CHROMEDRIVER)), options=options)
    driver.set_page_load_timeout(60)
    try:
        yield driver
    finally:
        driver.quit()


def wait_for(driver: Any, script: str, timeout: float = 60.0) -> Any:
    """The value of the JavaScript expression `script` once it is truthy."""
    deadline = time.monotonic() + timeout
    while True:
        value = driver.execute_script("return " + script)
        if value:
            return value
        if time.monotonic() > deadline:
            page = driver.execute_script("return document.body.innerText")
            raise AssertionError(f"timed out waiting for: {script}\n{page}")
        time.sleep(0.1)


def errors_logged(driver: Any) -> list[dict]:
    return [e for e in driver.get_log("browser") if e.get("level") == "SEVERE"]


def numbers(driver: Any, element_id: str) -> list[float]:
    return [float(v) for v in driver.find_element("id", element_id).text.split()]


def test_page_localizes_a_photo_and_draws_the_camera(server: str, browser: Any, tmp_path: Path):
    path = tmp_path / "photo.png"
    cv2.imwrite(str(path), photo(160, 120))
    browser.get(server)
    assert wait_for(browser, "Array.from(document.getElementById('map').options).map(o => o.value).join(',')") == "room"
    wait_for(browser, "(document.getElementById('view').data || []).length >= 2")  # the map's points and cameras
    browser.find_element("id", "focal").send_keys(str(FOCAL))
    browser.find_element("id", "file").send_keys(str(path))
    wait_for(browser, "document.getElementById('pose-center').textContent")
    assert "pose found" in browser.find_element("id", "status").text

    with path.open("rb") as f:  # the same photo posted to the API directly
        direct = httpx.post(server + "v1/maps/room/localize", files={"photo": ("photo.png", f, "image/png")},
                            data={"focal": str(FOCAL)}, timeout=60).json()
    assert direct["success"]
    shown = json.loads(browser.find_element("id", "out").text)
    timing = ("seconds",)
    assert {k: v for k, v in shown.items() if k not in timing} == {k: v for k, v in direct.items() if k not in timing}
    assert numbers(browser, "pose-center") == pytest.approx(direct["camera_center"], abs=6e-5)
    assert numbers(browser, "pose-quat") == pytest.approx(direct["q_wxyz"], abs=6e-6)
    assert numbers(browser, "pose-t") == pytest.approx(direct["t"], abs=6e-5)
    assert float(browser.find_element("id", "pose-confidence").text) == pytest.approx(direct["confidence"], abs=6e-5)
    assert browser.find_element("id", "pose-warnings").text == ("\n".join(direct["warnings"]) if direct.get("warnings")
                                                                 else "none")
    assert "total" in browser.find_element("id", "pose-seconds").text

    # the 3D view: plotly's plot with the points, the mapping cameras and the localized camera
    assert browser.find_elements("css selector", "#view.js-plotly-plot .plot-container")
    traces = browser.execute_script("return document.getElementById('view').data.map(t => "
                                    "({name: t.name, x: Array.from(t.x), y: Array.from(t.y), z: Array.from(t.z)}))")
    names = [t["name"] for t in traces]
    assert names[0].startswith("map points (300 of 300)") and names[1] == "mapping cameras (8)"
    assert "localized camera" in names
    centre = traces[names.index("camera centre")]
    assert [centre["x"][0], centre["y"][0], centre["z"][0]] == pytest.approx(direct["camera_center"])
    frustum = traces[names.index("localized camera")]
    assert [frustum["x"][0], frustum["y"][0], frustum["z"][0]] == pytest.approx(direct["camera_center"])
    assert errors_logged(browser) == []


def test_a_refused_photo_shows_why(server: str, browser: Any, tmp_path: Path):
    path = tmp_path / "photo.png"
    cv2.imwrite(str(path), photo(160, 120))
    browser.get(server)
    wait_for(browser, "document.getElementById('map').options.length")
    browser.find_element("id", "focal").send_keys("1e9")  # an absurd focal length: the pose is refused
    browser.find_element("id", "file").send_keys(str(path))
    wait_for(browser, "document.getElementById('status').textContent.startsWith('HTTP')")
    assert "HTTP 422" in browser.find_element("id", "status").text
    assert browser.find_element("id", "pose-center").text == ""
    assert browser.find_element("id", "pose-warnings").text.startswith("refused: ")
    assert json.loads(browser.find_element("id", "out").text)["reason"] == "pose_refused"
    # an HTTP error answer is logged by the browser as a failed resource; nothing else is
    assert [e for e in errors_logged(browser) if "422" not in e["message"]] == []


def test_docs_render_offline(server: str, browser: Any):
    browser.get(server + "docs")
    title = wait_for(browser, "document.querySelector('.swagger-ui .info .title')?.textContent")
    assert "usvc serve" in title
    wait_for(browser, "document.querySelectorAll('.opblock').length >= 5")
    requested = browser.execute_script("return performance.getEntriesByType('resource').map(r => r.name)")
    assert requested and all(url.startswith(server) for url in requested), requested
    assert errors_logged(browser) == []

