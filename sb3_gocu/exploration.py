"""Exploration measures of the hard-exploration Atari games: the rooms an agent visits, and its best episode score.

:class:`RoomInfoWrapper` reads the room the agent is in from the console RAM after every step and writes it into
``info["room"]``; :class:`ExplorationCallback` (any SB3 algorithm) counts the rooms of each episode and logs
``rollout/rooms_per_episode`` (mean over the last 100 episodes), ``rollout/rooms_total`` (distinct rooms since
training started) and ``rollout/ep_rew_max`` (the best episode return so far). Without a ``RoomInfoWrapper`` the
callback logs the best return alone.

Episodes are Monitor's (``info["episode"]``): a whole game, not a life, when SB3's ``AtariWrapper`` ends an
"episode" at each life lost; without a ``Monitor`` (``make_vec_env`` and the zoo add one) nothing is counted. The counts live in the callback: a resumed run starts them afresh.
"""

from __future__ import annotations

import re
from collections import deque
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.callbacks import BaseCallback

#: the console RAM byte that holds the current room, per game (Montezuma's Revenge: rooms 0-23 of level 1)
ROOM_RAM_INDEX: dict[str, int] = {"MontezumaRevenge": 3}


def atari_game(env: gym.Env) -> str:
    """The game of an ale-py env, from its id: ``ALE/MontezumaRevenge-v5`` and ``MontezumaRevengeNoFrameskip-v4`` ->
    ``MontezumaRevenge``. :param env: the env (any wrapper of an ale-py env)"""
    env_id = env.spec.id if env.spec is not None else ""
    match = re.fullmatch(r"(?:ALE/)?(\w+?)(?:NoFrameskip)?-v\d+", env_id)
    if match is None:
        raise ValueError(f"cannot tell the Atari game of the env id {env_id!r}: pass ram_index")
    return match.group(1)


class RoomInfoWrapper(gym.Wrapper):
    """Writes the room the agent is in (a byte of the console RAM) into ``info["room"]`` at reset and after each step.

    :param env: an ale-py env, or a wrapper of one (SB3's ``AtariWrapper`` included)
    :param ram_index: the RAM byte holding the room; default: the game's, from :data:`ROOM_RAM_INDEX`
    """

    def __init__(self, env: gym.Env, ram_index: int | None = None) -> None:
        super().__init__(env)
        if not hasattr(env.unwrapped, "ale"):
            raise TypeError(f"RoomInfoWrapper needs an ale-py env, got {type(env.unwrapped).__name__}")
        if ram_index is not None and (isinstance(ram_index, bool) or not isinstance(ram_index, (int, np.integer))):
            raise ValueError(f"ram_index must be an integer in [0, 127], got {ram_index!r}")
        if ram_index is None:
            game = atari_game(env)
            if game not in ROOM_RAM_INDEX:
                raise ValueError(f"no known room byte for {game} (known: {sorted(ROOM_RAM_INDEX)}): pass ram_index")
            ram_index = ROOM_RAM_INDEX[game]
        if not 0 <= ram_index < 128:
            raise ValueError(f"ram_index must be in [0, 127] (the Atari 2600 has 128 bytes of RAM), got {ram_index}")
        self.ram_index = int(ram_index)

    def room(self) -> int:
        """The room the agent is in now."""
        return int(self.env.unwrapped.ale.getRAM()[self.ram_index])

    def reset(self, **kwargs: Any) -> tuple[Any, dict]:
        obs, info = self.env.reset(**kwargs)
        info["room"] = self.room()
        return obs, info

    def step(self, action: Any) -> tuple[Any, Any, bool, bool, dict]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        info["room"] = self.room()
        return obs, reward, terminated, truncated, info


class ExplorationCallback(BaseCallback):
    """Logs the rooms visited per episode and in total (from ``info["room"]``, see :class:`RoomInfoWrapper`) and the
    best episode return, at each rollout end.

    :param window: episodes averaged in ``rollout/rooms_per_episode`` (100, as SB3's ``ep_rew_mean``)
    :param verbose: SB3's verbosity
    """

    def __init__(self, window: int = 100, verbose: int = 0) -> None:
        super().__init__(verbose)
        if window < 1:
            raise ValueError(f"window must be >= 1, got {window}")
        #: rooms of each finished episode (the last ``window``)
        self.episode_rooms: deque[int] = deque(maxlen=window)
        #: every room visited since training started
        self.rooms: set[int] = set()
        #: the best episode return so far (-inf before the first episode ends)
        self.max_return = -np.inf
        self._current: list[set[int]] = []

    def state_dict(self) -> dict[str, Any]:
        """The counts of finished episodes, JSON-serialisable (``max_return`` is None before the first episode ends)."""
        return {
            "episode_rooms": list(self.episode_rooms),
            "rooms": sorted(self.rooms),
            "max_return": float(self.max_return) if np.isfinite(self.max_return) else None,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore the counts of a :meth:`state_dict`. :param state: what :meth:`state_dict` returned"""
        self.episode_rooms = deque((int(n) for n in state["episode_rooms"]), maxlen=self.episode_rooms.maxlen)
        self.rooms = {int(r) for r in state["rooms"]}
        best = state["max_return"]
        self.max_return = -np.inf if best is None or not np.isfinite(best) else float(best)

    def _on_training_start(self) -> None:
        if len(self._current) != self.training_env.num_envs:  # a continued learn() keeps the episodes in progress
            self._current = [set() for _ in range(self.training_env.num_envs)]

    def _on_step(self) -> bool:
        for i, info in enumerate(self.locals["infos"]):
            if "room" in info:
                self._current[i].add(int(info["room"]))
            episode = info.get("episode")
            if episode is not None:  # Monitor's end of a whole episode
                self.max_return = max(self.max_return, float(episode["r"]))
                if self._current[i]:
                    self.episode_rooms.append(len(self._current[i]))
                    self.rooms |= self._current[i]
                self._current[i] = set()
        return True

    def _on_rollout_end(self) -> None:
        if self.episode_rooms:
            self.logger.record("rollout/rooms_per_episode", float(np.mean(self.episode_rooms)))
        if self.rooms or any(self._current):
            self.logger.record("rollout/rooms_total", len(self.rooms.union(*self._current)))
        if np.isfinite(self.max_return):
            self.logger.record("rollout/ep_rew_max", self.max_return)
