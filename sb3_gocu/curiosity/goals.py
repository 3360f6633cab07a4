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
      are likelier; section 5.1.4 says "inversely proportional to their order of visit (the final state has
      the highest probability)", which contradicts itself: this follows the parenthesis);
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
    (scale-free: it follows the buffer's own spread); each goal's nearest-neighbour distance is kept exact as
    goals come and go, and searched afresh after a VAE update (:meth:`refresh`). With ``novelty = 0`` only
    exact duplicates are refused, and no threshold and no neighbours are needed between refreshes. When the
    buffer is full, a random goal is replaced.

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
        self.nn_idx = np.full(capacity, -1, dtype=np.int64)  # and which goal it is (-1: none)
        self.size = 0
        self.n_added = 0
        self.n_refused = 0

    def _set_neighbour(self, i: int, dists: np.ndarray) -> None:
        """Goal ``i``'s nearest neighbour from its distances to every goal (inf for itself)."""
        j = int(dists.argmin()) if len(dists) else -1
        self.nn_dist[i], self.nn_idx[i] = (dists[j], j) if j >= 0 and np.isfinite(dists[j]) else (np.inf, -1)

    def threshold(self) -> float:
        if self.novelty == 0:
            return 0.0
        finite = self.nn_dist[: self.size][np.isfinite(self.nn_dist[: self.size])]
        return float(self.novelty * np.median(finite)) if finite.size else 0.0

    def add(self, observations: np.ndarray, embeddings: th.Tensor, rng: np.random.Generator) -> int:
        """Offer candidates one by one (each accepted one counts for the next).

        :return: number of goals added
        """
        added = 0
        for obs, phi in zip(observations, embeddings):
            size = self.size
            dists = th.linalg.vector_norm(self.embeddings[:size] - phi, dim=1).double().numpy()
            if size > 0 and not dists.min() > self.threshold():
                self.n_refused += 1
                continue
            replacing = size == self.capacity
            idx = int(rng.integers(self.capacity)) if replacing else size
            self.observations[idx] = obs
            self.embeddings[idx] = phi
            self.size = n = min(size + 1, self.capacity)
            self.n_added += 1
            added += 1
            if self.novelty == 0:  # only exact duplicates are refused: no threshold, no neighbours to keep
                continue
            d_new = dists if replacing else np.append(dists, np.inf)  # the new goal's distance to each goal
            d_new[idx] = np.inf  # itself (or the goal it replaced)
            self._set_neighbour(idx, d_new)
            nearer = d_new < self.nn_dist[:n]  # goals whose nearest neighbour it is now
            self.nn_dist[:n][nearer] = d_new[nearer]
            self.nn_idx[:n][nearer] = idx
            if replacing:  # goals whose nearest neighbour was the replaced goal: search again
                for i in np.flatnonzero((self.nn_idx[:n] == idx) & ~nearer):
                    if i != idx:
                        d_i = th.linalg.vector_norm(self.embeddings[:n] - self.embeddings[i], dim=1).double().numpy()
                        d_i[i] = np.inf
                        self._set_neighbour(i, d_i)
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
        self._find_neighbours()

    def _find_neighbours(self) -> None:
        """Every goal's nearest neighbour, searched afresh."""
        n = self.size
        self.nn_dist[:] = np.inf
        self.nn_idx[:] = -1
        if n >= 2:
            e = self.embeddings[:n]
            d = th.cdist(e, e)
            d.fill_diagonal_(float("inf"))
            nearest = d.min(dim=1)
            self.nn_dist[:n] = nearest.values.double().numpy()
            self.nn_idx[:n] = nearest.indices.numpy()

    def state_dict(self) -> dict:
        n = self.size
        return {
            "observations": th.from_numpy(self.observations[:n].copy()),
            "embeddings": self.embeddings[:n].clone(),
            "nn_dist": th.from_numpy(self.nn_dist[:n].copy()),
            "nn_idx": th.from_numpy(self.nn_idx[:n].copy()),
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
        if "nn_idx" in state:
            self.nn_dist[:] = np.inf
            self.nn_dist[:n] = state["nn_dist"].numpy()
            self.nn_idx[:] = -1
            self.nn_idx[:n] = state["nn_idx"].numpy()
        else:  # saved before the neighbours' indices were kept (their distances could be stale): search afresh
            self._find_neighbours()
        self.n_added = int(state["n_added"])
        self.n_refused = int(state["n_refused"])
