import importlib.util
import os
import pathlib
import sys

os.environ.setdefault("MUJOCO_GL", "egl")

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.logger import KVWriter


class ChainEnv(gym.Env):
    """A tiny deterministic env: a 1-D position in [0, length], actions 0 (left) / 1 (right).

    Reaching the right end terminates with reward 1; after ``max_steps`` steps the episode is truncated.
    Observations are float vectors (position, position squared) so that GoCu embeds them with its MLP VAE.
    """

    def __init__(self, length: int = 6, max_steps: int = 20):
        self.length = length
        self.max_steps = max_steps
        self.observation_space = spaces.Box(-1.0, 10.0, (2,), np.float32)
        self.action_space = spaces.Discrete(2)
        self.pos = 0
        self.t = 0

    def _obs(self):
        x = self.pos / self.length
        return np.array([x, x * x], dtype=np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.pos, self.t = 0, 0
        return self._obs(), {}

    def step(self, action):
        self.t += 1
        self.pos = int(np.clip(self.pos + (1 if action == 1 else -1), 0, self.length))
        terminated = self.pos == self.length
        truncated = not terminated and self.t >= self.max_steps
        return self._obs(), float(terminated), terminated, truncated, {}


class LivesEnv(ChainEnv):
    """ChainEnv with Atari's lives (``unwrapped.ale.lives()``, as ``EpisodicLifeEnv`` reads them): one lost every 4
    steps, the game over with the third; action 1 is FIRE (right), 2 left, as ``FireResetEnv`` wants."""

    def __init__(self):
        super().__init__(length=50, max_steps=100)
        self.action_space = spaces.Discrete(3)
        self.lives = 3
        self.ale = type("Ale", (), {"lives": lambda _: self.lives})()

    def get_action_meanings(self):
        return ["NOOP", "FIRE", "LEFT"]

    def reset(self, *, seed=None, options=None):
        self.lives = 3
        return super().reset(seed=seed)

    def step(self, action):
        obs, reward, terminated, truncated, info = super().step(action)
        self.lives -= self.t % 4 == 0
        return obs, reward, terminated or self.lives == 0, truncated, info


@pytest.fixture(autouse=True)
def _one_thread():
    th.set_num_threads(1)
    yield


def record_steps(module, batches) -> None:
    """Step a curiosity module through ``batches`` of (observations, dones), recording them as in training."""
    module.recording = True
    for obs, dones in batches:
        module.step(obs, dones)


SMALL_CURIOSITY = dict(
    n_goals=4,
    goal_buffer_size=32,
    predictor_hidden=(32, 32),
    predictor_pairs=256,
    predictor_epochs=2,
    predictor_train_freq=256,
    embed_dim=8,
    latent_dim=2,
    vae_epochs=1,
    vae_update_epochs=1,
    vae_patience=0,  # every VAE update trains (tests compare the weights before and after one)
    vae_train_freq=512,
    pretrain_steps=64,
    memory_size=256,
)


#: curiosity settings small enough for image envs in a test (JSON-friendly: lists, not tuples)
TINY_IMAGE_CURIOSITY = dict(
    n_goals=4,
    goal_buffer_size=64,
    predictor_hidden=[32, 32],
    predictor_pairs=256,
    predictor_epochs=1,
    predictor_train_freq=512,
    vae_epochs=1,
    vae_update_epochs=1,
    vae_patience=0,
    pretrain_steps=256,
    memory_size=512,
)

ROOT = pathlib.Path(__file__).resolve().parents[1]


def load_script(name: str, relpath: str):
    """Import a script of the repository (benchmarks/, examples/) as a module."""
    spec = importlib.util.spec_from_file_location(name, ROOT / relpath)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # as an import does (dataclasses look their module up there)
    spec.loader.exec_module(module)
    return module


class Capture(KVWriter):
    """A logger output that keeps every dump's key-values (``Logger(folder=None, output_formats=[Capture()])``)."""

    def __init__(self):
        self.records = []

    def write(self, key_values, key_excluded, step=0):
        self.records.append(dict(key_values))
