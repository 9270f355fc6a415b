"""benchmarks/suggest_frame_objective.py's choice (issue 27's lead): shares are view overlaps, and
the choice is a local optimum that no single swap improves."""

from __future__ import annotations

from itertools import combinations

import numpy as np

from .conftest import load_benchmark


def _module():
    return load_benchmark("suggest_frame_objective.py")


def test_shares_and_choice() -> None:
    m = _module()
    rng = np.random.default_rng(0)
    quality = np.where(rng.random((8, 200)) < 0.4, rng.random((8, 200)), 0.0).astype(np.float32)
    shares = m.teacher_shares(quality)
    assert np.allclose(np.diag(shares), 1.0) and (shares >= 0).all() and (shares <= 1 + 1e-9).all()
    i, j = 2, 5  # by hand: the share of frame j's view that frame i sees as well
    assert np.isclose(shares[i, j], np.minimum(quality[i], quality[j]).sum() / quality[j].sum(), rtol=1e-5)
    for k in (2, 3):
        picks = m.choose(shares, k)
        assert len(set(picks)) == k
        score = m.frame_score(shares, picks)
        for slot in range(k):
            for c in set(range(8)) - set(picks):
                assert m.frame_score(shares, picks[:slot] + [c] + picks[slot + 1:]) <= score + 1e-12
        best = max(m.frame_score(shares, list(s)) for s in combinations(range(8), k))
        assert score >= best - 0.05  # a local optimum, close to the best subset on this small case


def test_two_groups_get_one_teacher_each() -> None:
    """Frames 0-2 see points 0-49, frames 3-5 points 50-99: two teachers, one per group."""
    m = _module()
    quality = np.zeros((6, 100), np.float32)
    quality[:3, :50] = 1.0
    quality[3:, 50:] = 1.0
    picks = m.choose(m.teacher_shares(quality), 2)
    assert sum(p < 3 for p in picks) == 1 and m.frame_score(m.teacher_shares(quality), picks) == 1.0
