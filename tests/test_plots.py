"""The metrics stage's PNGs: CDF axes fitted to the errors, a trajectory that tells ground truth from estimate."""

from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np
import pytest

from usvc.metrics.plots import (
    CDF_MIN_SPAN,
    METRIC_THRESHOLDS_CM,
    RELATIVE_THRESHOLDS_PCT,
    ROTATION_THRESHOLDS_DEG,
    cdf_figure,
    cdf_x_limit,
    trajectory_figure,
)


@pytest.fixture(autouse=True)
def _close_figures():
    yield
    plt.close("all")


def _cdf_limits(trans: np.ndarray, rot: np.ndarray, failed: np.ndarray) -> tuple[float, float]:
    fig = cdf_figure(trans, "translation error (cm)", METRIC_THRESHOLDS_CM, rot, failed, "t")
    a, b = fig.axes
    assert a.get_xlim()[0] == 0.0 and b.get_xlim()[0] == 0.0
    return a.get_xlim()[1], b.get_xlim()[1]


def test_each_cdf_axis_follows_its_own_errors():
    rng = np.random.default_rng(0)
    trans = rng.uniform(0.5, 6.0, 40)  # cm
    rot = rng.uniform(0.05, 0.4, 40)  # deg: on a shared 0-10 axis this curve would be a vertical line
    failed = np.zeros(40, bool)
    t_hi, r_hi = _cdf_limits(trans, rot, failed)
    assert trans.max() <= t_hi <= 1.5 * trans.max()
    assert r_hi == CDF_MIN_SPAN  # 0.4 deg fits in the minimum span (the 1 degree threshold)
    _, r_hi = _cdf_limits(trans, 3.0 * rot, failed)
    assert 1.2 <= r_hi <= 1.5 * 1.2  # wider errors, a wider axis


def test_cdf_axis_ignores_failures_and_far_outliers():
    errors = np.r_[np.linspace(0.1, 2.0, 19), 170.0]  # one query flipped round: a 170 degree error
    assert 2.0 <= cdf_x_limit(errors) <= 3.0
    failed = np.zeros(20, bool)
    failed[:5] = True
    big = np.r_[np.full(5, 500.0), np.linspace(1.0, 8.0, 15)]  # the failed queries' errors are not plotted
    assert 8.0 <= cdf_x_limit(big, failed) <= 10.0


def test_cdf_axis_has_a_minimum_span():
    assert cdf_x_limit(np.zeros(10)) == CDF_MIN_SPAN
    assert cdf_x_limit(np.full(10, 0.01)) == CDF_MIN_SPAN
    assert cdf_x_limit(np.full(4, np.nan)) == CDF_MIN_SPAN  # nothing succeeded
    assert cdf_x_limit(np.array([1.0, 2.0]), np.array([True, True])) == CDF_MIN_SPAN
    assert cdf_x_limit(np.full(10, 0.01), min_span=0.05) == 0.05


def test_cdf_draws_the_thresholds_inside_the_axis():
    trans = np.linspace(0.2, 2.5, 20)
    rot = np.linspace(0.1, 0.6, 20)
    fig = cdf_figure(trans, "translation error (cm)", METRIC_THRESHOLDS_CM, rot, np.zeros(20, bool), "t")
    a, b = fig.axes
    vertical = lambda ax: sorted(line.get_xdata()[0] for line in ax.get_lines()[1:])  # noqa: E731
    assert vertical(a) == [1.0, 2.0]  # 5 and 10 cm lie past the 3 cm axis
    assert vertical(b) == [1.0]
    assert ROTATION_THRESHOLDS_DEG == (1.0, 2.0, 5.0)
    assert RELATIVE_THRESHOLDS_PCT == pytest.approx((100 / 150, 200 / 150, 500 / 150))


def test_cdf_counts_the_errors_past_the_axis():
    errors = np.r_[np.linspace(0.1, 1.0, 19), 90.0]
    fig = cdf_figure(errors, "translation error (cm)", METRIC_THRESHOLDS_CM, errors, np.zeros(20, bool), "t")
    assert all(any(t.get_text().startswith("1 beyond") for t in ax.texts) for ax in fig.axes)


def _trajectory(n: int = 12, failed: tuple[int, ...] = (), missing: tuple[int, ...] = ()) -> tuple:
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    gt = np.c_[2 * np.cos(a), 0.05 * np.sin(3 * a), 2 * np.sin(a)]
    est = gt + np.random.default_rng(1).normal(0, 0.05, gt.shape)
    est[list(missing)] = np.nan
    mask = np.zeros(n, bool)
    mask[list(failed) + list(missing)] = True
    return gt, est, mask


def _legend(ax) -> list[str]:
    legend = ax.get_legend()
    assert legend is not None
    return [t.get_text() for t in legend.get_texts()]


def test_trajectory_tells_ground_truth_from_estimate():
    fig = trajectory_figure(*_trajectory(), "mini")
    (ax,) = fig.axes
    labels = _legend(ax)
    assert "ground truth" in labels and "estimate" in labels
    by_label = {c.get_label(): c for c in ax.collections}
    gt, est = by_label["ground truth"], by_label["estimate"]
    # different colours and different markers
    assert not np.allclose(gt.get_edgecolor()[0], est.get_facecolor()[0])
    assert gt.get_paths()[0].vertices.shape != est.get_paths()[0].vertices.shape or \
        not np.allclose(gt.get_paths()[0].vertices, est.get_paths()[0].vertices)
    # a line from each ground-truth position to its estimate
    assert len(_error_segments(ax)) == 12


def _error_segments(ax) -> list:
    """The ground-truth-to-estimate segments of the trajectory plot (one collection, one segment each)."""
    (lines,) = [c for c in ax.collections if c.get_label() == "error (ground truth to estimate)"]
    return [seg for seg in lines.get_segments() if len(seg) == 2]


def test_trajectory_marks_failures_and_missing_estimates():
    fig = trajectory_figure(*_trajectory(failed=(2,), missing=(5, 7)), "mini")
    (ax,) = fig.axes
    labels = _legend(ax)
    assert {"ground truth", "estimate", "estimate (failed)"} <= set(labels)
    assert any("2 queries without an estimate" in label for label in labels)
    assert len(_error_segments(ax)) == 10
