"""The thread policy: `threads=auto` shares the cores among the usvc jobs running side by side."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import pytest

from usvc.pipeline import threads


def test_numbers_are_used_as_given_and_bad_values_refused():
    assert threads.resolve("3") == 3 and threads.resolve(2) == 2
    for bad in ("0", "-1", "banana", ""):
        with pytest.raises(ValueError, match="must be 'auto' or a positive number"):
            threads.resolve(bad)


def test_auto_divides_the_cores_by_the_jobs(monkeypatch):
    monkeypatch.setattr(threads, "cores_available", lambda: 8)
    monkeypatch.setattr(threads, "_USER_OMP", "")
    for jobs, expected in ((1, 8), (2, 4), (3, 2), (16, 1)):
        monkeypatch.setattr(threads, "jobs_side_by_side", lambda jobs=jobs: jobs)
        assert threads.resolve("auto") == expected


def test_an_exported_omp_num_threads_caps_auto(monkeypatch):
    monkeypatch.setattr(threads, "cores_available", lambda: 8)
    monkeypatch.setattr(threads, "jobs_side_by_side", lambda: 1)
    monkeypatch.setattr(threads, "_USER_OMP", "3")
    assert threads.resolve("auto") == 3 and threads.resolve("6") == 6


def test_a_stage_running_beside_this_one_is_counted():
    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)", "-m", "stages.train"])
    try:
        time.sleep(0.5)
        assert other.pid in threads.other_jobs()
    finally:
        other.kill()
        other.wait()
    assert other.pid not in threads.other_jobs()


def test_ancestors_do_not_count():
    """A stage started by pytest or DVC does not count its own parent as a job beside it."""
    import os

    code = "import os; from usvc.pipeline import threads; print(os.getppid() in threads.other_jobs())"
    child = subprocess.run([sys.executable, "-c", code, "-m", "stages.train"], capture_output=True, text=True,
                           check=True)
    assert child.stdout.strip() == "False"
    assert os.getpid() not in threads.other_jobs()


def test_the_command_line_setting_is_read_before_hydra():
    assert threads.setting_from_argv(["scene=mini", "threads=2"]) == "2"
    assert threads.setting_from_argv(["scene=mini"]) == "auto"


def test_cores_respect_the_affinity_mask():
    import os

    assert 1 <= threads.cores_available() <= len(os.sched_getaffinity(0))


def test_config_refuses_a_bad_thread_setting():
    from conftest import REPO
    from hydra import compose, initialize_config_dir

    from usvc.pipeline.config import ConfigError, register_configs, validate

    register_configs()
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base=None):
        cfg = compose("config", overrides=["threads=lots"])
    with pytest.raises(ConfigError, match="threads='lots' must be 'auto' or a positive number"):
        validate(cfg)


def test_cpu_lists_parse_as_the_kernel_writes_them():
    assert threads.parse_cpu_list("0-3,8,10-11\n") == {0, 1, 2, 3, 8, 10, 11}
    assert threads.parse_cpu_list("5") == {5}


@pytest.mark.skipif(len(__import__("os").sched_getaffinity(0)) < 2, reason="needs two CPUs to pin apart")
def test_a_job_pinned_to_other_cores_is_not_counted():
    """On a cluster node a scheduler's cpusets keep jobs apart: they must not shrink each other's share."""
    import os

    cpus = sorted(os.sched_getaffinity(0))
    first, rest = {cpus[0]}, set(cpus[1:])
    pinned = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)", "-m", "stages.train"],
                              preexec_fn=lambda: os.sched_setaffinity(0, rest))
    probe = "import os, sys; from usvc.pipeline import threads; print(int(sys.argv[1]) in threads.other_jobs())"
    try:
        time.sleep(0.5)
        apart = subprocess.run([sys.executable, "-c", probe, str(pinned.pid)], capture_output=True, text=True,
                               check=True, preexec_fn=lambda: os.sched_setaffinity(0, first))
        shared = subprocess.run([sys.executable, "-c", probe, str(pinned.pid)], capture_output=True, text=True,
                                check=True)
    finally:
        pinned.kill()
        pinned.wait()
    assert apart.stdout.strip() == "False" and shared.stdout.strip() == "True"


def test_a_parents_export_is_not_taken_for_a_users_ceiling():
    """A Hydra/submitit job inherits the thread variables its launcher exported; they must not cap it."""
    import os

    code = "from usvc.pipeline import threads; print(repr(threads._USER_OMP))"
    env = {k: v for k, v in os.environ.items() if k not in threads.ENV_VARS and k != threads.EXPORT_MARK}
    ours = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                          env={**env, "OMP_NUM_THREADS": "2", threads.EXPORT_MARK: "2"})
    users = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                           env={**env, "OMP_NUM_THREADS": "3", threads.EXPORT_MARK: "2"})
    assert ours.stdout.strip() == "''" and users.stdout.strip() == "'3'"


def _imports_torch(code: str) -> tuple[bool, str]:
    out = subprocess.run([sys.executable, "-c", code + "\nimport sys; print('torch' in sys.modules)"],
                         capture_output=True, text=True, check=True).stdout.split()
    return out[-1] == "True", " ".join(out[:-1])


def test_a_step_without_torch_does_not_load_it_for_the_thread_setting():
    loaded, _ = _imports_torch("from usvc.pipeline import threads; threads.apply(2, torch_pool=False)")
    assert not loaded
    loaded, n = _imports_torch("from usvc.pipeline import threads; threads.apply(2)\n"
                               "import torch; print(torch.get_num_threads())")
    assert loaded and n == "2"
    # torch loaded already: its pool is set all the same
    _, n = _imports_torch("import torch; from usvc.pipeline import threads; threads.apply(1, torch_pool=False)\n"
                          "print(torch.get_num_threads())")
    assert n == "1"


@pytest.mark.slow
def test_a_3dgs_stage_without_rendered_views_skips_without_loading_torch(tmp_path):
    """`method=multiview` renders no views: the gaussians stage writes why, reads no input, and
    neither loads its step nor torch (a second or two instead of four to six)."""
    proc = subprocess.run([sys.executable, "-X", "importtime", "-m", "stages.gaussians", "scene=mini", "threads=1",
                           f"data_dir={tmp_path / 'data'}", f"results_dir={tmp_path / 'results'}",
                           f"hydra.run.dir={tmp_path / 'logs'}"], capture_output=True, text=True,
                          cwd=Path(__file__).resolve().parents[1])
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "not computed" in (tmp_path / "data/mini/gaussians/NOT_COMPUTED.txt").read_text()
    imported = {line.split("|")[-1].strip() for line in proc.stderr.splitlines() if line.startswith("import time:")}
    assert "usvc.gaussians.run" not in imported and "torch" not in imported
