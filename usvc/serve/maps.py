"""The maps a service answers for: registered by name at start, each loaded once (its network
and landmarks) on the device the rest of usvc uses. Requests name a map; nothing they send is a
path."""

from __future__ import annotations

import datetime as dt
import logging
import re
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from usvc.core.artifact_names import MAP_PT
from usvc.core.errors import UsvcError
from usvc.relocalize.relocalizer import Relocalizer, RelocalizeOptions

log = logging.getLogger(__name__)

NAME = re.compile(r"[A-Za-z0-9_.-]{1,64}")


def check_name(name: str) -> str:
    if not isinstance(name, str) or not NAME.fullmatch(name) or name in (".", ".."):
        raise UsvcError(f"map name {str(name)[:70]!r}: use 1-64 of A-Z a-z 0-9 _ . - (not . or ..)")
    return name


@dataclass
class ServedMap:
    """A loaded map and what GET /v1/maps says of it."""

    name: str
    relocalizer: Relocalizer
    info: dict[str, Any] = field(default_factory=dict)


def describe(name: str, relocalizer: Relocalizer) -> dict[str, Any]:
    """name, photos (the mapping photos its landmarks come from, when known), size (bytes of the map
    file and its landmarks), encoder, made (the map file's time, UTC), scene, short side."""
    meta = relocalizer.metadata
    landmarks = relocalizer.landmarks
    photos = None
    if landmarks is not None and landmarks.observations is not None:
        photos = len(landmarks.observations.image_names)
    files = [relocalizer.map_path] + ([relocalizer.landmarks_path] if relocalizer.landmarks_path else [])
    size = sum(p.stat().st_size for p in files if p.is_file())
    made = None
    if relocalizer.map_path.is_file():
        made = dt.datetime.fromtimestamp(relocalizer.map_path.stat().st_mtime, dt.timezone.utc).isoformat(
            timespec="seconds")
    return {"name": name, "scene": meta.get("scene"), "photos": photos, "landmarks": None if landmarks is None
            else int(len(landmarks.xyz)), "size_bytes": int(size), "encoder": meta.get("model") or
            meta.get("encoder_file"), "method": meta.get("method"), "short_side": relocalizer.short_side,
            "made": made, "device": relocalizer.device, "precision": relocalizer.precision}


class MapRegistry:
    """name -> loaded map. `add` takes a Relocalizer made elsewhere (tests, other options);
    `load` makes one from a map file, as `usvc localize --map` does."""

    def __init__(self) -> None:
        self._maps: dict[str, ServedMap] = {}

    def add(self, name: str, relocalizer: Relocalizer) -> ServedMap:
        check_name(name)
        if name in self._maps:
            raise UsvcError(f"map name {name!r} is given twice")
        served = ServedMap(name, relocalizer, describe(name, relocalizer))
        self._maps[name] = served
        return served

    def load(self, name: str, path: str | Path, options: RelocalizeOptions | None = None, device: str = "auto",
             make: Callable[..., Relocalizer] | None = None) -> ServedMap:
        check_name(name)
        if name in self._maps:
            raise UsvcError(f"map name {name!r} is given twice")
        path = Path(path)
        if not path.is_file():
            raise UsvcError(f"map {name}: {path} is not a file (a map.pt the train stage wrote)")
        log.info("loading map %s from %s", name, path)
        return self.add(name, (make or Relocalizer)(path, None, options, device=device))

    def get(self, name: str) -> ServedMap | None:
        return self._maps.get(name) if isinstance(name, str) else None

    def __iter__(self) -> Iterator[ServedMap]:
        return iter(self._maps.values())

    def __len__(self) -> int:
        return len(self._maps)

    def names(self) -> list[str]:
        return list(self._maps)


def parse_map_arg(text: str) -> tuple[str, Path]:
    """`NAME=PATH` of --map."""
    name, sep, path = text.partition("=")
    if not sep or not path:
        raise UsvcError(f"--map {text!r}: give NAME=PATH, e.g. office=data/office/map/map.pt")
    return check_name(name), Path(path)


def maps_in_folder(folder: str | Path) -> list[tuple[str, Path]]:
    """--maps-dir: each `NAME/map.pt`, `NAME/map/map.pt` (a scene's data folder) or `NAME.pt` in the
    folder, named NAME, sorted."""
    folder = Path(folder)
    if not folder.is_dir():
        raise UsvcError(f"--maps-dir {folder}: not a folder")
    found: list[tuple[str, Path]] = []
    for entry in sorted(folder.iterdir(), key=lambda p: p.name):
        if entry.is_dir():
            for candidate in (entry / MAP_PT, entry / "map" / MAP_PT):
                if candidate.is_file():
                    found.append((entry.name, candidate))
                    break
        elif entry.suffix == ".pt" and entry.is_file():
            found.append((entry.stem, entry))
    if not found:
        raise UsvcError(f"--maps-dir {folder}: no NAME/map.pt, NAME/map/map.pt or NAME.pt in it")
    for name, _ in found:
        check_name(name)
    return found
