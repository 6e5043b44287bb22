"""Figures: they draw what they are given and refuse nothing to draw."""

import pytest

from e2e_lite.viz import collision_chart, save_figure


def test_collision_chart_draws_each_driver_with_its_interval(tmp_path):
    rows = [
        ("a", {"collisions_per_100mi": 10.0, "ci95_per_100mi": [5.0, 18.0]}),
        ("b", {"collisions_per_100mi": 0.0, "ci95_per_100mi": [0.0, 3.7]}),
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
