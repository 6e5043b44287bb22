"""Figures: they draw what they are given and refuse nothing to draw."""

from types import SimpleNamespace

import pytest

from e2e_lite.driving.figures import collision_chart, save_figure


def _result(rate: float, ci: tuple[float, float]) -> SimpleNamespace:
    """What the chart reads of a result: its rate, its interval and its seeds (none)."""
    return SimpleNamespace(collisions_per_100mi=rate, ci95_per_100mi=ci, seeds=())


def test_collision_chart_draws_each_driver_with_its_interval(tmp_path):
    rows = [
        ("a", _result(10.0, (5.0, 18.0))),
        ("b", _result(0.0, (0.0, 3.7))),
    ]
    fig = collision_chart(rows, reference=[("paper", 12.7)])
    ax = fig.axes[0]
    assert [t.get_text() for t in ax.get_yticklabels()] == ["a", "b"]
    assert sorted(p.get_width() for p in ax.patches) == [0.0, 10.0]
    assert ax.get_xlim()[1] >= 18.0  # the widest interval fits
    path = save_figure(fig, tmp_path / "c.png")
    assert path.stat().st_size > 1000
    with pytest.raises(ValueError, match="at least one row"):
        collision_chart([])


def test_collision_chart_marks_each_row_and_can_use_a_log_axis():
    rows = [
        ("a", _result(800.0, (780.0, 820.0))),
        ("b", _result(0.5, (0.1, 2.0))),
    ]
    fig = collision_chart(rows, marks=[183.3, None], marks_label="paper", log=True)
    ax = fig.axes[0]
    assert ax.get_xscale() == "symlog" and ax.get_xlim()[1] >= 820.0
    (line,) = [ln for ln in ax.get_lines() if ln.get_label() == "paper"]
    assert list(line.get_xdata()) == [183.3] and list(line.get_ydata()) == [1]  # row "a" on top
    with pytest.raises(ValueError, match="marks"):
        collision_chart(rows, marks=[1.0])
