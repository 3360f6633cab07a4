"""The goal buffer R_g, the three strategies that pick new goals from an episode (section 5.1.4), and the
novelty filter of eq 12.

Goals are kept as raw observations (uint8 images stay uint8) and re-embedded after each VAE update.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import torch as th

GOAL_STRATEGIES = ("random", "proportional", "late")


def select_goal_steps(episode_length: int, n_new: int, strategy: str, rng: np.random.Generator) -> np.ndarray:
    """Steps of an episode that become goal candidates.

    The final state is always a candidate ("in addition to the state reached at the end of the episode");
    ``n_new`` more steps are drawn without replacement among the earlier ones:

    * ``random``: uniformly;
    * ``proportional``: with probability proportional to the order of visit, ``p(t) ~ t + 1`` (later states
      are likelier);
    * ``late``: uniformly among the ``4 * n_new`` steps before the final one.

    :param episode_length: number of recorded states T (indices 0..T-1)
    :param n_new: l, the number of goals drawn besides the final state
    :param strategy: one of :data:`GOAL_STRATEGIES`
    :param rng: random generator
    :return: sorted step indices, the last one being ``T - 1``
    """
    if strategy not in GOAL_STRATEGIES:
        raise ValueError(f"goal_strategy must be one of {GOAL_STRATEGIES}, got {strategy!r}")
    if episode_length <= 0:
        return np.zeros(0, dtype=np.int64)
    last = episode_length - 1
    first = max(0, last - 4 * n_new) if strategy == "late" else 0
    pool = np.arange(first, last)
    k = min(n_new, len(pool))
    if k > 0:
        p = None
        if strategy == "proportional":
            w = (pool + 1).astype(np.float64)
            p = w / w.sum()
        picked = rng.choice(pool, size=k, replace=False, p=p)
    else:
        picked = np.zeros(0, dtype=np.int64)
    return np.sort(np.append(picked, last)).astype(np.int64)


class GoalBuffer:
    """Goals as raw observations with their embeddings.

    Novelty filter (eq 12 with A = I): a candidate is added only if its Euclidean distance in phi-space to
    the nearest stored goal is larger than ``novelty * median nearest-neighbour distance`` of the buffer
    (scale-free: it follows the buffer's own spread). With ``novelty = 0`` only exact duplicates are
    refused. When the buffer is full, a random goal is replaced.

    :param capacity: maximum number of goals
    :param obs_shape: raw observation shape
    :param obs_dtype: raw observation dtype
    :param embed_dim: size of phi
    :param novelty: relative novelty threshold, >= 0
    """

    def __init__(self, capacity: int, obs_shape: tuple[int, ...], obs_dtype: np.dtype, embed_dim: int, novelty: float) -> None:
        if capacity < 1:
            raise ValueError(f"goal_buffer_size must be >= 1, got {capacity}")
        if not novelty >= 0:
            raise ValueError(f"goal_novelty must be >= 0, got {novelty}")
        self.capacity = capacity
        self.novelty = novelty
        self.observations = np.zeros((capacity, *obs_shape), dtype=obs_dtype)
        self.embeddings = th.zeros(capacity, embed_dim)
        # distance of each goal to its nearest other goal (inf while it has none)
        self.nn_dist = np.full(capacity, np.inf, dtype=np.float64)
        self.size = 0
        self.n_added = 0
        self.n_refused = 0

    def threshold(self) -> float:
        finite = self.nn_dist[: self.size][np.isfinite(self.nn_dist[: self.size])]
        return float(self.novelty * np.median(finite)) if finite.size else 0.0

    def add(self, observations: np.ndarray, embeddings: th.Tensor, rng: np.random.Generator) -> int:
        """Offer candidates one by one (each accepted one counts for the next).

        :return: number of goals added
        """
        added = 0
        for obs, phi in zip(observations, embeddings):
            if self.size > 0:
                dists = th.linalg.vector_norm(self.embeddings[: self.size] - phi, dim=1)
                j = int(th.argmin(dists))
                d = float(dists[j])
                if not d > self.threshold():
                    self.n_refused += 1
                    continue
            else:
                j, d = -1, np.inf
            idx = self.size if self.size < self.capacity else int(rng.integers(self.capacity))
            self.observations[idx] = obs
            self.embeddings[idx] = phi
            self.nn_dist[idx] = d
            if j >= 0 and j != idx:
                self.nn_dist[j] = min(self.nn_dist[j], d)
            self.size = min(self.size + 1, self.capacity)
            self.n_added += 1
            added += 1
        return added

    def sample(self, n_sets: int, k: int, rng: np.random.Generator) -> np.ndarray:
        """Indices of ``k`` goals for each of ``n_sets`` episodes, (n_sets, k).

        Without replacement within a set when the buffer holds at least ``k`` goals, with replacement
        otherwise; an empty buffer gives an (n_sets, 0) array.
        """
        if self.size == 0:
            return np.zeros((n_sets, 0), dtype=np.int64)
        if self.size >= k:
            return np.argsort(rng.random((n_sets, self.size)), axis=1)[:, :k].astype(np.int64)
        return rng.integers(self.size, size=(n_sets, k)).astype(np.int64)

    def refresh(self, embed: Callable[[np.ndarray], th.Tensor], batch_size: int = 1024) -> None:
        """Re-embed every goal (after a VAE update) and recompute the nearest-neighbour distances."""
        n = self.size
        for start in range(0, n, batch_size):
            stop = min(n, start + batch_size)
            self.embeddings[start:stop] = embed(self.observations[start:stop])
        self.nn_dist[:] = np.inf
        if n >= 2:
            e = self.embeddings[:n]
            d = th.cdist(e, e)
            d.fill_diagonal_(float("inf"))
            self.nn_dist[:n] = d.min(dim=1).values.double().numpy()

    def state_dict(self) -> dict:
        n = self.size
        return {
            "observations": th.from_numpy(self.observations[:n].copy()),
            "embeddings": self.embeddings[:n].clone(),
            "nn_dist": th.from_numpy(self.nn_dist[:n].copy()),
            "n_added": self.n_added,
            "n_refused": self.n_refused,
        }

    def load_state_dict(self, state: dict) -> None:
        n = int(state["observations"].shape[0])
        if n > self.capacity:
            raise ValueError(f"saved goal buffer holds {n} goals, more than goal_buffer_size={self.capacity}")
        self.size = n
        self.observations[:n] = state["observations"].numpy()
        self.embeddings[:n] = state["embeddings"]
        self.nn_dist[:] = np.inf
        self.nn_dist[:n] = state["nn_dist"].numpy()
        self.n_added = int(state["n_added"])
        self.n_refused = int(state["n_refused"])
