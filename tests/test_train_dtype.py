"""The VAE's and the predictor's updates in mixed precision (``train_dtype="bfloat16"``) against float32."""

import numpy as np
import pytest
import torch as th
from gymnasium import spaces

from sb3_gocu import GoalCuriosityModule

from conftest import SMALL_CURIOSITY, ChainEnv

SETTINGS = {**SMALL_CURIOSITY, "predictor_hidden": (64, 64, 64), "predictor_epochs": 3, "predictor_batch_size": 32}


def fitted(dtype: str) -> tuple[GoalCuriosityModule, dict, list[th.dtype]]:
    """A module fitted once on the same 256 random pairs, with the dtypes its first linear layer put out."""
    module = GoalCuriosityModule(ChainEnv().observation_space, **SETTINGS, train_dtype=dtype, seed=5)
    gen = th.Generator().manual_seed(0)
    phi_s, phi_g = th.randn(256, 8, generator=gen), th.randn(256, 8, generator=gen)
    dist = th.randint(0, 30, (256,), generator=gen).float()
    seen: list[th.dtype] = []
    first = module.predictor.hidden[0]
    hook = first.register_forward_hook(lambda mod, inp, out: seen.append(out.dtype) if mod.training else None)
    fit = module._fit_predictor(phi_s, phi_g, dist)
    hook.remove()
    return module, fit, seen


def test_bfloat16_predictor_training_runs_the_forward_in_bfloat16_and_keeps_float32_state():
    m32, fit32, seen32 = fitted("float32")
    m16, fit16, seen16 = fitted("bfloat16")
    assert set(seen32) == {th.float32} and set(seen16) == {th.bfloat16}
    assert len(seen16) == len(seen32) == 3 * 8  # 3 epochs of 8 minibatches
    for (name, a), b in zip(m32.predictor.state_dict().items(), m16.predictor.state_dict().values()):
        assert b.dtype == a.dtype, name  # weights, batch-norm statistics: float32
        if a.is_floating_point():
            assert th.isfinite(b).all(), name
    assert all(s["exp_avg"].dtype == th.float32 for s in m16.predictor_optimizer.state.values())
    w32, w16 = m32.predictor.hidden[0].weight, m16.predictor.hidden[0].weight
    assert not th.equal(w32, w16)  # the rounding changed the steps...
    assert (w32 - w16).abs().max() < 0.05 * w32.abs().max()  # ...by a little
    assert fit16["skipped"] == 0 and len(fit16["losses"]) == 24
    assert np.mean(fit16["losses"]) == pytest.approx(np.mean(fit32["losses"]), rel=0.05)
    # the same seed gives the same bfloat16 run
    again, _, _ = fitted("bfloat16")
    assert all(th.equal(a, b) for a, b in zip(again.predictor.state_dict().values(), m16.predictor.state_dict().values()))


IMAGE = spaces.Box(0, 255, (16, 16, 3), np.uint8)
VAE_SETTINGS = {**SMALL_CURIOSITY, "vae_batch_size": 32, "embed_dim": 16}


def fitted_vae(dtype: str, **kwargs) -> tuple[GoalCuriosityModule, dict, dict[bool, set]]:
    """An image module's VAE fitted 2 epochs on the same 96 random frames (24 held out for early stopping),
    with the dtypes its first convolution put out, in train mode (True) and in eval mode (False)."""
    module = GoalCuriosityModule(IMAGE, **VAE_SETTINGS, train_dtype=dtype, seed=5, **kwargs)
    rng = np.random.default_rng(0)
    data = rng.integers(0, 256, (96, 16, 16, 3), dtype=np.uint8)
    seen: dict[bool, set] = {True: set(), False: set()}
    hook = module.vae.conv[0].register_forward_hook(lambda mod, inp, out: seen[mod.training].add(out.dtype))
    fit = module._fit_vae(data[:72], np.ones(72, np.float32), 2, data[72:], np.ones(24, np.float32), patience=5)
    hook.remove()
    return module, fit, seen


@pytest.mark.parametrize("shards", [1, 2])
def test_bfloat16_vae_training_runs_the_forward_in_bfloat16_and_keeps_float32_state(shards):
    """Also with ``vae_shards=2`` in 2 threads, where the second part runs in a pool thread (autocast is
    thread-local); the held-out loss of early stopping stays float32."""
    kwargs = {"vae_shards": shards, "update_threads": 2}
    m32, fit32, seen32 = fitted_vae("float32", **kwargs)
    m16, fit16, seen16 = fitted_vae("bfloat16", **kwargs)
    assert seen32 == {True: {th.float32}, False: {th.float32}}
    assert seen16 == {True: {th.bfloat16}, False: {th.float32}}
    assert all(v.dtype == th.float32 and th.isfinite(v).all() for v in m16.vae.state_dict().values() if v.is_floating_point())
    assert fit16["skipped"] == 0 and len(fit16["losses"]) == len(fit32["losses"]) == 2 * 3
    assert all(np.isfinite(fit16["losses"]))
    assert np.mean(fit16["losses"]) == pytest.approx(np.mean(fit32["losses"]), rel=0.02)
    w32, w16 = m32.vae.conv[0].weight, m16.vae.conv[0].weight
    assert not th.equal(w32, w16) and (w32 - w16).abs().max() < 0.05 * w32.abs().max()


def test_train_dtype_is_checked():
    with pytest.raises(ValueError, match="train_dtype must be one of \\('float32', 'bfloat16'\\), got 'half'"):
        GoalCuriosityModule(ChainEnv().observation_space, **SMALL_CURIOSITY, train_dtype="half")
