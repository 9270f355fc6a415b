"""The field's pieces: encoding derivatives, rendering weights, class weights, wound-bed
aggregation, per-frame gating, recipes; and a tiny end-to-end recovery of a two-class scene."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from labelsynth.classes import ClassInfo, ClassMap
from labelsynth.errors import RecipeError
from labelsynth.field.config import SemanticConfig, load_recipe
from labelsynth.field.encoding import HashGridEncoding
from labelsynth.field.rendering import OccupancyGrid, composite_weights, march, ray_box
from labelsynth.field.semantic import class_weights, decide_labels, wound_bed_logits, wound_bed_probability
from labelsynth.field.training import (
    LabelledFrame,
    bake_semantic_rays,
    resolve_class_weighting,
    semantic_iterations,
    weighted_cross_entropy,
)


def test_encoding_fast_path_matches_autograd_and_finite_differences():
    torch.manual_seed(0)
    enc = HashGridEncoding(levels=6, log2_table=10, base_resolution=4, max_resolution=64).double()
    enc.table.data.normal_()
    x = (torch.rand(40, 3, dtype=torch.float64) * 1.8 - 0.9).requires_grad_(True)
    weights = torch.randn(40, enc.output_dim, dtype=torch.float64)
    fast = (enc(x) * weights).sum()
    slow = (enc(x, twice_differentiable=True) * weights).sum()
    g_fast = torch.autograd.grad(fast, [x, enc.table])
    g_slow = torch.autograd.grad(slow, [x, enc.table])
    assert torch.allclose(fast, slow)
    assert torch.allclose(g_fast[0], g_slow[0], atol=1e-9)
    assert torch.allclose(g_fast[1], g_slow[1], atol=1e-12)
    h = 1e-6
    eye = torch.eye(3, dtype=torch.float64)
    f = lambda p: (enc(p) * weights).sum(-1)  # noqa: E731
    fd = torch.stack([(f(x + h * eye[k]) - f(x - h * eye[k])) / (2 * h) for k in range(3)], -1)
    per_point = torch.autograd.grad(f(x).sum(), x)[0]
    assert torch.allclose(per_point, fd, atol=1e-5)


def test_encoding_is_twice_differentiable_for_the_eikonal_loss():
    enc = HashGridEncoding(levels=4, log2_table=10, base_resolution=4, max_resolution=32)
    enc.table.data.normal_()
    x = (torch.rand(16, 3) * 1.6 - 0.8).requires_grad_(True)
    (g,) = torch.autograd.grad(enc(x, twice_differentiable=True).sum(), x, create_graph=True)
    (g.norm(dim=-1) - 1).pow(2).mean().backward()
    assert enc.table.grad is not None and enc.table.grad.abs().sum() > 0


def test_progressive_levels_zero_the_fine_features():
    enc = HashGridEncoding(levels=5, features_per_level=2, log2_table=10, base_resolution=4, max_resolution=64)
    enc.table.data.normal_()
    enc.set_active_levels(2)
    out = enc(torch.rand(8, 3) * 2 - 1)
    assert out.shape == (8, 10)
    assert torch.all(out[:, 4:] == 0) and torch.any(out[:, :4] != 0)


def test_ray_box_and_march_stay_in_the_cube():
    o = torch.tensor([[0.0, 0.0, 3.0], [5.0, 5.0, 5.0]])
    d = torch.tensor([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
    near, far = ray_box(o, d)
    assert math.isclose(near[0].item(), 2.0, abs_tol=1e-6) and math.isclose(far[0].item(), 4.0, abs_tol=1e-6)
    assert far[1] <= near[1]  # the second ray misses
    grid = OccupancyGrid(8)
    s = march(o, d, grid, steps=32, perturb=False)
    assert s.positions.shape[0] == 32 and bool((s.ray_index == 0).all())
    assert s.positions.abs().max() <= 1.0 + 1e-6


def test_composite_weights_match_a_per_ray_loop():
    torch.manual_seed(1)
    ray_index = torch.tensor([0, 0, 0, 2, 2, 3])
    alpha = torch.rand(6)
    w = composite_weights(alpha, ray_index, 4)
    expected = []
    for r in range(4):
        t = 1.0
        for a in alpha[ray_index == r]:
            expected.append(a * t)
            t *= 1 - a
    assert torch.allclose(w, torch.stack(expected), atol=1e-6)


def test_class_weights_follow_the_paper():
    cm = ClassMap.default()
    counts = np.array([1000, 300, 100, 0, 100, 0])  # background, granulation, slough, necrotic, epithelial, unknown
    w = class_weights(counts, cm)
    assert w[0] == pytest.approx(0.1)
    assert w[1] == pytest.approx(0.1 + 0.9 * 300 / 500)
    assert w[2] == pytest.approx(0.1 + 0.9 * 100 / 500)
    assert w[3] == pytest.approx(0.1)  # absent class keeps the floor
    assert w[4] == pytest.approx(0.1 + 0.9 * 100 / 500)


def test_class_weighting_schemes():
    cm = ClassMap.default()
    counts = np.array([1000, 300, 100, 0, 100, 0])
    u = class_weights(counts, cm, scheme="uniform")
    assert np.allclose(u, 1.0)
    eq = class_weights(counts, cm, background_weight=0.2, scheme="equal-tissue")
    assert eq.tolist() == pytest.approx([0.2, 1, 1, 1, 1, 1])
    inv = class_weights(counts, cm, scheme="inverse")
    # inverse frequency: every present class carries the same total weight; absent classes none
    totals = inv * counts
    assert np.allclose(totals[counts > 0], totals[0])
    assert inv[3] == 0 and inv[5] == 0
    assert (inv * counts).sum() == pytest.approx(counts.sum(), rel=1e-5)  # mean weight per pixel 1
    sq = class_weights(counts, cm, scheme="inverse-sqrt")
    assert sq[2] / sq[1] == pytest.approx(np.sqrt(3.0), rel=1e-5)
    with pytest.raises(ValueError, match="unknown class weighting"):
        class_weights(counts, cm, scheme="median")


def test_wound_bed_first_decision():
    cm = ClassMap.default()  # background, granulation, slough, necrotic, epithelial, unknown
    probs = np.array([
        [0.40, 0.35, 0.25, 0.0, 0.0, 0.0],  # bed 0.60 beats background: its likeliest tissue
        [0.60, 0.30, 0.10, 0.0, 0.0, 0.0],  # background wins outright
        [0.10, 0.20, 0.70, 0.0, 0.0, 0.0],  # plain tissue
    ])
    assert decide_labels(probs, cm, "argmax").tolist() == [0, 0, 2]
    assert decide_labels(probs, cm, "wound-bed-first").tolist() == [1, 0, 2]
    assert decide_labels(probs.reshape(3, 1, 6), cm).shape == (3, 1)
    # a class that is neither background nor wound bed competes with the bed as a whole
    other = ClassMap((ClassInfo(0, "background", (0, 0, 0)), ClassInfo(1, "a", (1, 1, 1), True),
                      ClassInfo(2, "b", (2, 2, 2), True), ClassInfo(3, "ruler", (3, 3, 3))))
    p2 = np.array([[0.1, 0.25, 0.2, 0.45], [0.1, 0.3, 0.3, 0.3]])
    assert decide_labels(p2, other).tolist() == [3, 1]
    with pytest.raises(ValueError, match="unknown decision rule"):
        decide_labels(probs, cm, "vote")


def test_wound_bed_is_log_sum_exp_of_tissue_logits():
    cm = ClassMap.default()
    logits = torch.tensor([[2.0, 0.5, 1.0, -1.0, 0.0, -3.0]])
    wb = wound_bed_logits(logits, cm)
    assert wb[0, 0] == pytest.approx(2.0)
    assert wb[0, 1].item() == pytest.approx(math.log(sum(math.exp(v) for v in [0.5, 1.0, -1.0, 0.0, -3.0])), rel=1e-6)
    p = wound_bed_probability(logits, cm)
    probs = torch.softmax(logits, -1)[0]
    assert p.item() == pytest.approx(probs[1:].sum().item(), rel=1e-6)  # same as summing tissue probabilities


def test_two_class_map_uses_the_object_as_wound_bed():
    cm = ClassMap((ClassInfo(0, "background", (0, 0, 0)), ClassInfo(1, "object", (255, 255, 255))))
    assert cm.wound_bed_indices == [1]


def test_weighted_cross_entropy_ignores_rays_of_weight_zero():
    logits = torch.tensor([[2.0, 0.0], [0.0, 2.0], [5.0, -5.0]])
    labels = torch.tensor([0, 1, 1])
    cw = torch.tensor([0.1, 1.0])
    with_gate = weighted_cross_entropy(logits, labels, cw, torch.tensor([1.0, 1.0, 0.0]))
    without = weighted_cross_entropy(logits[:2], labels[:2], cw, torch.tensor([1.0, 1.0]))
    assert with_gate.item() == pytest.approx(without.item())


def _plane_frames(n: int, size: int = 8):
    from labelsynth.cameras import Camera, look_at

    frames = []
    for i in range(n):
        cam = Camera(size, size, size, size, size / 2, size / 2, look_at([0.3 * i - 0.3, 0.1, 2.0], [0, 0, 0], (0, 1, 0)))
        mask = np.zeros((size, size), np.uint8)
        mask[:, size // 2 :] = 1
        frames.append(LabelledFrame(cam, mask, 1.0))
    return frames


def test_semantic_iterations_cover_the_labelled_rays():
    cfg = SemanticConfig(iterations=400, rays_per_batch=2048, min_epochs=1.0)
    assert semantic_iterations(cfg, 100_000) == 400  # few rays: the recipe's count stands
    assert semantic_iterations(cfg, 2_000_000) == math.ceil(2_000_000 / 2048)  # every ray once
    assert semantic_iterations(SemanticConfig(iterations=10, rays_per_batch=2048, min_epochs=2.0), 4096) == 10
    assert semantic_iterations(SemanticConfig(iterations=1, rays_per_batch=2048, min_epochs=2.0), 4096) == 4
    assert semantic_iterations(SemanticConfig(iterations=5, min_epochs=0.0), 10**7) == 5
    assert semantic_iterations(SemanticConfig(iterations=1, rays_per_batch=4096), 100) == 1  # batch <= rays


def test_frames_without_labels_contribute_no_rays():
    """Per-frame gating: a frame whose mask is all ignore adds nothing to the semantic stage."""
    from labelsynth.field.sdf import SDFConfig, SDFField

    torch.manual_seed(0)
    field = SDFField(SDFConfig(levels=2, log2_table=8, base_resolution=4, max_resolution=8, feature_dim=3))
    field.initialise_shape([[0.0, 0.0, -1.0]])
    grid = OccupancyGrid(16)
    cm = ClassMap((ClassInfo(0, "background", (0, 0, 0)), ClassInfo(1, "object", (255, 255, 255))))
    cfg = load_recipe("fast").semantic
    cfg.train_scale = 1.0
    frames = _plane_frames(2)
    baked = bake_semantic_rays(field, grid, frames, cm, cfg, steps=32, progress=False)
    unlabelled = LabelledFrame(frames[0].camera, np.full((8, 8), 255, np.uint8), 1.0)
    baked2 = bake_semantic_rays(field, grid, frames + [unlabelled], cm, cfg, steps=32, progress=False)
    assert len(baked) == 2 * 64 and len(baked2) == len(baked)
    assert np.array_equal(baked.class_counts, baked2.class_counts)
    assert torch.equal(baked.labels, baked2.labels)
    # the rays meet the plane: most of their weight lies on it
    assert float(baked.weights.sum(1).mean()) > 0.9
    # class_weighting auto: expert-only labels -> equal-tissue, any prediction -> uniform
    assert not baked.expert_only and resolve_class_weighting("auto", baked.expert_only) == "uniform"
    experts = [LabelledFrame(f.camera, f.mask, 1.0, f"e{i}", expert=True) for i, f in enumerate(frames)]
    baked_e = bake_semantic_rays(field, grid, experts, cm, cfg, steps=32, progress=False)
    assert baked_e.expert_only and resolve_class_weighting("auto", baked_e.expert_only) == "equal-tissue"
    assert baked_e.without({"e0"}).expert_only and len(baked_e.without({"e0"})) == 64
    assert resolve_class_weighting("paper", True) == "paper"


def test_recipes_load_and_reject_typos():
    for name in ("default", "fast", "quality", "paper"):
        r = load_recipe(name)
        assert r.geometry.iterations > 0 and r.semantic.dropout == pytest.approx(0.5)
    r = load_recipe("fast", ["geometry.iterations=7", "semantic.use_position=false"])
    assert r.geometry.iterations == 7 and r.semantic.use_position is False
    with pytest.raises(RecipeError, match="unknown key 'iteratons'"):
        load_recipe("fast", ["geometry.iteratons=7"])
    with pytest.raises(RecipeError, match="expected a int"):
        load_recipe("fast", ["geometry.iterations=many"])
    with pytest.raises(RecipeError, match="unknown recipe"):
        load_recipe("no-such-recipe")
    with pytest.raises(RecipeError, match="class_weighting: 'balanced' is not one of"):
        load_recipe("fast", ["semantic.class_weighting=balanced"])


def test_initial_shape_follows_how_the_cameras_see_a_plane():
    """A plane only for cameras that all look at it from one side, squarely enough.

    The lego of NeRF-synthetic (cameras on a hemisphere around the object) averages a mean
    viewing direction of length 0.575, above the 0.5 that once picked a plane; some of its
    cameras see any plane edge-on, so it must get the sphere."""
    from labelsynth.cameras import look_at
    from labelsynth.field.sdf import choose_init_shape

    def forwards(elevations_deg, azimuths_deg, target=(0.0, 0.0, 0.0)):
        out = []
        for el in np.radians(elevations_deg):
            for az in np.radians(azimuths_deg):
                eye = 3.0 * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
                out.append(-look_at(eye, np.asarray(target))[:3, 2])
        return np.array(out)

    hemisphere = forwards([5, 20, 35, 50, 65, 80], np.arange(0, 360, 30))  # lego-like
    assert np.linalg.norm(hemisphere.mean(0)) > 0.5  # what fooled the old rule
    assert choose_init_shape(hemisphere) == "sphere"
    assert choose_init_shape(forwards([0], np.arange(0, 360, 20))) == "sphere"  # an orbit
    assert choose_init_shape(forwards([40, 60, 80], np.arange(0, 300, 25))) == "plane"  # a phone's arc over a wound
    assert choose_init_shape(forwards([90], [0])) == "plane"  # one camera
    # a few stray oblique frames do not turn a one-sided capture into a sphere
    arc = forwards([50, 65, 80], np.arange(0, 360, 30))
    assert choose_init_shape(np.concatenate([arc, forwards([2], [0, 180])])) == "plane"


def test_contraction_keeps_the_cube_and_folds_the_rest_into_a_shell():
    from labelsynth.field.background import contract

    inside = torch.rand(100, 3) * 2 - 1
    assert torch.equal(contract(inside), inside)
    far = torch.randn(100, 3) * 1e4
    r = contract(far).abs().amax(-1)
    assert bool(((r > 1) & (r < 2)).all())
    edge = torch.tensor([[1.0, 0.3, -0.2]])
    assert torch.allclose(contract(edge * 1.0001), edge, atol=1e-3)  # continuous at the wall


def test_outer_background_starts_clear_and_runs_only_where_the_surface_lets_light_through():
    from labelsynth.field.encoding import sh_deg2
    from labelsynth.field.sdf import SDFConfig, SDFField

    torch.manual_seed(0)
    field = SDFField(SDFConfig(levels=2, log2_table=8, base_resolution=4, max_resolution=8, background="outer"))
    field.initialise_background([1.0, 1.0, 1.0])  # a white backdrop
    origins = torch.tensor([[0.0, 0.0, 3.0]]).repeat(6, 1)
    dirs = torch.nn.functional.normalize(torch.randn(6, 3), dim=-1)
    far = torch.full((6,), 2.5)
    rgb, transmittance = field.outer(origins, dirs, far)
    assert bool((transmittance > 0.9).all())  # transparent at the start: the backdrop shows
    full = field.get_background(dirs, origins, far)
    assert torch.allclose(full, torch.full_like(full, 0.98), atol=0.02)
    visible = torch.tensor([True, False, True, False, False, True])
    part = field.get_background(dirs, origins, far, visible=visible)
    env = torch.sigmoid(field.background(sh_deg2(dirs)))
    assert torch.allclose(part[visible], full[visible]) and torch.allclose(part[~visible], env[~visible])


def test_partial_occupancy_updates_agree_with_full_ones_while_the_surface_moves_little():
    radius = [0.5]

    def sdf(p):
        return p.norm(dim=-1) - radius[0]

    partial = OccupancyGrid(32, full_every=4, margin=0.1)
    full = OccupancyGrid(32, full_every=1)
    for step in range(9):
        radius[0] = 0.5 + 0.01 * step  # moves far less than the margin between updates
        partial.update(sdf, 0.05, jitter=False)
        full.update(sdf, 0.05, jitter=False)
        assert torch.equal(partial.occupied, full.occupied), step
    assert 0.0 < float(full.occupied.float().mean()) < 0.5
