"""PPO + RND: the exploration peer GoCu is compared with (Burda et al. 2018, "Exploration by Random Network
Distillation"), on PPO_GoCu's PPO and two value heads, so that only the intrinsic reward differs.

A benchmark peer, not part of the library. rllte (the SB3 ecosystem's intrinsic-reward package) pins old versions
of gymnasium and torch, so RND is written here, after CleanRL's ``ppo_rnd_envpool.py``:

* a fixed, randomly initialised target network f and a trained predictor network f_hat, both on the observation
  normalised per pixel by a running mean and std and clipped to [-5, 5];
* the intrinsic reward of a reached state s is ``0.5 * ||f_hat(s) - f(s)||^2``, divided by the running std of the
  discounted intrinsic returns (a forward filter per env, gamma ``intrinsic_gamma``);
* the predictor learns on every observation of the rollout at its end (``epochs`` epochs of minibatches of
  ``batch_size``; Burda et al. train on a quarter of 128 envs' samples, that is 32 envs' worth: with 16 envs all
  samples are used).

The observation and return statistics update at every step, before the step is scored (CleanRL updates them once
per rollout, and first plays a random policy to fill the observation statistics; this peer pays no such steps, where
PPO_GoCu's pretraining is 10,000). The networks keep PyTorch's default initialisation (CleanRL: orthogonal). The intrinsic stream is
non-episodic and its advantage weighs ``intrinsic_coef=0.5`` against the extrinsic one (Burda et al.: 2 and 1).
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback
from stable_baselines3.common.vec_env import VecEnv, VecEnvWrapper
from stable_baselines3.common.vec_env.base_vec_env import VecEnvStepReturn
from torch import nn

from sb3_gocu import PPO_GoCu

#: Burda et al.'s weight of the intrinsic advantage relative to the extrinsic one (coefficients 1 and 2)
RND_INTRINSIC_COEF = 0.5
#: bound of the normalised observation
OBS_CLIP = 5.0


class RunningStats(nn.Module):
    """Running mean and variance (parallel algorithm of Chan et al.), kept as buffers so they are saved."""

    def __init__(self, shape: tuple[int, ...]) -> None:
        super().__init__()
        self.register_buffer("mean", th.zeros(shape, dtype=th.float64))
        self.register_buffer("var", th.ones(shape, dtype=th.float64))
        self.register_buffer("count", th.tensor(0.0, dtype=th.float64))

    def update(self, batch: th.Tensor) -> None:
        """:param batch: samples along the first dimension"""
        batch = batch.to(th.float64)
        n = batch.shape[0]
        if n == 0:
            return
        mean, var = batch.mean(0), batch.var(0, unbiased=False)
        total = self.count + n
        delta = mean - self.mean
        self.var.copy_((self.var * self.count + var * n + delta**2 * self.count * n / total) / total)
        self.mean.add_(delta * n / total)
        self.count.fill_(total)


def _conv_net(n_channels: int, side: int, out_dim: int, extra_layers: int) -> nn.Sequential:
    """Three convolutions sized for small images (NatureCNN's need 36x36), then ``extra_layers`` ReLU layers of
    ``out_dim`` before the output layer (the predictor is deeper than the target, as in Burda et al.)."""
    cnn = nn.Sequential(
        nn.Conv2d(n_channels, 32, 3, stride=2, padding=1), nn.LeakyReLU(),
        nn.Conv2d(32, 64, 3, stride=2, padding=1), nn.LeakyReLU(),
        nn.Conv2d(64, 64, 3, stride=1, padding=1), nn.LeakyReLU(),
        nn.Flatten(),
    )
    with th.no_grad():
        n_flat = cnn(th.zeros(1, n_channels, side, side)).shape[1]
    layers: list[nn.Module] = [cnn, nn.Linear(n_flat, out_dim)]
    for _ in range(extra_layers):
        layers += [nn.ReLU(), nn.Linear(out_dim, out_dim)]
    return nn.Sequential(*layers)


class RND(nn.Module):
    """Random Network Distillation on channel-first image observations.

    :param observation_space: a channel-first image Box (uint8 or float)
    :param n_envs: number of envs (one forward filter of intrinsic returns each)
    :param feature_dim: size of the target's output
    :param learning_rate: Adam learning rate of the predictor
    :param epochs: passes over a rollout's observations per update
    :param batch_size: minibatch size of the predictor's training
    :param intrinsic_gamma: discount of the intrinsic returns whose std normalises the reward
    :param seed: seed of the two networks' initial weights and the minibatch order
    :param device: torch device
    """

    def __init__(
        self,
        observation_space: gym.Space,
        n_envs: int,
        feature_dim: int = 512,
        learning_rate: float = 1e-4,
        epochs: int = 4,
        batch_size: int = 256,
        intrinsic_gamma: float = 0.99,
        seed: int | None = None,
        device: th.device | str = "cpu",
    ) -> None:
        super().__init__()
        if not isinstance(observation_space, spaces.Box) or len(observation_space.shape) != 3:
            raise ValueError(f"observation_space must be a channel-first image Box, got {observation_space}")
        for name, value in (("n_envs", n_envs), ("feature_dim", feature_dim), ("epochs", epochs), ("batch_size", batch_size)):
            if not (isinstance(value, (int, np.integer)) and value >= 1):
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
        if not 0 <= intrinsic_gamma <= 1:
            raise ValueError(f"intrinsic_gamma must be in [0, 1], got {intrinsic_gamma}")
        if not learning_rate > 0:
            raise ValueError(f"learning_rate must be > 0, got {learning_rate}")
        self.n_envs, self.epochs, self.batch_size, self.intrinsic_gamma = int(n_envs), int(epochs), int(batch_size), float(intrinsic_gamma)
        self.generator = th.Generator().manual_seed(0 if seed is None else int(seed))
        channels, side = observation_space.shape[0], observation_space.shape[1]
        with th.random.fork_rng(devices=[]):
            th.manual_seed(0 if seed is None else int(seed))
            self.target = _conv_net(channels, side, feature_dim, extra_layers=0)
            self.predictor = _conv_net(channels, side, feature_dim, extra_layers=2)
        self.target.requires_grad_(False)
        self.obs_stats = RunningStats(observation_space.shape)
        self.return_stats = RunningStats(())
        self.register_buffer("returns", th.zeros(n_envs, dtype=th.float64))  # forward filter per env
        self.to(device)
        self.device = th.device(device)
        self.optimizer = th.optim.Adam(self.predictor.parameters(), lr=learning_rate)
        self.rollout: list[th.Tensor] = []  # normalised observations reached since the last update

    def normalize(self, obs: np.ndarray | th.Tensor) -> th.Tensor:
        """The observation as the networks see it: per pixel (x - mean) / std, clipped to [-OBS_CLIP, OBS_CLIP]."""
        x = th.as_tensor(obs, device=self.device, dtype=th.float64)
        return ((x - self.obs_stats.mean) / th.sqrt(self.obs_stats.var + 1e-8)).clamp(-OBS_CLIP, OBS_CLIP).float()

    def prediction_error(self, x: th.Tensor) -> th.Tensor:
        """0.5 * ||f_hat(x) - f(x)||^2 per row of normalised observations."""
        return 0.5 * (self.predictor(x) - self.target(x)).pow(2).sum(1)

    def step(self, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One vectorised step: update the observation statistics, score the reached states, normalise.

        :param obs: the states reached, one per env
        :return: the raw and the normalised intrinsic reward per env
        """
        if len(obs) != self.n_envs:
            raise ValueError(f"obs must hold one observation per env ({self.n_envs}), got {len(obs)}")
        pixels = th.as_tensor(obs, device=self.device, dtype=th.float64)
        self.obs_stats.update(pixels)
        x = self.normalize(pixels)
        with th.no_grad():
            raw = self.prediction_error(x).to(th.float64)
        self.rollout.append(x)
        self.returns.mul_(self.intrinsic_gamma).add_(raw)
        self.return_stats.update(self.returns)
        normalized = raw / th.sqrt(self.return_stats.var + 1e-8)
        return raw.cpu().numpy().astype(np.float32), normalized.cpu().numpy().astype(np.float32)

    def train_predictor(self) -> float:
        """Train the predictor on the rollout's observations; return the mean loss of the last epoch."""
        if not self.rollout:
            return float("nan")
        data = th.cat(self.rollout)
        self.rollout = []
        losses: list[float] = []
        for _ in range(self.epochs):
            losses = []
            order = th.randperm(len(data), generator=self.generator).to(self.device)
            for start in range(0, len(data), self.batch_size):
                loss = self.prediction_error(data[order[start : start + self.batch_size]]).mean()
                self.optimizer.zero_grad()
                loss.backward()
                self.optimizer.step()
                losses.append(loss.item())
        return float(np.mean(losses))


class RNDVecEnvWrapper(VecEnvWrapper):
    """Writes the normalised RND reward of each reached state into ``infos["gocu_reward"]`` (and the raw one into
    ``"rnd_raw_reward"``), where PPO_GoCu's rollout reads its intrinsic stream; the reward stays extrinsic.

    :param venv: the vectorised env
    :param rnd: the RND module (``n_envs`` = the env's)
    """

    def __init__(self, venv: VecEnv, rnd: RND) -> None:
        super().__init__(venv)
        if rnd.n_envs != venv.num_envs:
            raise ValueError(f"rnd was built for {rnd.n_envs} envs, the env has {venv.num_envs}")
        self.rnd = rnd

    def reset(self) -> Any:
        return self.venv.reset()

    def step_wait(self) -> VecEnvStepReturn:
        obs, rewards, dones, infos = self.venv.step_wait()
        reached = obs.copy()
        for i in np.flatnonzero(dones):
            if infos[i].get("terminal_observation") is not None:
                reached[i] = infos[i]["terminal_observation"]
        raw, normalized = self.rnd.step(reached)
        for i, info in enumerate(infos):
            info["rnd_raw_reward"], info["gocu_reward"] = float(raw[i]), float(normalized[i])
        return obs, rewards, dones, infos


class RNDCallback(BaseCallback):
    """Trains the RND predictor at each rollout end and logs ``rnd/loss``.

    :param rnd: the RND module
    """

    def __init__(self, rnd: RND) -> None:
        super().__init__()
        self.rnd = rnd

    def _on_step(self) -> bool:
        return True

    def _on_rollout_end(self) -> None:
        self.logger.record("rnd/loss", self.rnd.train_predictor())


class PPO_RND(PPO_GoCu):
    """PPO_GoCu's PPO (the paper's settings, two value heads, non-episodic intrinsic stream) with RND as the
    intrinsic reward in place of GoCu's.

    :param rnd_kwargs: keywords of :class:`RND` besides the space, the number of envs, the seed and the device
    """

    #: the file holds the RND module in place of GoCu's curiosity state
    GOCU_OBJECTS = ("global_rng",)

    def __init__(self, policy: Any, env: GymEnv | str, *args: Any, rnd_kwargs: dict[str, Any] | None = None,
                 intrinsic_coef: float = RND_INTRINSIC_COEF, **kwargs: Any) -> None:
        self.rnd_kwargs = dict(rnd_kwargs or {})
        self.rnd: RND | None = None
        super().__init__(policy, env, *args, intrinsic_coef=intrinsic_coef, **kwargs)

    def _attach_curiosity(self) -> None:
        """In place of GoCu's module: an RND module, and the env wrapped to report its reward."""
        if self.rnd is None:
            self.rnd = RND(self.observation_space, self.n_envs, seed=self.seed, device=self.device, **self.rnd_kwargs)
        if self.env is not None and not isinstance(self.env, RNDVecEnvWrapper):
            self.env = RNDVecEnvWrapper(self.env, self.rnd)

    def _init_callback(self, callback: MaybeCallback, progress_bar: bool = False) -> BaseCallback:
        callbacks = list(callback) if isinstance(callback, list) else ([] if callback is None else [callback])
        return PPO._init_callback(self, [*callbacks, RNDCallback(self.rnd)], progress_bar)

    def _excluded_save_params(self) -> list[str]:
        return [*super()._excluded_save_params(), "rnd"]

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        state_dicts, variables = super()._get_torch_save_params()
        return [*state_dicts, "rnd", "rnd.optimizer"], variables
