"""The curiosity module follows the model's device: PPO_GoCu(..., device=...) builds its module there."""

import numpy as np
import pytest
import torch as th
from stable_baselines3.common.env_util import make_vec_env

from sb3_gocu import PPO_GoCu

from conftest import SMALL_CURIOSITY, TINY_IMAGE_CURIOSITY, ChainEnv


def test_the_models_device_reaches_the_module():
    model = PPO_GoCu("MlpPolicy", make_vec_env(ChainEnv, n_envs=2, seed=0), device="cpu", curiosity_kwargs=SMALL_CURIOSITY)
    assert model.curiosity.device == model.device == th.device("cpu")
    assert next(model.curiosity.vae.parameters()).device == th.device("cpu")
    with pytest.raises(ValueError, match=r"curiosity_kwargs\['device'\]='meta' differs from the model's device cpu"):
        PPO_GoCu("MlpPolicy", make_vec_env(ChainEnv, n_envs=2, seed=0), device="cpu", curiosity_kwargs={**SMALL_CURIOSITY, "device": "meta"})


@pytest.mark.skipif(not th.cuda.is_available(), reason="needs a CUDA device")
def test_ppo_gocu_trains_its_curiosity_on_the_gpu():
    """device="cuda": the VAE and the predictor live and train on the GPU, and the rewards are finite."""
    env = make_vec_env("GoCu/DoorKey-5x5-v0", n_envs=4, seed=0)
    model = PPO_GoCu("CnnPolicy", env, n_steps=64, batch_size=64, seed=0, device="cuda",
                     curiosity_kwargs={**TINY_IMAGE_CURIOSITY, "predictor_train_freq": 256, "vae_train_freq": 512})
    module = model.curiosity
    assert module.device.type == "cuda"
    model.learn(1024)
    assert all(p.device.type == "cuda" for net in (module.vae, module.predictor) for p in net.parameters())
    assert module.pretrained and module.last_predictor_update > 0 and module.last_vae_update > 0
    assert np.isfinite(model.rollout_buffer.intrinsic_rewards).all() and model.rollout_buffer.intrinsic_rewards.any()


def test_learn_trains_at_the_callers_thread_count():
    from stable_baselines3.common.callbacks import BaseCallback

    seen = []

    class Probe(BaseCallback):
        def _on_step(self):
            seen.append(th.get_num_threads())
            return True

    model = PPO_GoCu("MlpPolicy", make_vec_env(ChainEnv, n_envs=2, seed=0), n_steps=32, batch_size=32, curiosity_kwargs=SMALL_CURIOSITY)
    th.set_num_threads(2)
    model.learn(64, callback=Probe())
    assert seen and set(seen) == {2}, "as SB3 trains: the caller's count, not one forced thread"
    assert th.get_num_threads() == 2
