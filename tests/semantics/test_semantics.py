"""The semantic stage's pieces: class weights, wound-bed aggregation and decision, the
weighted loss, per-frame gating of the baked rays and the iteration count."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from labelsynth.classes import ClassInfo, ClassMap
from labelsynth.geometry.sampling import OccupancyGrid
from labelsynth.recipe import load_recipe
from labelsynth.semantics.config import SemanticConfig
from labelsynth.semantics.head import class_weights, decide_labels, wound_bed_logits, wound_bed_probability
from labelsynth.semantics.training import (
    LabelledFrame,
    bake_semantic_rays,
    resolve_class_weighting,
    semantic_iterations,
    weighted_cross_entropy,
)


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


def test_tissue_balanced_keeps_the_bed_against_background_and_lifts_rare_tissue():
    cm = ClassMap.default()
    counts = np.array([1000, 400, 100, 0, 100, 4])
    w = class_weights(counts, cm, scheme="tissue-balanced", tissue_power=0.5)
    assert w[0] == 1.0  # background as in the plain loss
    tissue = [1, 2, 4, 5]
    # the tissues together weigh what their pixels weigh: the bed against background is unbiased
    assert (w[tissue] * counts[tissue]).sum() == pytest.approx(counts[tissue].sum(), rel=1e-5)
    assert w[2] / w[1] == pytest.approx(2.0, rel=1e-5) and w[5] / w[2] == pytest.approx(5.0, rel=1e-5)
    assert w[3] == 0.0  # no pixels, no weight
    mild = class_weights(counts, cm, scheme="tissue-balanced", tissue_power=0.25)
    assert mild[2] / mild[1] == pytest.approx(2.0 ** 0.5, rel=1e-5)
    assert np.allclose(class_weights(counts, cm, scheme="tissue-balanced", tissue_power=0.0)[[0, 1, 2, 4, 5]], 1.0)


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
    from labelsynth.geometry.sdf import SDFConfig, SDFField

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
    # class_weighting auto: expert-only labels -> equal-tissue, any prediction -> tissue-balanced
    assert not baked.expert_only and resolve_class_weighting("auto", baked.expert_only) == "tissue-balanced"
    experts = [LabelledFrame(f.camera, f.mask, 1.0, f"e{i}", expert=True) for i, f in enumerate(frames)]
    baked_e = bake_semantic_rays(field, grid, experts, cm, cfg, steps=32, progress=False)
    assert baked_e.expert_only and resolve_class_weighting("auto", baked_e.expert_only) == "equal-tissue"
    assert baked_e.without({"e0"}).expert_only and len(baked_e.without({"e0"})) == 64
    assert resolve_class_weighting("paper", True) == "paper"


def test_threshold_dropout_keeps_the_mean_drops_p_and_is_off_in_eval():
    import torch

    from labelsynth.semantics.head import ThresholdDropout

    torch.manual_seed(0)
    drop = ThresholdDropout(0.5)
    x = torch.ones(200_000)
    y = drop.train()(x)
    assert abs(float((y == 0).float().mean()) - 0.5) < 0.01
    assert abs(float(y.mean()) - 1.0) < 0.02 and set(torch.unique(y).tolist()) == {0.0, 2.0}
    assert torch.equal(drop.eval()(x), x)


def test_a_dropout_of_one_or_more_is_a_one_line_recipe_error():
    import pytest

    from labelsynth.errors import RecipeError
    from labelsynth.recipe import load_recipe

    with pytest.raises(RecipeError, match=r"semantic.dropout: 1.0 is not in \[0, 1\)"):
        load_recipe("fast", ["semantic.dropout=1.0"])


def test_leave_one_out_heads_trained_together_each_leave_out_only_their_own_frame():
    """train_leave_one_out: three frames label the same points 1, 1 and 2. The head without the
    frame that says 2 must say 1; the heads without one of the frames that say 1 are taught 1
    by the other and 2 by the third, and must not have learnt from their own frame: where
    frames A and C disagree alone (B says nothing there) the head without A says C's class."""
    from dataclasses import replace

    from labelsynth.semantics.head import SemanticHead
    from labelsynth.semantics.training import BakedRays, train_leave_one_out

    classes = ClassMap.default()
    g = torch.Generator().manual_seed(0)
    n = 600
    pos = torch.rand(n, 1, 3, generator=g) * 1.6 - 0.8
    feats = torch.zeros(n, 1, 15)
    feats[..., 0] = torch.sign(pos[..., 0]) * 3.0  # the head can tell the two regions apart
    frames, labels = [], []
    # region x < 0: A says 1, C says 2 (B silent); region x >= 0: B says 1, C says 1
    left = pos[:, 0, 0] < 0
    for f, (lab_left, lab_right) in enumerate([(1, None), (None, 1), (2, 1)]):
        for i in range(n):
            lab = lab_left if bool(left[i]) else lab_right
            if lab is not None:
                frames.append(f)
                labels.append((i, lab))
    idx = torch.tensor([i for i, _ in labels])
    baked = BakedRays(
        positions=pos[idx], features=feats[idx], weights=torch.ones(len(idx), 1),
        labels=torch.tensor([lab for _, lab in labels]), ray_weight=torch.ones(len(idx)),
        frame_of_ray=torch.tensor(frames), frame_names=["A", "B", "C"],
        frame_class_counts=np.array([[0, 300, 0, 0, 0, 0], [0, 300, 0, 0, 0, 0], [0, 300, 300, 0, 0, 0]]),
        frame_expert=[True, True, True],
    )
    cfg = replace(load_recipe("fast").semantic, iterations=150, min_epochs=0.0, rays_per_batch=512, dropout=0.0)
    make = lambda: SemanticHead(15, classes.num_classes, 32, 0.0, None)  # noqa: E731
    heads = train_leave_one_out(make, baked, classes, cfg, ["A", "C"], seed=0)
    assert set(heads) == {"A", "C"}
    with torch.no_grad():
        left_pts = left.nonzero().squeeze(-1)
        say_a = heads["A"](feats[left_pts, 0], pos[left_pts, 0]).argmax(-1)  # taught only by C there
        say_c = heads["C"](feats[left_pts, 0], pos[left_pts, 0]).argmax(-1)  # taught only by A there
    assert float((say_a == 2).float().mean()) > 0.9
    assert float((say_c == 1).float().mean()) > 0.9


def _random_baked(n_rays: int = 300, k: int = 4, seed: int = 0):
    """Baked rays with random samples, a third of the slots of weight 0 (dropped or padding)."""
    from labelsynth.semantics.training import BakedRays

    g = torch.Generator().manual_seed(seed)
    weights = torch.rand(n_rays, k, generator=g) / k
    weights[torch.rand(n_rays, k, generator=g) < 0.33] = 0.0
    weights[0] = 0.0  # a ray that met nothing
    return BakedRays(
        positions=torch.rand(n_rays, k, 3, generator=g) * 1.6 - 0.8, features=torch.randn(n_rays, k, 15, generator=g),
        weights=weights, labels=torch.randint(0, 6, (n_rays,), generator=g), ray_weight=torch.ones(n_rays),
        frame_of_ray=torch.zeros(n_rays, dtype=torch.long), frame_names=["a"],
        frame_class_counts=np.full((1, 6), 50), frame_expert=[True],
    )


def _small_head(seed: int = 0, dropout: float = 0.0):
    from labelsynth.geometry.encoding import HashGridEncoding
    from labelsynth.semantics.head import SemanticHead

    torch.manual_seed(seed)
    enc = HashGridEncoding(levels=4, features_per_level=2, log2_table=10, base_resolution=4, max_resolution=32)
    return SemanticHead(15, 6, 16, dropout, enc)


def test_rendered_logits_skip_weightless_samples_without_changing_the_sum():
    """Paper Eq. 3 over the K cached samples: evaluating the head only where a sample carries
    weight gives the dense weighted sum (plus the unabsorbed rest as background)."""
    from labelsynth.semantics.training import BACKGROUND_LOGIT, LiveSamples, rendered_logits

    baked = _random_baked()
    head = _small_head().eval()
    rays = torch.arange(len(baked))
    live = LiveSamples.of(baked, rays)
    assert live.ray.numel() == int((baked.weights > 0).sum())  # the head sees only live samples
    with torch.no_grad():
        got = rendered_logits(head, live, background_index=0)
        r, k, _ = baked.positions.shape
        dense = head(baked.features.reshape(r * k, -1), baked.positions.reshape(r * k, 3)).reshape(r, k, -1)
        want = (baked.weights[..., None] * dense).sum(1)
        want[:, 0] += (1.0 - baked.weights.sum(1)).clamp(0, 1) * BACKGROUND_LOGIT
    assert torch.allclose(got, want, atol=1e-5)
    assert torch.allclose(got[0], torch.tensor([BACKGROUND_LOGIT, 0, 0, 0, 0, 0]))  # the empty ray
    # a batch drawn with repeats finds each ray's samples (slots count rays of ``baked``)
    batch = torch.tensor([5, 5, 17, 0, 299])
    sub = LiveSamples.of(baked, batch)
    assert torch.equal(sub.positions, baked.positions.reshape(-1, 3)[sub.slots])
    with torch.no_grad():
        assert torch.allclose(rendered_logits(head, sub, 0), got[batch], atol=1e-6)


def test_cached_grid_lookups_train_the_same_head_as_lookups_made_every_step():
    """``lookup_cache_mb`` is speed only: the head trained with the position lookups of every
    sample made once equals, parameter for parameter, the head trained looking them up per step."""
    from dataclasses import replace

    from labelsynth.semantics.training import train_semantic

    cm = ClassMap.default()
    cfg = replace(SemanticConfig(), iterations=30, min_epochs=0.0, rays_per_batch=64)
    heads = {}
    for budget in (0.0, 64.0):
        baked = _random_baked()
        head = _small_head(dropout=0.5)
        train_semantic(head, baked, cm, replace(cfg, lookup_cache_mb=budget), seed=1, progress=False)
        assert (baked._lookups is None) == (budget == 0.0)
        heads[budget] = head.state_dict()
    assert all(torch.equal(heads[0.0][k], heads[64.0][k]) for k in heads[0.0])


def test_batches_whose_rays_all_miss_the_surface_train_nothing_and_do_not_fail():
    """A field with no surface where the rays go (a failed geometry, a capture of backdrop only)
    bakes rays without a weighted sample: the head has nothing to learn there. Found on a tiny
    table capture whose geometry formed no object: loss.backward() raised on a constant loss."""
    from dataclasses import replace

    from labelsynth.semantics.training import train_leave_one_out, train_semantic

    cm = ClassMap.default()
    cfg = replace(SemanticConfig(), iterations=5, min_epochs=0.0, rays_per_batch=64)
    baked = _random_baked()
    baked.weights.zero_()
    head = _small_head()
    before = {k: v.clone() for k, v in head.state_dict().items()}
    stats = train_semantic(head, baked, cm, cfg, seed=1, progress=False)
    assert stats.iterations == 5
    assert all(torch.equal(before[k], v) for k, v in head.state_dict().items())
    heads = train_leave_one_out(lambda: _small_head(), baked, cm, cfg, ["a"], seed=1)
    assert set(heads) == {"a"}


def test_baking_drops_samples_below_the_minimum_weight():
    from labelsynth.geometry.sdf import SDFConfig, SDFField
    from labelsynth.semantics.training import sample_frozen

    torch.manual_seed(0)
    field = SDFField(SDFConfig(levels=2, log2_table=8, base_resolution=4, max_resolution=8, feature_dim=3))
    field.initialise_shape([[0.0, 0.0, -1.0]])
    grid = OccupancyGrid(16)
    origins = torch.tensor([[0.0, 0.0, -0.9]]).repeat(16, 1) + torch.rand(16, 3) * 0.1
    dirs = torch.tensor([[0.0, 0.0, 1.0]]).repeat(16, 1)
    _, _, every = sample_frozen(field, grid, origins, dirs, 64, 8)
    _, _, kept = sample_frozen(field, grid, origins, dirs, 64, 8, min_weight=0.01)
    assert bool(((every > 0) & (every < 0.01)).any())  # there are light samples to drop
    assert torch.equal(kept, torch.where(every >= 0.01, every, torch.zeros(())))
    # highest first: the kept ones are a prefix of each ray's slots
    assert bool((kept[:, 1:] <= kept[:, :-1]).all())
