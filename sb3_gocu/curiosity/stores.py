"""Bounded stores of experience: the memory bank the VAE trains on, and the trajectory store the predictor's
training pairs (s_t, s_{t+y}) are drawn from (section 4.2.3)."""

from __future__ import annotations

import hashlib

import numpy as np
import torch as th


def observation_key(x: np.ndarray) -> bytes:
    """A short key of one raw observation's bytes (16-byte BLAKE2b), for memos and de-duplication."""
    return hashlib.blake2b(np.ascontiguousarray(x).data, digest_size=16).digest()


def distinct_rows(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct rows of ``rows`` by :func:`observation_key` (hashing rows is ~30x faster than
    ``np.unique(axis=0)`` on images).

    :return: the index of each distinct row's first occurrence, in order of first occurrence, and for every row
        the position of its distinct row in that list (``rows[first][inverse]`` equals ``rows``)
    """
    index: dict[bytes, int] = {}
    first: list[int] = []
    inverse = np.empty(len(rows), dtype=np.int64)
    for i, x in enumerate(rows):
        j = index.setdefault(observation_key(x), len(first))
        if j == len(first):
            first.append(i)
        inverse[i] = j
    return np.asarray(first, dtype=np.int64), inverse


class MemoryBank:
    """Observations for VAE training; when full, a random element is replaced (section 4.2.3).

    :param capacity: maximum number of observations (>= 1)
    :param obs_shape: raw observation shape
    :param obs_dtype: raw observation dtype
    """

    def __init__(self, capacity: int, obs_shape: tuple[int, ...], obs_dtype: np.dtype) -> None:
        if capacity < 1:
            raise ValueError(f"memory_size must be >= 1, got {capacity}")
        self.capacity = capacity
        self.observations = np.zeros((capacity, *obs_shape), dtype=obs_dtype)
        self.size = 0

    def add(self, observations: np.ndarray, rng: np.random.Generator) -> None:
        n_free = min(self.capacity - self.size, len(observations))
        if n_free > 0:
            self.observations[self.size : self.size + n_free] = observations[:n_free]
            self.size += n_free
        rest = observations[n_free:]
        if len(rest):
            self.observations[rng.integers(self.capacity, size=len(rest))] = rest

    def state_dict(self) -> dict:
        return {"observations": th.from_numpy(self.observations[: self.size].copy())}

    def load_state_dict(self, state: dict) -> None:
        n = int(state["observations"].shape[0])
        if n > self.capacity:
            raise ValueError(f"saved memory bank holds {n} observations, more than memory_size={self.capacity}")
        self.size = n
        self.observations[:n] = state["observations"].numpy()


class TrajectoryStore:
    """The most recent embedded states of each env, with episode ids, to draw training pairs from.

    The per-env ring length is ``max(ceil(total_capacity / n_envs), min_per_env)``, set for the number of envs
    known when the first state is written (envs added before that, e.g. one per-env wrapper at a time, resize
    the empty rings), so the store holds about ``total_capacity`` states whatever the number of envs. Envs
    added after a state was written get rings of the same length (the store then holds more).

    :param total_capacity: states kept over all envs
    :param embed_dim: size of phi
    :param min_per_env: smallest ring length per env
    """

    def __init__(self, total_capacity: int, embed_dim: int, min_per_env: int = 1) -> None:
        self.total_capacity = total_capacity
        self.min_per_env = min_per_env
        self.capacity = 0
        self.embed_dim = embed_dim
        self.embeddings = th.zeros(0, 0, embed_dim)
        self.episode_ids = np.zeros((0, 0), dtype=np.int64)
        self.count = np.zeros(0, dtype=np.int64)  # states written per env, ever (ring position = count % capacity)

    @property
    def n_envs(self) -> int:
        return len(self.count)

    def ensure_envs(self, n_envs: int) -> None:
        extra = n_envs - self.n_envs
        if extra > 0 and not self.count.any():
            # nothing written yet: size the rings for all the envs known now
            self.capacity = max(-(-self.total_capacity // n_envs), self.min_per_env)
            self.embeddings = th.zeros(self.capacity, n_envs, self.embed_dim)
            self.episode_ids = np.full((self.capacity, n_envs), -1, dtype=np.int64)
            self.count = np.zeros(n_envs, dtype=np.int64)
        elif extra > 0:
            self.embeddings = th.cat([self.embeddings, th.zeros(self.capacity, extra, self.embed_dim)], dim=1)
            self.episode_ids = np.concatenate([self.episode_ids, np.full((self.capacity, extra), -1)], axis=1)
            self.count = np.concatenate([self.count, np.zeros(extra, dtype=np.int64)])

    def add(self, embeddings: th.Tensor, episode_ids: np.ndarray, env_indices: np.ndarray) -> None:
        """Write one state per env of ``env_indices``."""
        pos = self.count[env_indices] % self.capacity
        # through numpy views (the same memory): torch's indexed assignment costs ~0.8 ms a step here, numpy's ~10 us
        self.embeddings.numpy()[pos, env_indices] = embeddings.numpy()
        self.episode_ids[pos, env_indices] = episode_ids
        self.count[env_indices] += 1

    def clear(self) -> None:
        self.episode_ids[:] = -1
        self.count[:] = 0

    def __len__(self) -> int:
        return int(np.minimum(self.count, self.capacity).sum())

    def state_dict(self) -> dict:
        return {
            "embeddings": self.embeddings.clone(),
            "episode_ids": th.from_numpy(self.episode_ids.copy()),
            "count": th.from_numpy(self.count.copy()),
        }

    def load_state_dict(self, state: dict) -> None:
        """Restore a :meth:`state_dict`."""
        self.embeddings = state["embeddings"].clone()
        self.episode_ids = state["episode_ids"].numpy().copy()
        self.count = state["count"].numpy().copy()
        self.capacity = int(self.embeddings.shape[0])

    def _episode_runs(self, holdout: int, held_out: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every state that can start a pair, as (env, chronological index, steps left in its episode within the part).

        The newest ``holdout`` states of each env form the held-out part: ``held_out=False`` keeps the states before
        them (and their pairs' goals before them too), ``held_out=True`` the held-out states."""
        envs, times, room = [], [], []
        filled = np.minimum(self.count, self.capacity)
        for e in range(self.n_envs):
            n = int(filled[e])
            if n == 0:
                continue
            ids = self.episode_ids[(self.count[e] - n + np.arange(n)) % self.capacity, e]
            last = np.append(np.flatnonzero(ids[1:] != ids[:-1]), n - 1)  # chronological index of each run's last state
            end = last[np.searchsorted(last, np.arange(n))]  # the last state of each state's episode
            lo, hi = (max(0, n - holdout), n) if held_out else (0, max(0, n - holdout))
            t = np.arange(lo, hi)
            envs.append(np.full(len(t), e)), times.append(t), room.append(np.minimum(end[t], hi - 1) - t)
        if not envs:
            return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64)
        return np.concatenate(envs), np.concatenate(times), np.concatenate(room)

    def sample_pairs(
        self, n_pairs: int, max_distance: int | None, rng: np.random.Generator, first_visit: bool = False, min_distance: int = 1,
        holdout: int = 0, held_out: bool = False,
    ) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
        """Draw up to ``n_pairs`` pairs (s_t, s_{t+y}) from one episode: s_t uniform among the states with room for
        a gap of ``min_distance``, y uniform in [min_distance, max_distance] within the episode.

        :param max_distance: the largest gap (None: the rest of the episode)
        :param first_visit: give each pair the distance of the *first* visit of the goal after s_t,
            ``min {k in [0, y] : phi(s_{t+k}) == phi(s_{t+y})}``, instead of y: the steps the agent actually needed
            to reach g from s. When the agent stays put or comes back to a state, the plain step gap would label
            (s, s) as "not mastered" once y exceeds the threshold, contradicting the pairs of the same states at
            small y; with the first visit an identical state is at distance 0.
        :param min_distance: the smallest gap (0: any state of the part can start a pair, its own goal at gap 0 included)
        :param holdout: the newest ``holdout`` states of each env are held out: no pair drawn with ``held_out=False``
            touches them
        :param held_out: draw pairs whose s_t (and so g) is among the held-out states instead
        :return: phi(s), phi(g), distance (float), each with the same first dimension (possibly fewer than n_pairs)
        """
        if max_distance is not None and max_distance < min_distance:
            raise ValueError(f"max_distance must be >= min_distance={min_distance}, got {max_distance}")
        empty = th.zeros(0, self.embed_dim)
        if self.capacity == 0 or len(self) < 2 or n_pairs == 0:
            return empty, empty, th.zeros(0)
        env, t, room = self._episode_runs(holdout, held_out)
        ok = room >= min_distance
        env, t, room = env[ok], t[ok], room[ok]
        if len(env) == 0:
            return empty, empty, th.zeros(0)
        pick = rng.integers(len(env), size=n_pairs)
        env, t, room = env[pick], t[pick], room[pick]
        top = room if max_distance is None else np.minimum(room, max_distance)
        y = min_distance + (rng.random(n_pairs) * (top - min_distance + 1)).astype(np.int64)
        start = self.count[env] - np.minimum(self.count[env], self.capacity)
        s_slot, g_slot = (start + t) % self.capacity, (start + t + y) % self.capacity
        e_t = th.from_numpy(env)
        phi_s, phi_g = self.embeddings[th.from_numpy(s_slot), e_t], self.embeddings[th.from_numpy(g_slot), e_t]
        dist = th.from_numpy(y).float()
        if first_visit:
            dist = th.from_numpy(self._first_visits(env, t, y)).float()
        return phi_s, phi_g, dist

    def _first_visits(self, env: np.ndarray, t: np.ndarray, y: np.ndarray) -> np.ndarray:
        """For pairs (chronological index t, gap y) of one episode each: the smallest k in [0, y] whose state
        s_{t+k} has the embedding of s_{t+y} (equal values), by a binary search among each env's states sorted by
        (embedding, time)."""
        k = y.copy()
        filled = np.minimum(self.count, self.capacity)
        for e in np.unique(env):
            n = int(filled[e])
            rows = np.flatnonzero(env == e)
            phi = self.embeddings[(self.count[e] - n + np.arange(n)) % self.capacity, e].numpy() + np.float32(0.0)  # -0.0 -> 0.0
            _, ids = np.unique(np.ascontiguousarray(phi).view(np.dtype((np.void, phi.itemsize * phi.shape[1]))).ravel(), return_inverse=True)
            ids = ids.ravel().astype(np.int64)
            code = ids * n + np.arange(n)  # sorted by code: by embedding, then by time
            order = np.sort(code)
            g = t[rows] + y[rows]
            first = order[np.searchsorted(order, ids[g] * n + t[rows])] % n  # the earliest index >= t with g's embedding
            k[rows] = first - t[rows]
        return k
