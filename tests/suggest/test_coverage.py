"""Greedy surface coverage on known surfaces (no fitting): what a frame sees, how well, counted once."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from labelsynth.cameras import Camera, look_at
from labelsynth.capture.select import select_frames
from labelsynth.errors import LabelsynthError
from labelsynth.options import SuggestOptions
from labelsynth.render.surface import SurfaceCaster
from labelsynth.suggest import SuggestResult
from labelsynth.suggest.coverage import CoverageConfig, surface_views, view_density

SIZE = 32


def _camera(azimuth_deg: float, elevation_deg: float = 20.0, radius: float = 3.0, size: int = SIZE) -> Camera:
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    eye = radius * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    return Camera(size, size, 1.1 * size, 1.1 * size, size / 2, size / 2, look_at(eye, np.zeros(3)))


def _one_sided_path() -> tuple[list[Camera], list[str]]:
    """Seven frames dwelling on one side of a ball (azimuth 0-60 degrees), one on the far side last:
    spread:2 picks frames 2 and 6, both on the near side."""
    azimuths = [0, 10, 20, 30, 40, 50, 60, 200]
    return [_camera(a) for a in azimuths], [f"f{i}" for i in range(len(azimuths))]


def test_greedy_covers_what_spread_misses_and_counts_each_point_once():
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.6)
    cams, names = _one_sided_path()
    views = surface_views(ball, cams, names, CoverageConfig(samples=4000), progress=False)
    assert views.quality.shape == (8, 4000) and views.quality.min() >= 0 and views.quality.max() == pytest.approx(1.0)
    assert views.coverage(list(range(8))) == pytest.approx(1.0)
    picks = views.greedy(2)
    spread = [names.index(n) for n in select_frames("spread:2", names)]
    assert spread == [2, 6]
    assert "f7" in [p.name for p in picks]  # the only frame of the far side
    assert picks[-1].coverage > views.coverage(spread) + 0.15
    # gains add up to the coverage and never grow (submodular); a frame seen already adds nothing
    more = views.greedy(5)
    assert [p.name for p in more[:2]] == [p.name for p in picks]
    assert sum(p.gain for p in more) == pytest.approx(more[-1].coverage)
    assert all(a.gain >= b.gain - 1e-9 for a, b in zip(more, more[1:]))
    twin = surface_views(ball, cams + [cams[7]], names + ["f7-again"], CoverageConfig(samples=4000), progress=False)
    again = twin.greedy(3)
    assert "f7-again" not in [p.name for p in again[:2]]
    assert twin.coverage([7, 8]) == pytest.approx(twin.coverage([7]))


def test_a_point_counts_by_how_close_and_square_it_is_seen():
    plate = trimesh.creation.box(extents=(1.0, 1.0, 0.02))  # top face at z = 0.01, normal +z
    caster = SurfaceCaster(plate)
    point, normal = np.array([[0.0, 0.0, 0.01]]), np.array([[0.0, 0.0, 1.0]])

    def overhead(height: float, tilt_deg: float = 0.0) -> Camera:
        t = np.radians(tilt_deg)
        eye = height * np.array([np.sin(t), 0.0, np.cos(t)])
        return Camera(SIZE, SIZE, 40.0, 40.0, SIZE / 2, SIZE / 2, look_at(eye, np.zeros(3), up=(0, 1, 0)))

    def expected(cam: Camera) -> float:
        ray = point[0] - cam.center
        return 40.0 * float(-ray @ normal[0] / np.linalg.norm(ray)) / float(ray @ cam.forward)  # f cos / depth

    near, far, oblique = (overhead(*a) for a in ((1.0,), (2.0,), (1.0, 60.0)))
    got = [view_density(point, normal, cam, caster, 1e-3)[0] for cam in (near, far, oblique)]
    assert got == pytest.approx([expected(near), expected(far), expected(oblique)], rel=1e-6)
    assert got[0] == pytest.approx(40.0 / 0.99) and got[1] < 0.5 * got[0]  # square; twice as far: half as dense
    assert got[2] == pytest.approx(0.5 * got[0], rel=0.03)  # 60 degrees off the normal: cos 60
    below = view_density(point, normal, overhead(-1.0), caster, 1e-3)[0]
    assert below == 0.0  # facing away


def test_a_hidden_point_is_not_seen():
    front = trimesh.creation.box(extents=(1.0, 1.0, 0.02))
    back = front.copy()
    back.apply_translation((0.0, 0.0, -0.5))
    both = trimesh.util.concatenate([front, back])
    caster = SurfaceCaster(both)
    cam = Camera(SIZE, SIZE, 40.0, 40.0, SIZE / 2, SIZE / 2, look_at(np.array([0.0, 0.0, 2.0]), np.zeros(3), up=(0, 1, 0)))
    points = np.array([[0.0, 0.0, 0.01], [0.0, 0.0, -0.49]])  # the front plate's top, the back plate's top
    density = view_density(points, np.array([[0.0, 0.0, 1.0]] * 2), cam, caster, 1e-3)
    assert density[0] > 0 and density[1] == 0.0
    outside = view_density(np.array([[5.0, 0.0, 0.01]]), np.array([[0.0, 0.0, 1.0]]), cam, caster, 1e-3)
    assert outside[0] == 0.0  # projects outside the image


def test_nothing_to_cover_is_one_line():
    empty = trimesh.Trimesh(vertices=np.zeros((0, 3)), faces=np.zeros((0, 3), dtype=np.int64))
    with pytest.raises(LabelsynthError, match="the fitted surface is empty"):
        surface_views(empty, [_camera(0)], ["a"], progress=False)
    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.3)
    away = Camera(SIZE, SIZE, 40.0, 40.0, SIZE / 2, SIZE / 2, look_at(np.array([3.0, 0, 0]), np.array([6.0, 0, 0])))
    with pytest.raises(LabelsynthError, match="no frame sees the fitted surface"):
        surface_views(ball, [away], ["a"], progress=False)


@pytest.mark.parametrize("k", range(1, 7))
def test_every_k_from_one_to_six_names_k_frames(k, tmp_path):
    """K = 1..6 are all choices: K distinct frames, the first K of the longest choice (so a
    suggest run for 6 answers every smaller K), coverage growing with K, printed as such."""
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.6)
    cams, names = _one_sided_path()
    views = surface_views(ball, cams, names, CoverageConfig(samples=2000), progress=False)
    picks, longest = views.greedy(k), views.greedy(6)
    assert len({p.index for p in picks}) == k and [p.name for p in picks] == [p.name for p in longest[:k]]
    assert all(a.coverage <= b.coverage + 1e-12 for a, b in zip(longest, longest[1:]))
    spread = [names.index(n) for n in select_frames(f"spread:{k}", names)]
    result = SuggestResult(out=tmp_path / "s", capture=tmp_path / "cap", picks=picks, coverage=picks[-1].coverage,
                           spread=[names[i] for i in spread], spread_coverage=views.coverage(spread),
                           options=SuggestOptions(annotate=k))
    text = result.summary()
    assert text.startswith("annotate this frame" if k == 1 else f"annotate these {k} frames")
    assert all(f"{i + 1}. {p.name}" in text for i, p in enumerate(picks)) and f"spread:{k} (" in text
    assert result.expand_command() == f"labelsynth expand {tmp_path / 'cap'} --out OUT --geometry {tmp_path / 's'}"


def test_frame_objective_shares_and_local_optimum():
    """The frame objective: a teacher's share of a frame's view, and a choice no single swap improves."""
    from itertools import combinations

    from labelsynth.suggest import SurfaceViews

    rng = np.random.default_rng(0)
    quality = np.where(rng.random((8, 200)) < 0.4, rng.random((8, 200)), 0.0).astype(np.float32)
    views = SurfaceViews([f"f{i}" for i in range(8)], np.zeros((200, 3)), np.zeros((200, 3)), quality, 1.0)
    shares = views.teacher_shares()
    assert np.allclose(np.diag(shares), 1.0) and (shares >= 0).all() and (shares <= 1 + 1e-9).all()
    i, j = 2, 5  # by hand: the share of frame j's view that frame i sees as well
    assert np.isclose(shares[i, j], np.minimum(quality[i], quality[j]).sum() / quality[j].sum(), rtol=1e-5)
    w = rng.random(200).astype(np.float32)  # weighted samples count by their weight in both sums
    assert np.isclose(views.weighted(w).teacher_shares()[i, j],
                      (w * np.minimum(quality[i], quality[j])).sum() / (w * quality[j]).sum(), rtol=1e-5)
    for k in (2, 3):
        picks = views.frame_choice(k)
        assert len(set(picks)) == k and picks == sorted(picks)
        score = views.frame_score(picks)
        for slot in range(k):
            for c in set(range(8)) - set(picks):
                assert views.frame_score(picks[:slot] + [c] + picks[slot + 1:]) <= score + 1e-12
        best = max(views.frame_score(list(s)) for s in combinations(range(8), k))
        assert score >= best - 0.05  # a local optimum, close to the best subset on this small case
        ordered = views.ordered(picks)  # the same frames, in greedy surface order, gains adding up
        assert sorted(p.index for p in ordered) == picks
        assert sum(p.gain for p in ordered) == pytest.approx(views.coverage(picks))
    with pytest.raises(LabelsynthError):
        views.frame_choice(9)


def test_frame_objective_gives_each_group_of_frames_a_teacher():
    """Frames 0-2 see points 0-49 and frames 3-5 points 50-99: one teacher per group, where surface
    coverage is indifferent to which frames it takes as long as both halves are seen."""
    from labelsynth.suggest import SurfaceViews

    quality = np.zeros((6, 100), np.float32)
    quality[:3, :50] = 1.0
    quality[3:, 50:] = 1.0
    views = SurfaceViews([f"f{i}" for i in range(6)], np.zeros((100, 3)), np.zeros((100, 3)), quality, 1.0)
    picks = views.frame_choice(2)
    assert sum(p < 3 for p in picks) == 1 and views.frame_score(picks) == 1.0


def test_frame_objective_prefers_a_teacher_that_sees_a_frame_whole():
    """Frame 0 sees all 99 points, poorly (0.3); frames 1-3 each see one third, well. Surface
    coverage takes two of the thirds (each adds more than frame 0); the frame objective takes frame
    0 and one third: frame 0's view then has one teacher, and frame 0 teaches the other two thirds'
    frames a little."""
    from labelsynth.suggest import SurfaceViews

    quality = np.zeros((4, 99), np.float32)
    quality[0] = 0.3
    for f in (1, 2, 3):
        quality[f, 33 * (f - 1):33 * f] = 1.0
    views = SurfaceViews([f"f{i}" for i in range(4)], np.zeros((99, 3)), np.zeros((99, 3)), quality, 1.0)
    assert sorted(p.index for p in views.greedy(2)) == [1, 2]
    choice = views.frame_choice(2)
    assert 0 in choice and views.frame_score(choice) > views.frame_score([1, 2]) + 0.05


def test_rare_colours_weigh_more_and_a_single_colour_weighs_alike():
    from labelsynth.suggest.coverage import appearance_weights

    rng = np.random.default_rng(0)
    skin = np.clip(np.array([0.85, 0.65, 0.55]) + rng.normal(0, 0.02, (900, 3)), 0, 1)
    tissue = np.clip(np.array([0.55, 0.05, 0.05]) + rng.normal(0, 0.02, (100, 3)), 0, 1)
    colours = np.concatenate([skin, tissue, np.full((5, 3), np.nan)]).astype(np.float32)
    w = appearance_weights(colours, CoverageConfig(weight_cap=50.0))
    assert np.all(w[-5:] == 0) and np.all(w[:-5] > 0)  # no colour: no weight
    assert np.median(w[:1000]) == pytest.approx(1.0, rel=0.05)
    # a tenth as dense: about sqrt(10) times the weight (inverse square root of the density)
    assert 2.0 < np.median(w[900:1000]) / np.median(w[:900]) < 5.0
    capped = appearance_weights(colours, CoverageConfig(weight_cap=2.0))
    assert capped.max() <= 2.0 + 1e-6
    flat = appearance_weights(np.full((50, 3), 0.5, np.float32))  # one exact colour: the floor keeps weights alike
    assert flat == pytest.approx(np.ones(50))


def test_colours_are_read_where_the_best_frame_sees_each_sample():
    from labelsynth.suggest.coverage import surface_colours

    plate = trimesh.creation.box(extents=(1.0, 1.0, 0.02))
    cam = Camera(SIZE, SIZE, 20.0, 20.0, SIZE / 2, SIZE / 2, look_at(np.array([0.0, 0.0, 2.0]), np.zeros(3), up=(0, 1, 0)))
    away = Camera(SIZE, SIZE, 20.0, 20.0, SIZE / 2, SIZE / 2, look_at(np.array([0.0, 0.0, -2.0]), np.zeros(3), up=(0, 1, 0)))
    views = surface_views(plate, [away, cam], ["under", "over"], CoverageConfig(samples=3000), progress=False)
    image = np.zeros((SIZE, SIZE, 3), np.uint8)
    image[:, : SIZE // 2] = (200, 30, 30)  # left half red, right half grey
    image[:, SIZE // 2:] = (120, 120, 120)
    loaded = []

    def load(i: int) -> np.ndarray:
        loaded.append(i)
        return image if i == 1 else np.full_like(image, 255)

    colours = surface_colours(views, [away, cam], load, blur=1, progress=False)
    top = views.quality[1] >= views.quality[0]
    top &= views.quality[1] > 0
    pix, _ = cam.project(views.points[top])
    left, right = pix[:, 0] < SIZE / 2 - 1, pix[:, 0] >= SIZE / 2 + 1
    assert np.allclose(colours[top][left], np.array([200, 30, 30]) / 255, atol=1e-6)
    assert np.allclose(colours[top][right], np.array([120, 120, 120]) / 255, atol=1e-6)
    assert np.isnan(colours[~views.seen]).all() and sorted(set(loaded)) == [0, 1]  # each frame read once


def test_weighted_coverage_follows_the_heavy_samples():
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.6)
    cams, names = _one_sided_path()
    views = surface_views(ball, cams, names, CoverageConfig(samples=4000), progress=False)
    assert views.greedy(1)[0].name != "f0"
    heavy = np.where(views.quality[0] >= views.quality.max(axis=0) - 1e-6, 1.0, 0.0) * (views.quality[0] > 0)
    weighted = views.weighted(heavy + 1e-3)  # nearly all the weight where f0 sees best
    assert weighted.greedy(1)[0].name == "f0"
    q = views.quality[[0, 7]].max(axis=0)
    full = views.quality.max(axis=0)
    assert weighted.coverage([0, 7]) == pytest.approx(float(((heavy + 1e-3) * q).sum() / ((heavy + 1e-3) * full).sum()), rel=1e-5)
    assert views.weighted(None).coverage([0, 7]) == pytest.approx(views.coverage([0, 7]))
