"""The predictor's update in mixed precision (``predictor_train_dtype="bfloat16"``) against float32."""

import numpy as np
import pytest
import torch as th

from sb3_gocu import GoalCuriosityModule

from conftest import SMALL_CURIOSITY, ChainEnv

SETTINGS = {**SMALL_CURIOSITY, "predictor_hidden": (64, 64, 64), "predictor_epochs": 3, "predictor_batch_size": 32}


def fitted(dtype: str) -> tuple[GoalCuriosityModule, dict, list[th.dtype]]:
    """A module fitted once on the same 256 random pairs, with the dtypes its first linear layer put out."""
    module = GoalCuriosityModule(ChainEnv().observation_space, **SETTINGS, predictor_train_dtype=dtype, seed=5)
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


def test_predictor_train_dtype_is_checked():
    with pytest.raises(ValueError, match="predictor_train_dtype must be one of \\('float32', 'bfloat16'\\), got 'half'"):
        GoalCuriosityModule(ChainEnv().observation_space, **SMALL_CURIOSITY, predictor_train_dtype="half")
