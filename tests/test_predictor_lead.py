"""``predictor_lead``: a predictor update starts rollouts before it is due, runs only beside PPO's updates, and
is taken into use when due."""

import time

import numpy as np
import pytest
import torch as th
from stable_baselines3.common.env_util import make_vec_env

from sb3_gocu import GoalCuriosityModule, PPO_GoCu

from conftest import SMALL_CURIOSITY, ChainEnv


def lead_run(lead: int, vae_train_freq: int = 100_000) -> tuple[PPO_GoCu, dict[str, list[int]]]:
    """PPO_GoCu on 2 ChainEnvs, rollouts of 128 recorded steps, a predictor update due every 512, 16 rollouts,
    seed 0, updates overlapped with PPO's; the recorded step counts at which pairs were drawn and at which a
    predictor update was taken into use."""
    th.manual_seed(0)
    env = make_vec_env(lambda: ChainEnv(), n_envs=2, seed=0)
    curiosity = {**SMALL_CURIOSITY, "predictor_train_freq": 512, "vae_train_freq": vae_train_freq, "overlap_ppo_update": True,
                 "predictor_lead": lead, "scoring_process": False}
    model = PPO_GoCu("MlpPolicy", env, n_steps=64, batch_size=64, n_epochs=2, seed=0, curiosity_kwargs=curiosity)
    module = model.curiosity
    seen: dict[str, list[int]] = {"drawn": [], "in_use": []}
    prepare, finish = module._prepare_predictor, module._finish_predictor
    module._prepare_predictor = lambda: seen["drawn"].append(module.n_recorded_steps) or prepare()
    module._finish_predictor = lambda fit: seen["in_use"].append(module.n_recorded_steps) or finish(fit)
    model.learn(2048)
    return model, seen


def test_a_lead_update_is_drawn_early_and_taken_into_use_when_due():
    base, seen0 = lead_run(0)
    lead, seen1 = lead_run(1)
    assert seen0["in_use"] == [576, 1088, 1600, 2112]  # the pretraining's 64 steps, then every 512
    assert seen1["in_use"] == seen0["in_use"]  # the same schedule...
    assert seen1["drawn"] == [n - 128 for n in seen0["drawn"]]  # ...on pairs drawn one rollout earlier
    assert lead.curiosity._lead is None and lead.curiosity.last_predictor_update == base.curiosity.last_predictor_update
    # another run than without the lead, and the same run again with it
    assert not th.equal(base.curiosity.predictor.hidden[0].weight, lead.curiosity.predictor.hidden[0].weight)
    again, _ = lead_run(1)
    for a, b in zip(lead.curiosity.state_dict()["predictor"].values(), again.curiosity.state_dict()["predictor"].values()):
        assert th.equal(a, b)
    assert np.array_equal(lead.rollout_buffer.intrinsic_rewards, again.rollout_buffer.intrinsic_rewards)


def test_no_lead_when_a_vae_update_falls_due_first():
    """A VAE update due at the rollout end where the lead would start, or before the predictor's: the predictor
    update runs as without a lead there (its pairs drawn when due, after the VAE's embeddings)."""
    _, seen0 = lead_run(0, vae_train_freq=1024)
    _, seen1 = lead_run(1, vae_train_freq=1024)
    assert seen1["in_use"] == seen0["in_use"]
    skipped = [n for n, m in zip(seen0["drawn"], seen1["drawn"]) if n == m]
    assert skipped and len(skipped) < len(seen0["drawn"])  # some updates led, some did not
    assert all(m in (n, n - 128) for n, m in zip(seen0["drawn"], seen1["drawn"]))


def _module(**kwargs) -> GoalCuriosityModule:
    module = GoalCuriosityModule(ChainEnv().observation_space, **{**SMALL_CURIOSITY, "overlap_ppo_update": True, "predictor_train_freq": 64,
                                                                  "predictor_epochs": 40, "predictor_lead": 1, **kwargs}, seed=3)
    module.recording = True
    rng = np.random.default_rng(0)
    for _ in range(64):  # the pretraining's steps
        module.step(rng.random((2, 2), dtype=np.float32), np.zeros(2, bool))
    module.pretrain()
    return module


def _rollout(module: GoalCuriosityModule, steps: int = 16) -> None:
    rng = np.random.default_rng(module.n_recorded_steps)
    for _ in range(steps):
        module.step(rng.random((2, 2), dtype=np.float32), rng.random(2) < 0.1)


def _steps_taken(module: GoalCuriosityModule) -> list[int]:
    """Counts the lead update's minibatch steps from now on (its gate's waits)."""
    count = [0]
    wait = module._lead_gate.wait
    module._lead_gate.wait = lambda *a: count.append(0) or wait(*a)  # type: ignore[method-assign]
    return count


def test_a_lead_update_pauses_while_the_module_is_used_and_is_taken_into_use_when_due():
    module = _module()
    _rollout(module)
    module.maybe_train()  # 32 recorded steps since the pretraining: the update due at 64 starts now
    lead = module._lead
    assert lead is not None and module.update_running is False
    assert module._lead_gate.is_set()  # runs beside "PPO's update"
    _rollout(module, 1)  # the next rollout uses the module: the lead pauses
    assert not module._lead_gate.is_set()
    time.sleep(0.2)  # a step under way ends
    count = _steps_taken(module)
    time.sleep(0.3)
    assert len(count) <= 2 and not lead.finished.is_set()  # at most the wait it was in and the one after
    _rollout(module, 15)
    module.maybe_train()  # due: taken into use before the module is next used
    assert module._lead is None and module.last_predictor_update == module.n_recorded_steps
    before = module._folded
    _rollout(module, 1)
    assert lead.finished.is_set() and module._folded is not before


def test_saving_takes_a_lead_update_into_use():
    module = _module()
    _rollout(module)
    module.maybe_train()
    assert module._lead is not None
    _rollout(module, 1)  # paused
    state = module.state_dict()
    assert module._lead is None and module.last_predictor_update == module.n_recorded_steps
    assert state["counters"]["last_predictor_update"] == module.n_recorded_steps
    assert state["counters"]["recorded_at_last_train"] == module._recorded_at_last_train
    other = _module()
    other.load_state_dict(state)
    assert other._recorded_at_last_train == module._recorded_at_last_train
    assert all(th.equal(a, b) for a, b in zip(other.predictor.state_dict().values(), module.predictor.state_dict().values()))


@pytest.mark.parametrize("kwargs", [dict(predictor_lead=-1), dict(predictor_lead=True), dict(predictor_lead=1.5),
                                    dict(predictor_lead=1, overlap_ppo_update=False),
                                    dict(predictor_lead=1, train_in_background=True),
                                    dict(predictor_lead=1, refit_predictor_after_vae=True)])
def test_predictor_lead_is_checked(kwargs):
    with pytest.raises(ValueError, match="predictor_lead"):
        GoalCuriosityModule(ChainEnv().observation_space, **{**SMALL_CURIOSITY, "overlap_ppo_update": True, **kwargs})


def _failing_fit(module: GoalCuriosityModule) -> None:
    def fit(*args, **kwargs):
        raise ValueError("fit broke")

    module._fit_predictor = fit  # type: ignore[method-assign]


def test_an_error_in_a_lead_update_is_raised_where_it_is_taken_into_use():
    module = _module()
    _failing_fit(module)
    _rollout(module)
    module.maybe_train()  # the lead starts, and fails in its thread
    lead = module._lead
    assert lead is not None and lead.finished.wait(10)
    with pytest.raises(RuntimeError, match="a background curiosity update failed") as raised:
        module.finish_updates()
    assert isinstance(raised.value.__cause__, ValueError) and str(raised.value.__cause__) == "fit broke"
    assert module._lead is None and not module.update_running


def test_an_error_in_an_overlapped_update_is_raised_where_it_is_taken_into_use():
    """The same for an update due now (the job's thread), taken into use by the module's next use."""
    module = _module(predictor_lead=0)
    _failing_fit(module)
    _rollout(module, 64)
    module.maybe_train()  # due: runs beside "PPO's update" and fails
    assert module.update_running
    with pytest.raises(RuntimeError, match="a background curiosity update failed") as raised:
        _rollout(module, 1)
    assert isinstance(raised.value.__cause__, ValueError) and not module.update_running
