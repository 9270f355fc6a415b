"""Robustness perturbations: geometry, locality, determinism, ignore handling."""

import numpy as np
import pytest

from labelsynth.errors import RecipeError
from labelsynth.evaluation.perturb import (
    apply_perturbation,
    boundary_band,
    boundary_jitter,
    dilate,
    disk_offsets,
    erode,
    erode_dilate,
    half_frames,
)


def disk(radius, size=101, cid=1):
    yy, xx = np.mgrid[:size, :size]
    c = size // 2
    m = np.zeros((size, size), np.uint8)
    m[(yy - c) ** 2 + (xx - c) ** 2 <= radius**2] = cid
    return m


def extent(mask):
    """Half-width of the region along the horizontal line through the centre."""
    row = mask[mask.shape[0] // 2]
    xs = np.nonzero(row)[0]
    return (xs.max() - xs.min()) // 2


def test_erosion_and_dilation_move_a_disk_boundary_by_radius():
    m = disk(20)
    e = erode(m, 3)
    d = dilate(m, 3, rng=0)
    assert extent(e) == 17 and extent(d) == 23
    assert e[50, 50 + 17] == 1 and e[50, 50 + 18] == 0
    assert d[50, 50 + 23] == 1 and d[50, 50 + 24] == 0
    # the whole shape, not just one row: within one pixel ring of the ideal disks
    assert np.count_nonzero(e != disk(17)) < 0.05 * np.count_nonzero(disk(17))
    assert np.count_nonzero(d != disk(23)) < 0.05 * np.count_nonzero(disk(23))


def test_erosion_moves_only_the_wound_boundary():
    m = np.zeros((40, 40), np.uint8)
    m[10:30, 10:20] = 1
    m[10:30, 20:30] = 2
    e = erode(m, 3)
    # tissue/tissue boundary kept: no background opens up between the two classes
    assert (e[13:27, 13:20] == 1).all() and (e[13:27, 20:27] == 2).all()
    assert (e[:13] == 0).all() and (e[27:] == 0).all()
    # the image border is not a wound boundary
    full = np.ones((10, 10), np.uint8)
    assert (erode(full, 3) == 1).all()


def test_dilation_grows_into_background_only_and_does_not_favour_high_ids():
    m = np.zeros((60, 60), np.uint8)
    m[20:40, 20:30] = 1
    m[20:40, 30:40] = 5
    d = dilate(m, 3, rng=1)
    nonbg = m != 0
    assert (d[nonbg] == m[nonbg]).all()  # classes never invade each other
    grown1 = np.count_nonzero((d == 1) & ~nonbg)
    grown5 = np.count_nonzero((d == 5) & ~nonbg)
    assert grown1 > 0 and abs(grown1 - grown5) <= 0.1 * grown1
    assert set(np.unique(d)) <= {0, 1, 5}


def test_ignore_is_preserved_and_never_spreads():
    m = disk(15)
    m[:, :30] = 255
    m[45:55, 45:55] = 255
    for out in (erode(m, 3), dilate(m, 3, rng=0), boundary_jitter(m, 3, rng=0)):
        assert ((out == 255) == (m == 255)).all()
    for name in ("erosion-dilation", "jitter"):
        out = apply_perturbation(name, {"f": m}, seed=3)["f"]
        assert ((out == 255) == (m == 255)).all()


def test_erode_dilate_chooses_both_and_is_deterministic():
    m = disk(20)
    results = [erode_dilate(m, 3, rng=s) for s in range(12)]
    areas = {int(np.count_nonzero(r)) for r in results}
    a0 = np.count_nonzero(m)
    assert any(a < a0 for a in areas) and any(a > a0 for a in areas)
    assert (erode_dilate(m, 3, rng=5) == erode_dilate(m, 3, rng=5)).all()


def _labels_within(mask, y, x, r):
    labels = set()
    for dy, dx in disk_offsets(r):
        qy, qx = y + dy, x + dx
        if 0 <= qy < mask.shape[0] and 0 <= qx < mask.shape[1]:
            labels.add(int(mask[qy, qx]))
    return labels


def test_jitter_is_local_and_uses_nearby_labels():
    m = disk(20)
    m[50:, :] = np.where(m[50:, :] == 1, 2, m[50:, :])  # two tissues and background
    band = boundary_band(m, 3)
    j = boundary_jitter(m, 3, rng=7)
    changed = j != m
    assert changed.any()
    assert not (changed & ~band).any()  # only band pixels change
    for y, x in zip(*np.nonzero(changed)):
        assert int(j[y, x]) in _labels_within(m, y, x, 3) - {int(m[y, x]), 255}
    # a band pixel is at most 3 px (Euclidean) from a pixel of another class
    ys, xs = np.nonzero(band)
    for y, x in list(zip(ys, xs))[::25]:
        assert len(_labels_within(m, y, x, 3)) >= 2
    # roughly: half the band is picked, a good share of picks land on another class
    frac = changed.sum() / band.sum()
    assert 0.05 < frac < 0.5
    assert (boundary_jitter(m, 3, rng=7) == j).all()
    assert not (boundary_jitter(m, 3, rng=8) == j).all()


def test_jitter_leaves_uniform_masks_alone():
    m = np.full((20, 20), 2, np.uint8)
    assert (boundary_jitter(m, 3, rng=0) == m).all()


def test_half_frames():
    names = [f"f{i:02d}" for i in range(50)]
    kept = half_frames(names)
    assert len(kept) == 25 and kept[0] == "f00" and kept[-1] == "f48"
    assert half_frames(list("abcdefg")) == ["a", "c", "e", "g"]  # 7 -> 4: ceil(N/2)
    assert half_frames([]) == []


def test_apply_perturbation_names_and_determinism():
    masks = {f"f{i}": disk(10 + i, size=64) for i in range(6)}
    assert all((apply_perturbation("none", masks)[k] == v).all() for k, v in masks.items())
    half = apply_perturbation("half-frames", masks)
    assert list(half) == ["f0", "f2", "f4"]
    for name in ("erosion-dilation", "jitter"):
        a = apply_perturbation(name, masks, seed=11)
        b = apply_perturbation(name, masks, seed=11)
        assert list(a) == list(masks)
        assert all((a[k] == b[k]).all() for k in a)
        # a frame's perturbation does not depend on the other frames in the set
        single = apply_perturbation(name, {"f3": masks["f3"]}, seed=11)
        assert (single["f3"] == a["f3"]).all()
        c = apply_perturbation(name, masks, seed=12)
        assert any((a[k] != c[k]).any() for k in a)
    assert masks["f0"].max() == 1  # inputs untouched
    underscored = apply_perturbation("erosion_dilation", masks, seed=11)  # aliases accepted
    assert all((underscored[k] == apply_perturbation("erosion-dilation", masks, seed=11)[k]).all() for k in masks)
    with pytest.raises(RecipeError, match="unknown perturbation"):
        apply_perturbation("blur", masks)


def test_rejects_non_2d():
    with pytest.raises(ValueError):
        erode(np.zeros((4, 4, 3), np.uint8))
