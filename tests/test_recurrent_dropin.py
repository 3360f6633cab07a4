"""examples/recurrent_dropin.py, the drop-in path in an sb3-contrib algorithm (RecurrentPPO), on a tiny budget (about
30-60 s on 2 busy cores: the pretraining's 10,000 random steps and 20 VAE epochs run in full)."""

import numpy as np
import torch as th
from sb3_contrib import RecurrentPPO

from conftest import load_script
from sb3_gocu import GoCuVecEnvWrapper


def test_recurrent_ppo_trains_on_the_sum_wrapper_saves_and_evaluates(tmp_path):
    example = load_script("recurrent_dropin", "examples/recurrent_dropin.py")
    save = tmp_path / "recurrent"
    model, returns = example.main(["--timesteps", "2048", "--eval-episodes", "2", "--save", str(save)])
    assert model.num_timesteps == 2048  # one rollout of 16 envs x 128 steps
    wrapper = model.get_env().venv  # VecTransposeImage over the GoCu wrapper
    assert isinstance(wrapper, GoCuVecEnvWrapper) and wrapper.mode == "sum" and wrapper.centred
    module = wrapper.module
    assert module.pretrained and module.goal_buffer.size > 0 and module.n_recorded_steps >= 10_000 + 2048
    # the rollout RecurrentPPO learned from holds the curiosity: DoorKey pays r_e only at the goal, and the sum pays
    # sigma (r_gc - mean) on every step, positive and negative
    rewards = model.rollout_buffer.rewards
    assert (rewards > 0).mean() > 0.01 and (rewards < 0).mean() > 0.01
    loaded = RecurrentPPO.load(save, device="cpu")
    for name, tensor in model.policy.state_dict().items():
        assert th.equal(loaded.policy.state_dict()[name], tensor), name
    assert len(returns) == 2 and np.all((returns >= 0) & (returns <= 1))
