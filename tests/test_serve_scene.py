"""`usvc serve`'s page support: GET /v1/maps/{name}/scene (the map's points, strided, and the
mapping cameras from the scene's SfM files), the page's plotly.js and the offline /docs (Swagger
UI's files served by the service, no URL elsewhere). The browser itself: tests/test_serve_page.py.
"""

from __future__ import annotations

import re
import shutil
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_localize_bad_input import tiny_map  # noqa: F401 (fixture)

pytest.importorskip("fastapi")
pytest.importorskip("httpx")

from fastapi.testclient import TestClient  # noqa: E402

from usvc.relocalize.relocalizer import Relocalizer  # noqa: E402
from usvc.serve import MapRegistry, ServeOptions  # noqa: E402
from usvc.serve.app import create_app  # noqa: E402
from usvc.serve.scene_view import DECIMALS, scene_record, strided  # noqa: E402

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")

TOKEN = "s3cret-token"


def mapping_poses(n: int) -> tuple[np.ndarray, np.ndarray]:
    """n world-to-camera poses on a circle, each looking at the origin."""
    R, t = [], []
    for a in np.linspace(0, 2 * np.pi, n, endpoint=False):
        centre = np.array([3 * np.cos(a), 0.2, 3 * np.sin(a)])
        forward = -centre / np.linalg.norm(centre)
        right = np.cross([0.0, 1.0, 0.0], forward)  # y down (OpenCV): right = down x forward
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        rot = np.stack([right, down, forward])
        R.append(rot)
        t.append(-rot @ centre)
    return np.array(R), np.array(t)


def write_tracks(path: Path, points: np.ndarray, R: np.ndarray, t: np.ndarray) -> None:
    """The parts of a tracks.h5 the scene endpoint reads: images/{name,R_world_to_cam,t_world_to_cam}, points/xyz."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with h5py.File(path, "w") as h5:
        h5.create_dataset("images/name", data=np.array([f"seq/frame-{i:03d}.png" for i in range(len(R))], dtype=object),
                          dtype=h5py.string_dtype())
        h5["images/R_world_to_cam"], h5["images/t_world_to_cam"], h5["points/xyz"] = R, t, points


def scene_folder(root: Path, tiny_map: tuple[Path, Path], points: np.ndarray, cameras: int = 12) -> Path:
    """A scene folder as the pipeline lays it out: <root>/map/map.pt (the tiny map) and <root>/sfm/tracks.h5."""
    (root / "map").mkdir(parents=True)
    shutil.copy(tiny_map[0], root / "map" / "map.pt")
    write_tracks(root / "sfm" / "tracks.h5", points, *mapping_poses(cameras))
    return root / "map" / "map.pt"


@pytest.fixture(scope="module")
def points() -> np.ndarray:
    return np.random.default_rng(0).normal(size=(45_001, 3))


@pytest.fixture(scope="module")
def client(tiny_map: tuple[Path, Path], points: np.ndarray, tmp_path_factory: pytest.TempPathFactory) -> Any:
    registry = MapRegistry()
    registry.add("room", Relocalizer(scene_folder(tmp_path_factory.mktemp("room"), tiny_map, points), tiny_map[1]))
    registry.add("bare", Relocalizer(*tiny_map))  # no SfM files beside it: no points, no cameras
    with TestClient(create_app(registry, ServeOptions(token=TOKEN)), raise_server_exceptions=False) as c:
        c.headers["Authorization"] = f"Bearer {TOKEN}"
        yield c


def test_strided_is_deterministic_and_bounded():
    rows = np.arange(45_001)
    picked = strided(rows, 20_000)
    assert len(picked) <= 20_000 and picked[0] == 0 and np.all(np.diff(picked) == 3)
    assert np.array_equal(picked, strided(rows, 20_000))
    assert len(strided(rows[:10], 20_000)) == 10
    with pytest.raises(ValueError):
        strided(rows, 0)


def test_scene_has_points_and_mapping_cameras(client: TestClient, points: np.ndarray):
    r = client.get("/v1/maps/room/scene")
    assert r.status_code == 200 and r.headers["content-type"] == "application/json"
    scene = r.json()
    p = scene["points"]
    assert p["total"] == len(points) and p["source"] == "sfm points" and p["shown"] == len(p["x"]) <= 20_000
    shown = strided(points, 20_000)
    assert np.allclose(np.c_[p["x"], p["y"], p["z"]], shown, atol=0.5 * 10 ** -DECIMALS)
    cams = scene["cameras"]
    assert cams["total"] == 12 and cams["source"] == "tracks.h5" and cams["names"][0] == "seq/frame-000.png"
    R, t = mapping_poses(12)
    centres = -np.einsum("mji,mj->mi", R, t)
    assert np.allclose(cams["centers"], centres, atol=1e-4)
    assert np.allclose(cams["forward"], R[:, 2], atol=1e-4)  # each looks at the origin
    assert np.allclose(np.array(cams["forward"]), -centres / np.linalg.norm(centres, axis=1, keepdims=True), atol=1e-3)
    assert np.allclose(scene["up"], [0, -1, 0], atol=1e-3)  # OpenCV's y is down: the cameras' up is -y
    assert scene["radius"] > 0 and len(scene["center"]) == 3
    assert client.get("/v1/maps/room/scene").content == r.content  # cached: the same bytes


def test_scene_of_a_map_without_points_or_cameras(client: TestClient):
    scene = client.get("/v1/maps/bare/scene").json()
    assert scene["points"] == {"total": 0, "shown": 0, "source": "none", "x": [], "y": [], "z": []}
    assert scene["cameras"]["total"] == 0 and scene["cameras"]["source"] is None
    assert scene["center"] is None and scene["radius"] is None and scene["up"] is None


def test_scene_refusals_are_one_json_error(client: TestClient):
    r = client.get("/v1/maps/nowhere/scene")
    assert r.status_code == 404 and r.json()["reason"] == "unknown_map" and "room" in r.json()["error"]
    r = client.get("/v1/maps/room/scene", headers={"Authorization": "Bearer wrong"})
    assert r.status_code == 401 and r.json()["reason"] == "unauthorized"


def test_cameras_of_another_scene_are_passed_over(tiny_map: tuple[Path, Path], tmp_path: Path):
    reloc = Relocalizer(scene_folder(tmp_path / "s", tiny_map, np.zeros((3, 3))), tiny_map[1])

    class Obs:
        image_names = ["elsewhere/frame-000.png"]

    class Marks:
        xyz = np.ones((5, 3))
        observations = Obs()

    reloc.landmarks = Marks()  # landmarks that name images the SfM file does not have
    scene = scene_record("s", reloc)
    assert scene["points"]["source"] == "landmarks" and scene["cameras"]["total"] == 0


def test_plotly_is_served_once_with_a_long_cache(client: TestClient):
    r = client.get("/static/plotly.min.js")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/javascript")
    assert "max-age=" in r.headers["cache-control"] and b"plotly.js" in r.content[:200]
    page = client.get("/").text
    assert '<script src="static/plotly.min.js"></script>' in page
    assert not re.search(r"""(src|href)=["']?(https?:)?//""", page)  # nothing from elsewhere
    for element in ('id="pose-center"', 'id="pose-quat"', 'capture="environment"', 'id="view"'):
        assert element in page
    assert client.get("/static/nope.js").json()["reason"] == "not_found"


def test_docs_are_offline(client: TestClient):
    r = client.get("/docs")
    assert r.status_code == 200
    refs = re.findall(r"""(?:src|href)=["']([^"']+)["']""", r.text)
    assert refs and not [u for u in refs if re.match(r"(https?:)?//", u)], refs
    for url in refs:
        got = client.get(url)
        assert got.status_code == 200 and len(got.content) > 100, url
    assert client.get("/redoc").status_code == 404
    assert client.get("/openapi.json").json()["paths"]["/v1/maps/{name}/scene"]["get"]
