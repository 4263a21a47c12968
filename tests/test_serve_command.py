"""`usvc serve` as a command: map names and folders, the flags it passes to uvicorn, and one clear
line for each wrong flag (the service itself: test_serve.py)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from test_localize_bad_input import tiny_map  # noqa: F401 (fixture)

pytest.importorskip("fastapi")

from usvc.cli import main  # noqa: E402
from usvc.core.errors import UsvcError  # noqa: E402
from usvc.relocalize.relocalizer import Relocalizer  # noqa: E402
from usvc.serve.maps import check_name, maps_in_folder, parse_map_arg  # noqa: E402

pytestmark = [pytest.mark.filterwarnings("ignore::DeprecationWarning")]

TOKEN = "s3cret-token"


def test_map_names_and_folders(tmp_path: Path) -> None:
    assert parse_map_arg("office=data/office/map/map.pt") == ("office", Path("data/office/map/map.pt"))
    for bad in ("office", "=x.pt", "a/b=x.pt", "..=x.pt", "a b=x.pt"):
        with pytest.raises(UsvcError):
            parse_map_arg(bad)
    assert check_name("bird_2.v1-x") == "bird_2.v1-x"
    (tmp_path / "office" / "map").mkdir(parents=True)
    (tmp_path / "office" / "map" / "map.pt").write_bytes(b"x")
    (tmp_path / "bird.pt").write_bytes(b"x")
    (tmp_path / "notes.txt").write_text("x")
    assert [n for n, _ in maps_in_folder(tmp_path)] == ["bird", "office"]
    (tmp_path / "empty").mkdir()
    with pytest.raises(UsvcError, match="no NAME/map.pt"):
        maps_in_folder(tmp_path / "empty")
    with pytest.raises(UsvcError, match="not a folder"):
        maps_in_folder(tmp_path / "bird.pt")


def test_usvc_serve_starts_uvicorn_with_the_maps(tiny_map: tuple[Path, Path], tmp_path: Path,
                                                 monkeypatch: pytest.MonkeyPatch,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    import uvicorn

    import usvc.serve.maps as maps_module

    started: dict[str, Any] = {}
    monkeypatch.setattr(uvicorn, "run", lambda app, **kw: started.update(app=app, **kw))
    monkeypatch.setattr(maps_module, "Relocalizer",
                        lambda path, weights, options, device: Relocalizer(path, tiny_map[1], options, device=device))
    token = tmp_path / "token"
    token.write_text(TOKEN + "\n")
    assert main(["serve", "--map", f"tiny={tiny_map[0]}", "--token-file", str(token), "--port", "8123",
                 "--workers", "2", "--queue", "3"]) == 0
    assert started["host"] == "127.0.0.1" and started["port"] == 8123
    app = started["app"]
    assert app.state.options.token == TOKEN and app.state.options.threads == 2 and app.state.pool.capacity == 5
    assert app.state.registry.names() == ["tiny"]
    for args, message in [([], "give at least one map"), (["--map", "x"], "give NAME=PATH"),
                          (["--map", f"a/b={tiny_map[0]}"], "map name"),
                          (["--map", f"t={tmp_path / 'none.pt'}"], "is not a file"),
                          (["--map", f"t={tiny_map[0]}", "--token-file", str(tmp_path / "none")], "--token-file"),
                          (["--map", f"t={tiny_map[0]}", "--queue", "-1"], "queue=-1")]:
        assert main(["serve", *args]) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("usvc serve: error: ") and message in err[0], err
