"""Rollout buffers with two reward and value streams (extrinsic e and curiosity gc) for PPO_GoCu.

GAE runs once per stream (eq 10 and Alg. 1 lines 16-18), each with its own discount; the advantage PPO
optimises is ``A = A_e + sigma * A_gc``. Samples carry both value targets: ``old_values`` and ``returns``
are the (batch, 2) arrays [e, gc] flattened row by row, matching the flattened (batch, 2) output of the
two-headed critic, so SB3's PPO loss trains both heads (its value loss is the mean of the two heads'
squared errors).
"""

from __future__ import annotations

from typing import Any, Generator

import numpy as np
import torch as th
from stable_baselines3.common.buffers import DictRolloutBuffer, RolloutBuffer
from stable_baselines3.common.vec_env import VecNormalize

from sb3_gocu.curiosity.checks import check_intrinsic_coef, is_number


def compute_gae(
    rewards: np.ndarray,
    values: np.ndarray,
    episode_starts: np.ndarray,
    last_values: np.ndarray,
    last_dones: np.ndarray,
    gamma: float,
    gae_lambda: float,
) -> np.ndarray:
    """GAE(lambda) advantages of one reward stream.

    :param rewards: (n_steps, n_envs) rewards r_t (time-limit bootstrap already added)
    :param values: (n_steps, n_envs) V(s_t)
    :param episode_starts: (n_steps, n_envs), 1 where s_t starts an episode
    :param last_values: (n_envs,) V of the observation after the last step
    :param last_dones: (n_envs,) whether the last step ended an episode
    :return: (n_steps, n_envs) advantages; the lambda-returns are ``advantages + values``
    """
    n_steps = rewards.shape[0]
    advantages = np.zeros_like(rewards, dtype=np.float32)
    last_gae = np.zeros(rewards.shape[1], dtype=np.float32)
    for step in reversed(range(n_steps)):
        if step == n_steps - 1:
            next_non_terminal = 1.0 - last_dones.astype(np.float32)
            next_values = last_values
        else:
            next_non_terminal = 1.0 - episode_starts[step + 1]
            next_values = values[step + 1]
        delta = rewards[step] + gamma * next_values * next_non_terminal - values[step]
        last_gae = delta + gamma * gae_lambda * next_non_terminal * last_gae
        advantages[step] = last_gae
    return advantages


class _TwoStreams:
    """Mixin for SB3 rollout buffers: a second (curiosity) reward and value stream."""

    intrinsic_rewards: np.ndarray
    intrinsic_values: np.ndarray
    intrinsic_returns: np.ndarray
    intrinsic_advantages: np.ndarray
    extrinsic_advantages: np.ndarray

    def _init_streams(self, intrinsic_gamma: float, intrinsic_coef: float, intrinsic_episodic: bool) -> None:
        if not (is_number(intrinsic_gamma) and 0 <= intrinsic_gamma <= 1):
            raise ValueError(f"intrinsic_gamma must be in [0, 1], got {intrinsic_gamma!r}")
        self.intrinsic_gamma = intrinsic_gamma
        self.intrinsic_coef = check_intrinsic_coef(intrinsic_coef)
        self.intrinsic_episodic = intrinsic_episodic

    def reset(self) -> None:
        shape = (self.buffer_size, self.n_envs)  # type: ignore[attr-defined]
        self.intrinsic_rewards = np.zeros(shape, dtype=np.float32)
        self.intrinsic_values = np.zeros(shape, dtype=np.float32)
        self.intrinsic_returns = np.zeros(shape, dtype=np.float32)
        self.intrinsic_advantages = np.zeros(shape, dtype=np.float32)
        self.extrinsic_advantages = np.zeros(shape, dtype=np.float32)
        self._streams_flat = False
        super().reset()  # type: ignore[misc]

    def add(
        self,
        obs: Any,
        action: np.ndarray,
        reward: np.ndarray,
        episode_start: np.ndarray,
        value: th.Tensor,
        log_prob: th.Tensor,
        intrinsic_reward: np.ndarray | None = None,
    ) -> None:
        """SB3's ``add`` with ``value`` of shape (n_envs, 2) [V_e, V_gc] and the curiosity reward of the step."""
        if intrinsic_reward is None:
            raise ValueError("a two-stream rollout buffer needs `intrinsic_reward` at every step")
        self.intrinsic_rewards[self.pos] = np.asarray(intrinsic_reward)  # type: ignore[attr-defined]
        self.intrinsic_values[self.pos] = value[:, 1].clone().cpu().numpy()  # type: ignore[attr-defined]
        super().add(obs, action, reward, episode_start, value[:, 0], log_prob)  # type: ignore[misc]

    def compute_returns_and_advantage(self, last_values: th.Tensor, dones: np.ndarray) -> None:
        """GAE for both streams; ``last_values`` is (n_envs, 2). A non-episodic curiosity stream ignores
        episode ends (RND-style)."""
        last = last_values.clone().cpu().numpy().reshape(-1, 2)
        self.extrinsic_advantages = compute_gae(
            self.rewards, self.values, self.episode_starts, last[:, 0], dones, self.gamma, self.gae_lambda  # type: ignore[attr-defined]
        )
        starts, last_dones = self.episode_starts, dones  # type: ignore[attr-defined]
        if not self.intrinsic_episodic:
            starts, last_dones = np.zeros_like(starts), np.zeros_like(dones)
        self.intrinsic_advantages = compute_gae(
            self.intrinsic_rewards, self.intrinsic_values, starts, last[:, 1], last_dones, self.intrinsic_gamma, self.gae_lambda  # type: ignore[attr-defined]
        )
        self.returns = self.extrinsic_advantages + self.values  # type: ignore[attr-defined]
        self.intrinsic_returns = self.intrinsic_advantages + self.intrinsic_values
        self.advantages = self.extrinsic_advantages + self.intrinsic_coef * self.intrinsic_advantages

    def get(self, batch_size: int | None = None) -> Generator[Any, None, None]:
        if not self._streams_flat:
            for name in ("intrinsic_values", "intrinsic_returns"):
                self.__dict__[name] = self.swap_and_flatten(self.__dict__[name])  # type: ignore[attr-defined]
            self._streams_flat = True
        yield from super().get(batch_size)  # type: ignore[misc]

    def _get_samples(self, batch_inds: np.ndarray, env: VecNormalize | None = None) -> Any:
        samples = super()._get_samples(batch_inds, env)  # type: ignore[misc]
        values = np.stack([self.values[batch_inds].flatten(), self.intrinsic_values[batch_inds].flatten()], axis=1)  # type: ignore[attr-defined]
        returns = np.stack([self.returns[batch_inds].flatten(), self.intrinsic_returns[batch_inds].flatten()], axis=1)  # type: ignore[attr-defined]
        return samples._replace(old_values=self.to_torch(values.reshape(-1)), returns=self.to_torch(returns.reshape(-1)))  # type: ignore[attr-defined]


class GoCuRolloutBuffer(_TwoStreams, RolloutBuffer):
    """SB3 ``RolloutBuffer`` with a curiosity stream.

    :param intrinsic_gamma: discount of the curiosity stream
    :param intrinsic_coef: sigma of eq 10, weight of A_gc in the advantage
    :param intrinsic_episodic: whether the curiosity stream stops at episode ends
    (other parameters: SB3's ``RolloutBuffer``)
    """

    def __init__(self, *args: Any, intrinsic_gamma: float = 0.99, intrinsic_coef: float = 0.25, intrinsic_episodic: bool = False, **kwargs: Any) -> None:
        self._init_streams(intrinsic_gamma, intrinsic_coef, intrinsic_episodic)
        super().__init__(*args, **kwargs)


class GoCuDictRolloutBuffer(_TwoStreams, DictRolloutBuffer):
    """SB3 ``DictRolloutBuffer`` with a curiosity stream (parameters as :class:`GoCuRolloutBuffer`)."""

    def __init__(self, *args: Any, intrinsic_gamma: float = 0.99, intrinsic_coef: float = 0.25, intrinsic_episodic: bool = False, **kwargs: Any) -> None:
        self._init_streams(intrinsic_gamma, intrinsic_coef, intrinsic_episodic)
        super().__init__(*args, **kwargs)
