"""Golden values of the one NeuS weighting path (march -> SDF and gradient -> alpha -> weights).

The numbers were taken at a fixed seed from the two copies that existed before
``sampling.neus_weights`` (RGB rendering and the semantic bake); any change to the weights
along rays, deliberate or not, shows here first.
"""

from __future__ import annotations

import torch

from labelsynth.geometry.sampling import OccupancyGrid, march, neus_weights
from labelsynth.geometry.sdf import SDFConfig, SDFField
from labelsynth.geometry.training import render_rays_rgb
from labelsynth.semantics.training import sample_frozen

GOLDEN_OPACITY = [0.997788, 0.99969, 0.989378, 0.999592, 0.999921, 0.999815, 0.999325, 0.99995]
GOLDEN_RGB0 = [0.4968, 0.475567, 0.476478]
GOLDEN_TOP_WEIGHTS = [
    [0.096456, 0.09302, 0.092528, 0.083007],
    [0.103796, 0.099548, 0.099345, 0.088017],
    [0.078998, 0.077774, 0.075863, 0.072597],
]


def _scene():
    torch.manual_seed(0)
    field = SDFField(SDFConfig(levels=4, log2_table=12, max_resolution=64, background="env"))
    field.initialise_background([0.5, 0.5, 0.5])
    field.inv_s_floor.fill_(6.0)
    grid = OccupancyGrid(16)
    g = torch.Generator().manual_seed(1)
    origins = torch.tensor([[0.0, 0.0, 2.5]]).repeat(8, 1)
    dirs = torch.cat([torch.rand(8, 2, generator=g) * 0.4 - 0.2, -torch.ones(8, 1)], 1)
    return field, grid, origins, torch.nn.functional.normalize(dirs, dim=-1)


def test_rgb_rendering_weights_match_the_golden_values() -> None:
    field, grid, origins, dirs = _scene()
    rgb, opacity, _ = render_rays_rgb(field, grid, origins, dirs, 0.5, 64, train=False)
    torch.testing.assert_close(opacity.detach(), torch.tensor(GOLDEN_OPACITY), atol=2e-6, rtol=0)
    torch.testing.assert_close(rgb[0].detach(), torch.tensor(GOLDEN_RGB0), atol=2e-6, rtol=0)


def test_baked_sample_weights_match_the_golden_values() -> None:
    field, grid, origins, dirs = _scene()
    _, _, w = sample_frozen(field, grid, origins, dirs, 64, 4)
    torch.testing.assert_close(w[:3], torch.tensor(GOLDEN_TOP_WEIGHTS), atol=2e-6, rtol=0)


def test_one_path_serves_both() -> None:
    """The bake's weights are the rendering's weights of the same samples (cosine fully annealed)."""
    field, grid, origins, dirs = _scene()
    samples = march(origins, dirs, grid, steps=64, perturb=False)
    along = neus_weights(field, samples, cos_anneal_ratio=1.0, train=False)
    assert along.weights.shape == (samples.positions.shape[0],)
    opacity = torch.zeros(8).index_add(0, samples.ray_index, along.weights.detach())
    _, _, w = sample_frozen(field, grid, origins, dirs, 64, 64)
    torch.testing.assert_close(w.sum(1), opacity, atol=1e-6, rtol=0)
    # weights are T_i * alpha_i: never negative, never more than 1 per ray
    assert bool((along.weights >= 0).all()) and bool((opacity <= 1 + 1e-6).all())


def test_without_opacity_grad_the_colour_loss_reaches_the_sdf_only_through_the_feature() -> None:
    """``geometry.opacity_warmup``: the same weights, but no gradient from them to the SDF network
    or the sharpness; the colour head's input (the feature) still carries one."""
    field, grid, origins, dirs = _scene()
    field.variance.data.fill_(0.5)  # sharpness from the learned variance, not the floor
    samples = march(origins, dirs, grid, steps=64, perturb=False)
    with_grad = neus_weights(field, samples, 0.5, train=True)
    without = neus_weights(field, samples, 0.5, train=True, opacity_grad=False)
    torch.testing.assert_close(without.weights, with_grad.weights.detach())
    assert with_grad.weights.requires_grad and not without.weights.requires_grad
    bias = field.sdf_l1.bias  # [0] offsets the distance (moves the whole surface), [1:] the feature
    g_bias, g_var = torch.autograd.grad(with_grad.weights.sum(), [bias, field.variance])
    assert g_bias[0].abs() > 0 and g_var.abs() > 0
    (g_feat,) = torch.autograd.grad(without.feature.sum(), [bias])
    assert g_feat[1:].abs().sum() > 0

    # and through the whole colour rendering: the SDF's bias (which moves the whole surface)
    # gets a gradient only through the colour head's feature, none through opacity
    torch.manual_seed(3)  # training samples are jittered along the ray: the same jitter for both
    rgb, opacity, _ = render_rays_rgb(field, grid, origins, dirs, 0.5, 64, train=True, opacity_grad=False)
    assert not opacity.requires_grad
    torch.manual_seed(3)
    rgb_full, opacity_full, _ = render_rays_rgb(field, grid, origins, dirs, 0.5, 64, train=True)
    torch.testing.assert_close(rgb.detach(), rgb_full.detach())
    assert opacity_full.requires_grad
