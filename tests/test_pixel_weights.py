"""vae_pixel_weighting: the reconstruction term of eq 8 with rare colours weighted up (PixelWeights)."""

import math

import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from torch.nn import functional as F

from sb3_gocu import GoalCuriosityModule
from sb3_gocu.curiosity.networks import ConvVAE, MlpVAE, PixelWeights, vae_loss

from conftest import SMALL_CURIOSITY, ChainEnv

IMAGE_SPACE = spaces.Box(0, 255, (8, 8, 3), np.uint8)


def test_colour_ids_by_hand():
    """RGB keeps 5 bits a channel (255, 128, 0 -> 31, 16, 0); grey keeps all 8."""
    rgb = th.tensor([1.0, 128 / 255, 0.0]).view(1, 3, 1, 1)
    assert PixelWeights.colour_ids(rgb).tolist() == [[[31 * 1024 + 16 * 32 + 0]]]
    grey = th.tensor([[0.0, 128 / 255], [1.0, 7 / 255]]).view(1, 1, 2, 2)
    assert PixelWeights.colour_ids(grey).tolist() == [[[0, 128], [255, 7]]]
    two = th.tensor([1.0, 1 / 255]).view(1, 2, 1, 1)  # 7 bits a channel: 127 << 7 | 0
    assert PixelWeights.colour_ids(two).tolist() == [[[127 * 128]]]


def grey_batches():
    """Image A (weight 3): pixels 0, 0; image B (weight 1): pixels 0, 255. Colour 0 holds 7 of the 8 weighted
    pixels, colour 255 holds 1."""
    x = th.tensor([[0.0, 0.0], [0.0, 1.0]]).view(2, 1, 1, 2)
    return [(x[:1], th.tensor([3.0])), (x[1:], th.tensor([1.0]))]


@pytest.mark.parametrize("exponent, w_common, w_rare", [
    (0.0, 1.0, 1.0),
    (1.0, 4 / 7, 4.0),  # raw 8/7 and 8, scaled by 1 / (7/8 * 8/7 + 1/8 * 8) = 1/2
    (0.5, math.sqrt(8 / 7) / (math.sqrt(7 / 8) + math.sqrt(1 / 8)), math.sqrt(8) / (math.sqrt(7 / 8) + math.sqrt(1 / 8))),
])
def test_fitted_weights_by_hand(exponent, w_common, w_rare):
    pw = PixelWeights.fit(grey_batches(), exponent)
    assert pw.table.shape == (256,)
    assert pw.table[0].item() == pytest.approx(w_common, rel=1e-6)
    assert pw.table[255].item() == pytest.approx(w_rare, rel=1e-6)
    assert pw.table[128].item() == pytest.approx(w_rare, rel=1e-6), "an unseen colour weighs as the rarest seen"
    assert (7 * pw.table[0] + pw.table[255]).item() / 8 == pytest.approx(1.0, rel=1e-6), "mean pixel weight 1"
    x = th.tensor([0.0, 1.0, 128 / 255]).view(1, 1, 1, 3)
    assert pw(x).shape == (1, 1, 3)
    assert pw(x).flatten().tolist() == pytest.approx([w_common, w_rare, w_rare], rel=1e-6)


def test_weighted_reconstruction_term_by_hand():
    """The reconstruction term is the BCE of each channel times its pixel's weight, summed over the image."""
    th.manual_seed(0)
    vae = ConvVAE((3, 4, 4), embed_dim=8, latent_dim=2).eval()
    x = (th.rand(2, 3, 4, 4, generator=th.Generator().manual_seed(1)) > 0.8).float()  # mostly black: black weighs less
    pw = PixelWeights.fit([(x, th.ones(2))], 0.5)
    _, recon, kl = vae_loss(vae, x, 1.0, pixel_weights=pw)
    logits = vae(x)[0]
    bce = F.binary_cross_entropy_with_logits(logits, x, reduction="none")
    expected = (bce * pw(x)[:, None]).sum((1, 2, 3)).mean()
    assert recon.item() == pytest.approx(expected.item(), rel=1e-5)
    unweighted = vae_loss(vae, x, 1.0)
    assert unweighted[1].item() == pytest.approx(bce.sum((1, 2, 3)).mean().item(), rel=1e-5)
    assert recon.item() != pytest.approx(unweighted[1].item(), rel=1e-3), "the weights change the term"
    assert kl.item() == pytest.approx(unweighted[2].item(), rel=1e-6), "the KL term is not weighted"


def test_bad_pixel_weights_are_refused():
    with pytest.raises(ValueError, match=r"exponent must be in \[0, 1\], got 1.5"):
        PixelWeights.fit(grey_batches(), 1.5)
    with pytest.raises(ValueError, match="at least one image of positive weight"):
        PixelWeights.fit([(th.zeros(1, 1, 2, 2), th.zeros(1))], 0.5)
    pw = PixelWeights.fit(grey_batches(), 0.5)
    with pytest.raises(ValueError, match="x must have 1 channels .* got 3"):
        pw(th.zeros(1, 3, 2, 2))
    with pytest.raises(ValueError, match=r"table must have shape \(32768,\) for 3 channels, got \(256,\)"):
        PixelWeights(th.ones(256), 3)
    with pytest.raises(ValueError, match=r"pixel weights need images in \[0, 1\] .* got values in \[0.0, 2.0\]"):
        pw(th.tensor([0.0, 2.0]).view(1, 1, 1, 2))
    with pytest.raises(ValueError, match="pixel_weights apply to a ConvVAE .* got MlpVAE"):
        vae_loss(MlpVAE((4,), embed_dim=8, latent_dim=2), th.rand(2, 4), pixel_weights=pw)


def module(**kwargs) -> GoalCuriosityModule:
    return GoalCuriosityModule(
        IMAGE_SPACE, n_goals=4, goal_buffer_size=32, predictor_hidden=(32,), embed_dim=16, latent_dim=3,
        vae_batch_size=16, vae_epochs=2, vae_patience=1, memory_size=64, seed=0, **kwargs
    )


@pytest.mark.parametrize("value", [-0.1, 1.01, True, "0.5"])
def test_vae_pixel_weighting_is_checked(value):
    with pytest.raises(ValueError, match=r"vae_pixel_weighting must be None or in \[0, 1\], got "):
        module(vae_pixel_weighting=value)


def test_vae_pixel_weighting_needs_images():
    with pytest.raises(ValueError, match="vae_pixel_weighting applies to image observations, got 0.5"):
        GoalCuriosityModule(ChainEnv().observation_space, **{**SMALL_CURIOSITY, "vae_pixel_weighting": 0.5})


def test_the_default_weighting_is_0_5_for_images_and_none_for_vectors():
    assert module().vae_pixel_weighting == 0.5
    assert GoalCuriosityModule(ChainEnv().observation_space, **SMALL_CURIOSITY).vae_pixel_weighting == 0.0
    assert GoalCuriosityModule(ChainEnv().observation_space, **{**SMALL_CURIOSITY, "vae_pixel_weighting": 0}).vae_pixel_weighting == 0.0


def fill(m: GoalCuriosityModule) -> np.ndarray:
    """A bank of 48 distinct grey-and-black images, 6 of them with a yellow pixel (a rare colour)."""
    images = np.zeros((48, 8, 8, 3), np.uint8)
    images[:, :2] = 100
    images[np.arange(48), 2 + np.arange(48) // 8, np.arange(48) % 8] = 60
    images[:6, 0, 0] = (250, 220, 10)
    m.memory.add(m.adapter.extract(images), np.random.default_rng(1))
    return images


def test_a_vae_update_fits_the_weights_to_its_observations_and_trains_on_them():
    weighted, plain = module(vae_pixel_weighting=0.5), module(vae_pixel_weighting=0)
    fill(weighted), fill(plain)
    job = weighted.vae_job()
    data = np.concatenate([job.data, job.val_data])
    weights = np.concatenate([job.weights, job.val_weights])
    expected = PixelWeights.fit([(weighted.adapter.to_tensor(data), th.from_numpy(weights))], 0.5)
    assert th.allclose(job.pixel_weights.table, expected.table, rtol=1e-6)
    yellow = PixelWeights.colour_ids(th.tensor([250, 220, 10]).view(1, 3, 1, 1) / 255.0).item()
    assert job.pixel_weights.table[yellow] > 5 * job.pixel_weights.table[0], "the rare colour weighs more"
    assert plain.vae_job().pixel_weights is None, "exponent 0 is the paper's loss, unweighted"
    weighted.train_vae(patience=0)
    plain.train_vae(patience=0)
    assert weighted.stats["vae_loss"] != pytest.approx(plain.stats["vae_loss"], rel=1e-3)
    a, b = weighted.vae.state_dict(), plain.vae.state_dict()
    assert any(not th.equal(a[k], b[k]) for k in a), "same seed, other loss: other weights"


def test_a_state_carries_its_weighting_and_an_older_state_trained_without_it():
    saved = module(vae_pixel_weighting=0.25).state_dict()
    assert saved["settings"] == {"vae_pixel_weighting": 0.25}
    restored = module()  # the default, 0.5 for images
    restored.load_state_dict(saved)
    assert restored.vae_pixel_weighting == 0.25, "a resumed run keeps the loss it trained with"
    older = {k: v for k, v in saved.items() if k != "settings"}  # as saved before the setting existed
    by_default = module()
    by_default.load_state_dict(older)
    assert by_default.vae_pixel_weighting == 0.0, "an older state's VAE trained with every pixel weighing 1"
    explicit = module(vae_pixel_weighting=0.5)
    explicit.load_state_dict(older)
    assert explicit.vae_pixel_weighting == 0.5, "a value given explicitly is kept"
