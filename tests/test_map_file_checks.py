"""Map files are checked on load (and on save): every field the code reads within its range, finite
weights, and a checksum over the whole payload; a map saved before checksums loads with one note."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest
import torch
from test_localize_bad_input import one_error_line, photo_file, tiny_map  # noqa: F401 (fixtures)
from test_relocalizer import SHORT_SIDE

from usvc.cli import main
from usvc.core.errors import UsvcError
from usvc.model.encoder import Encoder
from usvc.model.errors import ModelError
from usvc.model.head import Head, Regressor
from usvc.model.map_file import load_map, read_map_header, save_map
from usvc.model.map_checks import CHECKSUM_KEY, map_checksum
from usvc.relocalize.relocalizer import Relocalizer


def rewrite(src: Path, dst: Path, edit, checksum: str = "keep") -> Path:
    """A copy of map `src` with its payload edited; its checksum kept (a damaged file), recomputed
    (a file whose writer got it wrong) or dropped (a map saved before checksums)."""
    payload = torch.load(src, map_location="cpu", weights_only=True)
    edit(payload)
    if checksum == "recompute":
        payload[CHECKSUM_KEY] = map_checksum(payload)
    elif checksum == "drop":
        payload.pop(CHECKSUM_KEY, None)
    torch.save(payload, dst)
    return dst


# ------------------------------------------------------------------ 1. metadata out of range / missing

@pytest.mark.parametrize("field, value, match", [
    ("short_side", -120, r"metadata short_side=-120 must be an integer in \[32, 8192\]"),
    ("short_side", 0, r"metadata short_side=0 must be an integer"),
    ("short_side", "120", r"metadata short_side='120' must be an integer"),
    ("short_side", True, r"metadata short_side=True must be an integer"),
    ("median_depth", -2.0, r"metadata median_depth=-2.0 must be a finite positive number"),
    ("median_depth", float("nan"), r"metadata median_depth=nan must be a finite positive number"),
    ("scene", 7, r"metadata scene=7 must be a non-empty string"),
    ("iterations", -1, r"metadata iterations=-1 must be a non-negative integer"),
    ("focal_range", [0.9, 0.5], r"metadata focal_range=\[0.9, 0.5\] must be \[low, high\]"),
    ("focal_error", float("inf"), r"metadata focal_error=inf must be a finite number >= 0"),
])
def test_map_metadata_out_of_range_is_named(tiny_map: tuple[Path, Path], tmp_path: Path, field: str, value: object,
                                            match: str) -> None:
    bad = rewrite(tiny_map[0], tmp_path / "bad.map.pt", lambda p: p["metadata"].__setitem__(field, value),
                  checksum="recompute")
    with pytest.raises(ModelError, match=match) as info:
        read_map_header(bad)
    assert "bad.map.pt" in str(info.value) and "\n" not in str(info.value)
    with pytest.raises(ModelError, match=match):  # nor can such a map be written
        encoder = Encoder(width=0.25)
        save_map(tmp_path / "x.map.pt", Regressor(encoder, Head(in_channels=encoder.out_channels, width=8)),
                 {field: value})
    assert not (tmp_path / "x.map.pt").exists()


@pytest.mark.parametrize("section, key, value, match", [
    ("head_config", "width", -64, r"head_config width=-64 must be an integer in \[1, 65536\]"),
    ("head_config", "homogeneous", "yes", r"head_config homogeneous='yes' must be true or false"),
    ("encoder", "width", -1.0, r"encoder width=-1.0 must be a number in \[0, 16\]"),
])
def test_map_configuration_out_of_range_is_named(tiny_map: tuple[Path, Path], tmp_path: Path, section: str,
                                                 key: str, value: object, match: str) -> None:
    bad = rewrite(tiny_map[0], tmp_path / "bad.map.pt", lambda p: p[section].__setitem__(key, value),
                  checksum="recompute")
    with pytest.raises(ModelError, match=match):
        read_map_header(bad)


def test_negative_short_side_is_one_line_from_the_cli(tiny_map: tuple[Path, Path], tmp_path: Path,
                                                      photo_file: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """It used to reach cv2.resize and end in a traceback."""
    bad = rewrite(tiny_map[0], tmp_path / "neg.map.pt", lambda p: p["metadata"].__setitem__("short_side", -120),
                  checksum="recompute")
    rc = main(["localize", "--map", str(bad), "--encoder-weights", str(tiny_map[1]), "--focal", "130",
               str(photo_file)])
    line = one_error_line(rc, *capsys.readouterr())
    assert "neg.map.pt" in line and "short_side=-120" in line


def test_a_map_without_metadata_is_refused(tiny_map: tuple[Path, Path], tmp_path: Path) -> None:
    gone = rewrite(tiny_map[0], tmp_path / "gone.map.pt", lambda p: p.pop("metadata"), checksum="recompute")
    with pytest.raises(ModelError, match="gone.map.pt: map file has no valid 'metadata' entry"):
        read_map_header(gone)
    no_side = rewrite(tiny_map[0], tmp_path / "noside.map.pt", lambda p: p["metadata"].pop("short_side"),
                      checksum="recompute")
    read_map_header(no_side)  # a valid map file: only the relocalizer needs the working size
    with pytest.raises(UsvcError, match=r"noside.map.pt has no metadata field 'short_side'"):
        Relocalizer(no_side, tiny_map[1])


# ------------------------------------------------------------------ 2. checksums and non-finite weights

def test_an_intact_map_carries_a_checksum_and_loads(tiny_map: tuple[Path, Path], caplog: pytest.LogCaptureFixture
                                                    ) -> None:
    payload = torch.load(tiny_map[0], map_location="cpu", weights_only=True)
    assert payload[CHECKSUM_KEY].startswith("sha256:") and len(payload[CHECKSUM_KEY]) == 7 + 64
    assert map_checksum(payload) == payload[CHECKSUM_KEY]
    with caplog.at_level(logging.INFO):
        _, metadata = load_map(tiny_map[0], Relocalizer(*tiny_map).regressor.encoder)
    assert metadata == {"short_side": SHORT_SIDE}  # the checksum is the file's, not the metadata's
    assert "checksum" not in caplog.text


def test_a_flipped_byte_in_the_weights_is_refused(tiny_map: tuple[Path, Path], tmp_path: Path) -> None:
    data = bytearray(tiny_map[0].read_bytes())
    weight = torch.load(tiny_map[0], map_location="cpu", weights_only=True)["head_state"]["fc1.weight"]
    at = bytes(data).find(weight.reshape(-1).view(torch.uint8).numpy().tobytes()[:64])
    assert at > 0  # the fp16 weights are stored as they are
    data[at + 11] ^= 0x10
    flipped = tmp_path / "flipped.map.pt"
    flipped.write_bytes(bytes(data))
    # torch reads the damaged file without a word: only the checksum notices
    loaded = torch.load(flipped, map_location="cpu", weights_only=True)["head_state"]["fc1.weight"]
    assert not torch.equal(loaded, weight)
    with pytest.raises(ModelError, match=r"map file .*flipped.map.pt is corrupt: checksum mismatch") as info:
        read_map_header(flipped)
    assert "\n" not in str(info.value)
    with pytest.raises(ModelError, match="checksum mismatch"):
        Relocalizer(flipped, tiny_map[1])


@pytest.mark.parametrize("checksum", ["keep", "recompute", "drop"])
def test_non_finite_weights_are_refused(tiny_map: tuple[Path, Path], tmp_path: Path, checksum: str) -> None:
    def poison(payload: dict) -> None:
        payload["head_state"]["fc2.weight"][3, 5, 0, 0] = float("nan")

    bad = rewrite(tiny_map[0], tmp_path / "nan.map.pt", poison, checksum=checksum)
    with pytest.raises(ModelError, match=r"nan.map.pt is corrupt: head weight fc2.weight has non-finite values"):
        read_map_header(bad)


def test_a_diverged_head_is_not_saved(tmp_path: Path) -> None:
    encoder = Encoder(width=0.25)
    head = Head(in_channels=encoder.out_channels, width=8)
    with torch.no_grad():
        head.out.bias[0] = 1e6  # beyond fp16: inf once stored
    with pytest.raises(ModelError, match=r"cannot save map: head weight out.bias has non-finite values"):
        save_map(tmp_path / "x.map.pt", Regressor(encoder, head), {"short_side": 120})
    assert not (tmp_path / "x.map.pt").exists()


def test_an_old_map_without_checksum_loads_with_one_note(tiny_map: tuple[Path, Path], tmp_path: Path,
                                                         caplog: pytest.LogCaptureFixture) -> None:
    old = rewrite(tiny_map[0], tmp_path / "old.map.pt", lambda p: None, checksum="drop")
    with caplog.at_level(logging.WARNING):
        reloc = Relocalizer(old, tiny_map[1])
        read_map_header(old)
    notes = [r for r in caplog.records if "no checksum" in r.getMessage()]
    assert len(notes) == 1 and "old.map.pt" in notes[0].getMessage()
    assert reloc.short_side == SHORT_SIDE


# ------------------------------------------------------------------ 3. --max-error-px bound


# ------------------------------------------------------------------ sizes the header declares

def test_a_head_config_larger_than_the_stored_weights_is_refused_before_allocating(tiny_map: tuple[Path, Path],
                                                                                     tmp_path: Path) -> None:
    """head_config declares a head far larger than the weights the file holds (at the limits, 65536
    wide and 64 blocks: terabytes): refused from the shapes of a head on the meta device, before any is
    allocated. Sized here so that a build without the check allocates only ~100 MB before refusing."""
    from usvc.model.map_file import load_head

    huge = rewrite(tiny_map[0], tmp_path / "huge.map.pt",
                   lambda p: p["head_config"].update(width=2048, num_blocks=2), checksum="recompute")
    payload = read_map_header(huge)
    with pytest.raises(ModelError, match=r"huge.map.pt: map head \(as its head_config declares it\) "
                                         r"(keys do not match|entry \S+ has shape .* expected \[2048)"):
        load_head(huge, payload["encoder"]["fingerprint"], payload)


def test_a_map_torch_cannot_write_is_one_line_naming_it(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """torch's zip writer reports a full disk or a file-size limit as a RuntimeError without errno
    ("unexpected pos 704 vs 598"): the train stage says which map and why, and leaves no file."""
    from usvc.core.atomic import WriteError

    def full(obj: object, f: object) -> None:
        raise RuntimeError("[enforce fail at inline_container.cc:672] . unexpected pos 704 vs 598")

    monkeypatch.setattr(torch, "save", full)
    encoder = Encoder(width=0.25)
    final = tmp_path / "mini" / "map" / "map.pt"
    with pytest.raises(WriteError, match=rf"cannot write {final}: torch's writer failed \(unexpected pos 704 vs 598\): "
                                         "a full disk, a quota or a file-size limit\\?"):
        save_map(final, Regressor(encoder, Head(in_channels=encoder.out_channels, width=8)), {"short_side": 120})
    assert not (tmp_path / "mini").exists()
