"""The thread policy: `threads=auto` shares the cores among the usvc jobs running side by side."""

from __future__ import annotations

import subprocess
import sys
import time

import pytest

from usvc import threads


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

    code = "import os; from usvc import threads; print(os.getppid() in threads.other_jobs())"
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
    from hydra import compose, initialize_config_dir

    from conftest import REPO
    from usvc.config import ConfigError, register_configs, validate

    register_configs()
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base=None):
        cfg = compose("config", overrides=["threads=lots"])
    with pytest.raises(ConfigError, match="threads='lots' must be 'auto' or a positive number"):
        validate(cfg)
