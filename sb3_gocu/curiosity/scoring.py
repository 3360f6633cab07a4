"""Scoring states against their episodes' goals (eq 13), memoised: :class:`Scorer`.

Between two updates of the networks, the reward of a state against an episode's goals is a fixed function, so
it is memoised per episode on the observation's bytes (an observation seen again in the same episode costs a
hash), and phi on the observation alone until the next VAE update. No SB3 import.
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np
import torch as th

from sb3_gocu.curiosity.episodes import Episodes
from sb3_gocu.curiosity.networks import FoldedPredictor
from sb3_gocu.curiosity.reward import curiosity_reward

#: phi memo entries kept before the memo is cleared
PHI_MEMO_SIZE = 100_000


@th.inference_mode()
def eq13_rows(
    phi: th.Tensor, goal_parts: th.Tensor, has_goals: np.ndarray, folded: FoldedPredictor, alpha: float, aggregation: str, reward_scale: float
) -> th.Tensor:
    """Raw r_gc of states (phi, (n, d)) against their episodes' goals (goal halves, (n, K, h)); ``has_goals`` says
    whether each state's episode has its K goals, and a state whose episode has none yet gets h = 0, i.e. alpha / delta."""
    if has_goals.all():
        mastery = folded.mastery_from_parts(folded.state_part(phi), goal_parts)
        return curiosity_reward(mastery, alpha, aggregation, reward_scale)
    r = th.full((len(phi),), alpha / reward_scale)
    rows = th.from_numpy(np.flatnonzero(has_goals))
    if len(rows):
        mastery = folded.mastery_from_parts(folded.state_part(phi[rows]), goal_parts[rows])
        r[rows] = curiosity_reward(mastery, alpha, aggregation, reward_scale)
    return r


class Scorer:
    """Memoised scoring of one observation per env: the reward memo of each env's episode first, then the phi memo,
    then the encoder and eq 13 for what is left.

    :param episodes: the per-env episode state (its reward memos, ids and goal halves)
    :param embed_dim: size of phi
    :param to_tensor: raw batch -> the encoder's input on the networks' device
    :param eq13_args: (alpha, h, delta) of eq 13
    """

    def __init__(self, episodes: Episodes, embed_dim: int, to_tensor: Callable[[np.ndarray], th.Tensor],
                 eq13_args: tuple[float, str, float]) -> None:
        self.episodes, self.embed_dim, self.to_tensor, self.eq13_args = episodes, embed_dim, to_tensor, eq13_args
        self.phi_memo: dict[bytes, th.Tensor] = {}  # key -> phi
        self.cache_hits = self.cache_lookups = 0  # cumulative

    @th.inference_mode()
    def score(self, raw: np.ndarray, env_indices: np.ndarray, keys: list[bytes], encoder: Any,
              folded: FoldedPredictor) -> tuple[np.ndarray, np.ndarray]:
        """Raw r_gc (eq 13) and phi of one observation per env of ``env_indices``; the rows scored now are memoised in
        their episodes.

        :param raw: the observations, as the buffers keep them
        :param keys: :func:`~sb3_gocu.curiosity.stores.observation_key` of each
        :param encoder: the VAE that embeds (the module's frozen copy)
        :param folded: the predictor's inference form
        :return: rewards (n,) float32 and phi (n, embed_dim) float32"""
        n = len(raw)
        rewards = np.zeros(n, dtype=np.float32)
        phi = np.zeros((n, self.embed_dim), dtype=np.float32)
        episodes = self.episodes
        miss = []
        for j, (e, key) in enumerate(zip(env_indices, keys)):
            hit = episodes.rewards[e].get(key)
            if hit is None:
                miss.append(j)
            else:
                rewards[j], phi[j] = hit
        self.cache_lookups += n
        self.cache_hits += n - len(miss)
        if not miss:
            return rewards, phi
        todo = []
        for j in miss:
            known = self.phi_memo.get(keys[j])
            if known is None:
                todo.append(j)
            else:
                phi[j] = known
        if todo:
            phi[todo] = encoder.embed(self.to_tensor(raw[todo])).cpu().numpy()
            if len(self.phi_memo) + len(todo) > PHI_MEMO_SIZE:
                self.phi_memo.clear()
            for j in todo:
                self.phi_memo[keys[j]] = th.from_numpy(phi[j].copy())
        m_idx = np.asarray(miss)
        goal_parts = episodes.goal_parts[th.from_numpy(env_indices[m_idx])]
        rewards[m_idx] = eq13_rows(th.from_numpy(phi[m_idx]), goal_parts, episodes.has_goals[env_indices[m_idx]], folded,
                                   *self.eq13_args).numpy()
        for j in miss:
            episodes.remember_reward(env_indices[j], keys[j], rewards[j], phi[j])
        return rewards, phi
