"""PPO_GoCu's policies: two value heads for MlpPolicy, CnnPolicy (32x32 out of the box) and MultiInputPolicy."""

import gymnasium as gym
import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.torch_layers import NatureCNN

from sb3_gocu import GoCuVecEnvWrapper, PaperCNN, PPO_GoCu
from sb3_gocu.policies import GoCuActorCriticCnnPolicy, GoCuMultiInputActorCriticPolicy, SmallImageCombinedExtractor

from conftest import SMALL_CURIOSITY


class DictImageEnv(gym.Env):
    """Dict observations: a 32x32 RGB image and a 3-vector."""

    def __init__(self):
        self.observation_space = spaces.Dict(
            {"image": spaces.Box(0, 255, (32, 32, 3), np.uint8), "state": spaces.Box(-1, 1, (3,), np.float32)}
        )
        self.action_space = spaces.Discrete(3)
        self.t = 0

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return self.observation_space.sample(), {}

    def step(self, action):
        self.t += 1
        return self.observation_space.sample(), float(action == 2), False, self.t >= 10, {}


def test_cnn_policy_takes_32x32_images_from_an_env_id():
    model = PPO_GoCu("CnnPolicy", "GoCu/DoorKey-5x5-v0", n_steps=16, batch_size=16, seed=0, curiosity_kwargs=SMALL_CURIOSITY)
    assert isinstance(model.policy, GoCuActorCriticCnnPolicy)
    assert isinstance(model.policy.features_extractor, PaperCNN)
    convs = [m for m in model.policy.features_extractor.cnn if isinstance(m, th.nn.Conv2d)]
    assert [(c.out_channels, c.kernel_size, c.stride, c.padding) for c in convs] == [
        (16, (2, 2), (2, 2), (1, 1)), (32, (2, 2), (2, 2), (1, 1)), (64, (2, 2), (2, 2), (1, 1))
    ]
    obs = model.policy.obs_to_tensor(model.env.reset())[0]
    actions, values, _ = model.policy(obs)
    assert values.shape == (1, 2) and model.policy.predict_values(obs).shape == (1, 2)
    assert isinstance(model.env, GoCuVecEnvWrapper) and model.env.mode == "separate" and model.env.intrinsic_coef is None
    model.learn(32)
    assert model.num_timesteps == 32


def test_cnn_policy_keeps_nature_cnn_for_large_images():
    space = spaces.Box(0, 255, (3, 64, 64), np.uint8)
    policy = GoCuActorCriticCnnPolicy(space, spaces.Discrete(2), lambda _: 1e-3)
    assert isinstance(policy.features_extractor, NatureCNN)
    assert policy.value_net.out_features == 2
    # the optimizer trains the two-output head, not a discarded one-output head
    head = {id(p) for p in policy.value_net.parameters()}
    in_optimizer = {id(p) for group in policy.optimizer.param_groups for p in group["params"]}
    assert head <= in_optimizer


def test_multi_input_policy_with_dict_observations():
    model = PPO_GoCu("MultiInputPolicy", DictImageEnv(), n_steps=16, batch_size=16, seed=0, curiosity_kwargs=SMALL_CURIOSITY)
    assert isinstance(model.policy, GoCuMultiInputActorCriticPolicy)
    assert isinstance(model.policy.features_extractor, SmallImageCombinedExtractor)
    assert isinstance(model.policy.features_extractor.extractors["image"], PaperCNN)
    assert model.curiosity.adapter.obs_key == "image" and model.curiosity.adapter.is_image
    model.learn(48)
    assert model.curiosity.pretrained and np.isfinite(model.rollout_buffer.intrinsic_rewards).all()
    assert np.abs(model.rollout_buffer.intrinsic_rewards).max() > 0
