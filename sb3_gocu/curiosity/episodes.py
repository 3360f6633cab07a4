"""Per-env episode state: each env's current episode, its K goals, and what the episode has met so far.

For every env, :class:`Episodes` keeps the episode's id, its goals (raw observations and the predictor's goal
halves, the part of the first layer that depends on the goal alone), the episode's most recent states (goal
candidates when it ends), the rewards already computed in it (a memo keyed on the observation's bytes) and the
visit count of each state (for ``revisit_decay``). No SB3 import.
"""

from __future__ import annotations

from collections import deque
from typing import Any

import numpy as np
import torch as th

from sb3_gocu.curiosity.config import EPISODE_MEMORY


def _keys_to_tensor(table: dict[bytes, Any]) -> th.Tensor:
    """The (equal-length) byte keys of a memo as one uint8 tensor, a row per key."""
    return th.from_numpy(np.frombuffer(b"".join(table), dtype=np.uint8).reshape(len(table), -1 if table else 0).copy())


def memo_to_state(memo: dict[bytes, Any]) -> dict[str, th.Tensor]:
    """A memo {key bytes: phi} or {key bytes: (reward, phi)} as tensors (loadable with weights_only=True)."""
    keys = _keys_to_tensor(memo)
    values = list(memo.values())
    if values and isinstance(values[0], tuple):
        return {"keys": keys, "rewards": th.tensor(np.array([r for r, _ in values], dtype=np.float32)),
                "phi": th.from_numpy(np.stack([np.asarray(p) for _, p in values]))}
    return {"keys": keys, "phi": th.stack([th.as_tensor(p) for p in values]) if values else th.zeros(0, 0)}


def memo_from_state(state: dict[str, th.Tensor]) -> dict[bytes, Any]:
    """Inverse of :func:`memo_to_state`."""
    keys = [bytes(k) for k in state["keys"].numpy()]
    if "rewards" in state:
        return dict(zip(keys, zip(state["rewards"].numpy(), state["phi"].numpy())))
    return dict(zip(keys, state["phi"].clone()))


class Episodes:
    """The current episode of each env.

    :param n_goals: K, goals per episode
    :param raw_shape: shape of a raw observation (as kept in the buffers)
    :param raw_dtype: its dtype
    :param goal_part_size: width of the predictor's goal half (its first hidden layer)
    """

    def __init__(self, n_goals: int, raw_shape: tuple[int, ...], raw_dtype: np.dtype, goal_part_size: int) -> None:
        self.n_envs = 0
        self.goal_obs = np.zeros((0, n_goals, *raw_shape), dtype=raw_dtype)
        self.has_goals = np.zeros(0, dtype=bool)  # per env: its episode has K goals (none while the goal buffer is empty)
        self.goal_parts = th.zeros(0, n_goals, goal_part_size)
        self.ids = np.zeros(0, dtype=np.int64)
        self.next_id = 0
        self.states: list[deque] = []  # the episode's most recent raw states (goal candidates)
        self.rewards: list[dict[bytes, tuple[float, np.ndarray]]] = []  # memo: key -> (raw r_gc, phi)
        self.visits: list[dict[bytes, int]] = []
        # states of episodes ended while recording, for goal selection: unbounded, since they hold no more states than
        # the steps since the last add_finished_episode_goals (a rollout); a bound would drop episodes of short ones
        self.finished: deque = deque()

    def grow(self, n_envs: int) -> np.ndarray:
        """Grow to ``n_envs`` envs; returns the indices of the new ones (without goals yet)."""
        old = self.n_envs
        if n_envs <= old:
            return np.zeros(0, dtype=np.int64)
        extra = n_envs - old
        self.goal_obs = np.concatenate([self.goal_obs, np.zeros((extra, *self.goal_obs.shape[1:]), dtype=self.goal_obs.dtype)])
        self.has_goals = np.concatenate([self.has_goals, np.zeros(extra, dtype=bool)])
        self.goal_parts = th.cat([self.goal_parts, th.zeros(extra, *self.goal_parts.shape[1:])])
        self.ids = np.concatenate([self.ids, np.arange(self.next_id, self.next_id + extra)])
        self.next_id += extra
        self.states += [deque(maxlen=EPISODE_MEMORY) for _ in range(extra)]
        self.rewards += [{} for _ in range(extra)]
        self.visits += [{} for _ in range(extra)]
        self.n_envs = n_envs
        return np.arange(old, n_envs)

    def restart(self, env: int, recording: bool) -> None:
        """End env ``env``'s episode (its states become goal candidates if ``recording``) and start a new one."""
        if recording and len(self.states[env]):
            self.finished.append(np.stack(self.states[env]))
        self.states[env].clear()
        self.visits[env].clear()
        self.ids[env] = self.next_id
        self.next_id += 1

    def touch_goals(self, env_indices: np.ndarray) -> None:
        """The goal halves of ``env_indices`` change: drop their episodes' reward memos (computed against the old ones)."""
        for e in env_indices:
            self.rewards[e].clear()

    def count_visits(self, keys: list[bytes], env_indices: np.ndarray) -> np.ndarray:
        """Count this visit of each observation in its env's episode; returns n >= 1 (this visit included)."""
        visits = np.empty(len(keys), dtype=np.int64)
        for j, (e, key) in enumerate(zip(env_indices, keys)):
            counts = self.visits[e]
            if key not in counts and len(counts) >= EPISODE_MEMORY:
                counts.clear()
            visits[j] = counts[key] = counts.get(key, 0) + 1
        return visits

    def remember_reward(self, env: int, key: bytes, reward: float, phi: np.ndarray) -> None:
        """Memoise a state's raw r_gc and phi in env ``env``'s episode."""
        memo = self.rewards[env]
        if len(memo) >= EPISODE_MEMORY:
            memo.clear()
        memo[key] = (reward, phi)

    def state_dict(self) -> dict[str, Any]:
        return {
            "goal_obs": th.from_numpy(self.goal_obs.copy()),
            "goal_valid": th.from_numpy(self.has_goals.copy())[:, None].expand(-1, self.goal_obs.shape[1]).clone(),
            "episode_ids": th.from_numpy(self.ids.copy()),
            "episodes": [th.from_numpy(np.stack(ep)) if len(ep) else th.zeros(0) for ep in self.states],
            "finished_episodes": [th.from_numpy(ep) for ep in self.finished],
            "next_episode_id": self.next_id,
            # memoised values: recomputing them in other batches can change the last bits (float sums are not
            # batch-invariant), so they are saved for a bit-exact resumption
            "goal_parts": self.goal_parts.clone(),
            "reward_cache": [memo_to_state(c) for c in self.rewards],
            "visit_counts": [{"keys": _keys_to_tensor(c), "counts": th.tensor(list(c.values()), dtype=th.int64)} for c in self.visits],
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore the goals, ids and states of a :meth:`state_dict` into envs already grown to its number (the goal
        halves and the memos: :meth:`load_memos`)."""
        self.goal_obs[:] = state["goal_obs"].numpy()
        self.has_goals[:] = state["goal_valid"][:, 0].numpy()  # (n_envs, K), all or none of K per env
        self.ids[:] = state["episode_ids"].numpy()
        self.next_id = int(state["next_episode_id"])
        for e, ep in enumerate(state["episodes"]):
            self.states[e].clear()
            if ep.ndim > 1:
                self.states[e].extend(ep.numpy())
        self.finished.clear()
        self.finished.extend(ep.numpy() for ep in state["finished_episodes"])

    def load_memos(self, state: dict[str, Any]) -> None:
        """Restore the goal halves (if saved) and the memos of a :meth:`state_dict`, after the goals were refreshed."""
        if "goal_parts" in state:
            self.goal_parts[:] = state["goal_parts"]
            self.touch_goals(np.arange(self.n_envs))
        for memo, saved in zip(self.rewards, state.get("reward_cache", [])):
            memo.update(memo_from_state(saved))
        for counts, saved in zip(self.visits, state.get("visit_counts", [])):
            counts.update({bytes(k): int(n) for k, n in zip(saved["keys"].numpy(), saved["counts"].tolist())})
