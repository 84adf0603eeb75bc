"""The gradient diagnostics tool: statistics over seeds and the slice figure."""

from __future__ import annotations

import numpy as np
from test_score_gradient import gradient_medium, gradient_scene

from cloudct.retrieval.diagnostics import gradient_statistics, plot_gradient_slices


def test_gradient_statistics_and_figure(tmp_path):
    residual = np.ones((2, 6, 6))
    stats = gradient_statistics(
        gradient_medium(), gradient_scene(), residual, {"score": 4000, "drt": 2}, seeds=3
    )
    assert list(stats.estimator.values) == ["score", "drt"]
    assert stats["mean"].shape == (2, 6, 6, 6)
    assert np.all(stats["std"].values >= 0) and np.all(stats["seconds_per_estimate"] > 0)
    path = plot_gradient_slices(stats, tmp_path / "slices.png", z_index=2)
    assert path.exists() and path.stat().st_size > 1000
