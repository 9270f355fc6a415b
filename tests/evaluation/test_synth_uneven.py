"""The all-around-uneven layout: the all-around scene and wobbles of the same seed, the turn
dwelling on one side of the limb; the other layouts' paths unchanged."""

from __future__ import annotations

import numpy as np

from labelsynth.evaluation.synth import SynthConfig
from labelsynth.evaluation.synth.layouts import build_layout
from labelsynth.evaluation.synth.paths import UNEVEN_DWELL, UNEVEN_SHARE, turn_progress


def _angles(layout) -> np.ndarray:
    """Each camera's angle around the limb's axis (world x), unwrapped along the path."""
    rel = np.array([c.center for c in layout.cameras]) - layout.scene.axis_point
    return np.unwrap(np.arctan2(rel[:, 1], rel[:, 2]))


def test_the_uneven_turn_dwells_on_one_side():
    n = 40
    even = build_layout(SynthConfig(frames=n, width=32, height=24, seed=5, layout="all-around"))
    uneven = build_layout(SynthConfig(frames=n, width=32, height=24, seed=5, layout="all-around-uneven"))
    assert uneven.scene.describe() == even.scene.describe()
    assert np.array_equal(uneven.scene.vertices, even.scene.vertices)
    a, b = _angles(even), _angles(uneven)
    assert np.isclose(a[0], b[0], atol=1e-9)  # same start: only the speed differs
    dwell = int(UNEVEN_DWELL * n)
    slow = abs(b[dwell - 1] - b[0]) / (2 * np.pi)
    assert abs(slow - UNEVEN_SHARE) < 0.06  # 3/4 of the frames on a third of the turn (wobbles aside)
    steps = np.abs(np.diff(b))
    assert steps[dwell + 2:].mean() > 4 * steps[: dwell - 2].mean()  # the other side passed quickly
    t = np.arange(n) / n
    assert turn_progress(t, SynthConfig(frames=n, layout="all-around")) is t
    assert turn_progress(t, SynthConfig(frames=n, layout="one-sided")) is t
