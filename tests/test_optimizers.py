"""The curiosity networks' Adam runs its multi-tensor step (``foreach``): the same values as the per-parameter
loop, in fewer calls."""

import numpy as np
import torch as th
from gymnasium import spaces

from sb3_gocu import GoalCuriosityModule
from sb3_gocu.curiosity.training import VaeJob

from conftest import SMALL_CURIOSITY

IMAGE = spaces.Box(0, 255, (16, 16, 3), np.uint8)
# the paper's 5x512 predictor, a small image VAE
SETTINGS = {**SMALL_CURIOSITY, "predictor_hidden": (512,) * 5, "predictor_epochs": 3, "predictor_batch_size": 32,
            "vae_batch_size": 32, "embed_dim": 16}


def fitted(foreach: bool) -> GoalCuriosityModule:
    """A module whose VAE (2 epochs on 72 random frames) and predictor (3 epochs on 256 random pairs) were fitted
    once, with Adam's multi-tensor step (the default) or with its per-parameter loop."""
    module = GoalCuriosityModule(IMAGE, **SETTINGS, seed=5)
    for optimizer in (module.trainer.vae_optimizer, module.trainer.predictor_optimizer):
        assert [group["foreach"] for group in optimizer.param_groups] == [True]
        for group in optimizer.param_groups:
            group["foreach"] = foreach
    frames = np.random.default_rng(0).integers(0, 256, (96, 16, 16, 3), dtype=np.uint8)
    ones = lambda n: np.ones(n, np.float32)  # noqa: E731
    module.trainer.fit_vae(VaeJob(frames[:72], ones(72), 2, patience=5, val_data=frames[72:], val_weights=ones(24)))
    gen = th.Generator().manual_seed(0)
    phi_s, phi_g = th.randn(256, 16, generator=gen), th.randn(256, 16, generator=gen)
    module.trainer.fit_predictor(module.trainer.predictor_job(phi_s, phi_g, th.randint(0, 30, (256,), generator=gen).float()))
    return module


def _tensors(state: dict) -> list[th.Tensor]:
    """The tensors of a (nested) state dict, in order."""
    if isinstance(state, th.Tensor):
        return [state]
    if isinstance(state, dict):
        return [t for key in state for t in _tensors(state[key])]
    if isinstance(state, (list, tuple)):
        return [t for item in state for t in _tensors(item)]
    return []


def test_multi_tensor_adam_trains_the_same_networks_as_the_loop():
    multi, loop = fitted(True), fitted(False)
    # the fits moved the weights away from the initial ones
    assert not th.equal(GoalCuriosityModule(IMAGE, **SETTINGS, seed=5).predictor.hidden[0].weight, multi.predictor.hidden[0].weight)
    for net in ("vae", "predictor", "vae_optimizer", "predictor_optimizer"):
        a, b = (_tensors(getattr(m.trainer, net).state_dict()) for m in (multi, loop))
        assert len(a) == len(b) > 0, net
        assert all(th.equal(x, y) for x, y in zip(a, b)), net


def test_a_state_saved_with_the_loop_loads_with_the_multi_tensor_step():
    old = fitted(False)
    state = old.state_dict()
    assert state["predictor_optimizer"]["param_groups"][0]["foreach"] is False
    module = GoalCuriosityModule(IMAGE, **SETTINGS, seed=5)
    module.load_state_dict(state)
    for optimizer in (module.trainer.vae_optimizer, module.trainer.predictor_optimizer):
        assert [group["foreach"] for group in optimizer.param_groups] == [True]
    assert all(th.equal(x, y) for x, y in zip(_tensors(module.trainer.predictor_optimizer.state_dict()["state"]),
                                               _tensors(state["predictor_optimizer"]["state"])))
