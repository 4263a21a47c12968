from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from usvc.sfm.tracks_file import Tracks

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
AUTO_PRECISIONS = ("native", "bf16", "fp32")


def pytest_addoption(parser):
    parser.addoption(
        "--auto-precision", choices=AUTO_PRECISIONS, default="native",
        help="what precision=auto resolves to on the CPU in this process: native (this CPU's own "
             "choice), bf16 (as on a CPU with native bf16; emulated, slower, elsewhere) or fp32 (as on "
             "an AVX2-only CPU). CI runs the tests marked `precision` under both forced values.")


@pytest.fixture(autouse=True)
def _auto_precision(request, monkeypatch):
    """Make `auto` resolve as on another CPU (--auto-precision): the capability check and the probe
    answer as that CPU's would (except in tests marked `probe`, which test them); a test that patches
    them itself still wins inside the test."""
    forced = request.config.getoption("--auto-precision")
    if forced != "native" and request.node.get_closest_marker("probe") is None:
        from usvc.core import precision

        monkeypatch.setattr(precision, "cpu_has_native_bf16", lambda: forced == "bf16")
        monkeypatch.setattr(precision, "cpu_bf16_speedup", lambda: 10.0 if forced == "bf16" else 1.0)
    yield


def shared_scene(name: str) -> Path:
    path = SHARED / "scenes" / name
    if not path.is_dir():
        pytest.skip(f"{path} is not present (CI has ../shared)")
    return path


def tracks_of(R, t, xyz, offset, obs_image, K=None) -> Tracks:
    """SfM tracks for tests: cameras (R, t, K: 3x3, default a 64x48 pinhole with f = 50 px), points xyz,
    CSR `offset` into the observations' `obs_image`; pixels, descriptors and errors are zero."""
    K = np.array([[50.0, 0, 32.0], [0, 50.0, 24.0], [0, 0, 1]]) if K is None else np.asarray(K, float)
    n, m = len(xyz), len(obs_image)
    return Tracks(
        image_names=[f"m{i:02d}.png" for i in range(len(R))], R=np.asarray(R, float), t=np.asarray(t, float),
        K=np.repeat(K[None], len(R), axis=0), point_id=np.arange(n), xyz=np.asarray(xyz, float),
        rgb=np.zeros((n, 3), np.uint8), error=np.zeros(n, np.float32), offset=np.asarray(offset, np.int64),
        obs_image=np.asarray(obs_image, np.int32), obs_uv=np.zeros((m, 2), np.float32),
        obs_descriptor=np.zeros((m, 128), np.uint8), obs_error=np.zeros(m, np.float32),
    )
