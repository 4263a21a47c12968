"""`usvc map` refuses what `prepare` would refuse (a folding lens distortion, a focal length no
camera has) before anything is registered, so the corrected retry is not "already exists"."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from test_map_front_door import checkout, registered, snapshot  # noqa: F401 (checkout is a fixture)

from usvc.core.errors import UsvcError
from usvc.prepare.new_scene import NewSceneOptions, add_scene


def transforms_capture(folder: Path, n: int = 9, **intrinsics) -> Path:
    """A posed transforms.json capture of n 48x32 photos; `intrinsics` override the shared camera."""
    from importer_fixtures import make_gt, write_image
    from test_importers_nerf import transforms_frame

    from usvc.core.scene import Camera

    cam = Camera("PINHOLE", 48, 32, (40.0, 40.0, 24.0, 16.0))
    frames = []
    for i in range(n):
        write_image(folder / "images" / f"f{i:02d}.png", 48, 32)
        frames.append(transforms_frame(make_gt(10 + i, cam), f"./images/f{i:02d}.png"))
    data = {"fl_x": 40.0, "fl_y": 40.0, "cx": 24.0, "cy": 16.0, "w": 48, "h": 32, "frames": frames, **intrinsics}
    (folder / "transforms.json").write_text(json.dumps(data))
    return folder


@pytest.mark.parametrize("intrinsics, message", [
    ({"k1": -5.0}, "lens distortion folds over"),
    ({"fl_x": 1.78e6, "fl_y": 1.78e6}, r"focal length 1\.78e\+06 px for 48x32 images implies a 0\.00\d+ deg"),
    ({"fl_x": 0.5, "fl_y": 0.5}, "wider than a camera without lens distortion can see"),
])
def test_cameras_prepare_refuses_are_refused_before_registering(checkout: Path, tmp_path: Path, intrinsics,
                                                                  message) -> None:
    capture = transforms_capture(tmp_path / "capture", **intrinsics)
    before = snapshot(checkout)
    with pytest.raises(UsvcError, match=message):
        add_scene(capture, checkout, NewSceneOptions("kitchen", format="transforms"))
    assert snapshot(checkout) == before, "nothing registered: the corrected retry is not 'already exists'"
    transforms_capture(capture)  # corrected
    add_scene(capture, checkout, NewSceneOptions("kitchen", format="transforms"))
    assert registered(checkout, "kitchen")


def test_plausible_focal_lengths_pass_the_field_of_view_check() -> None:
    from usvc.core.scene import Camera
    from usvc.prepare.working_images import field_of_view_problem

    assert field_of_view_problem(Camera("PINHOLE", 480, 270, (420.0, 420.0, 240.0, 135.0))) == ""
    assert field_of_view_problem(Camera("PINHOLE", 6000, 4000, (500_000.0, 500_000.0, 3000.0, 2000.0))) == ""  # 0.69 deg
    assert field_of_view_problem(Camera("OPENCV_FISHEYE", 640, 480, (20.0, 20.0, 320.0, 240.0, 0, 0, 0, 0))) == ""
    assert "narrower" in field_of_view_problem(Camera("PINHOLE", 480, 270, (1.78e6, 1.78e6, 240.0, 135.0)))
