"""The exploration measures of the hard-exploration Atari games (sb3_gocu/exploration.py)."""

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3 import PPO
from stable_baselines3.common.logger import KVWriter, Logger
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import DummyVecEnv

from sb3_gocu.exploration import ExplorationCallback, RoomInfoWrapper, atari_game


class RoomWalk(gym.Env):
    """Five steps an episode through rooms 1, 1, 2, 3, 3 (env 0) or 7, 7, 7, 7, 7 (env 1); return 1 (env 0) or 2 (env 1)."""

    observation_space = gym.spaces.Box(-1, 1, (2,), np.float32)
    action_space = gym.spaces.Discrete(2)

    def __init__(self, which: int = 0) -> None:
        self.rooms = [1, 1, 2, 3, 3] if which == 0 else [7] * 5
        self.reward = 1.0 + which
        self.t = 0

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return np.zeros(2, np.float32), {"room": self.rooms[0]}

    def step(self, action):
        self.t += 1
        done = self.t == 5
        return np.zeros(2, np.float32), self.reward if done else 0.0, done, False, {"room": self.rooms[self.t - 1]}


class Recorder(KVWriter):
    def __init__(self):
        self.records = []

    def write(self, key_values, key_excluded, step=0):
        self.records.append(dict(key_values))


def test_callback_counts_rooms_per_episode_and_in_total_and_the_best_return():
    env = DummyVecEnv([lambda: Monitor(RoomWalk(0)), lambda: Monitor(RoomWalk(1))])
    model = PPO("MlpPolicy", env, n_steps=10, batch_size=20, n_epochs=1, seed=0)
    recorder = Recorder()
    model.set_logger(Logger(folder=None, output_formats=[recorder]))
    callback = ExplorationCallback(window=3)
    model.learn(40, callback=callback)  # 2 rollouts of 10 steps x 2 envs: 4 episodes per env
    assert callback.rooms == {1, 2, 3, 7}
    assert list(callback.episode_rooms) == [1, 3, 1]  # the last 3 of the episodes' room counts (3 and 1 alternate)
    assert callback.max_return == 2.0
    logged = recorder.records[-1]
    assert logged["rollout/rooms_total"] == 4 and logged["rollout/ep_rew_max"] == 2.0
    assert logged["rollout/rooms_per_episode"] == pytest.approx(5 / 3)



def test_callback_counts_survive_a_state_dict_round_trip_through_json():
    import json

    env = DummyVecEnv([lambda: Monitor(RoomWalk(0)), lambda: Monitor(RoomWalk(1))])
    model = PPO("MlpPolicy", env, n_steps=10, batch_size=20, n_epochs=1, seed=0)
    callback = ExplorationCallback(window=3)
    assert callback.state_dict()["max_return"] is None  # no episode yet: JSON null, not -inf
    model.learn(20, callback=callback)
    restored = ExplorationCallback(window=3)
    restored.load_state_dict(json.loads(json.dumps(callback.state_dict())))
    assert restored.rooms == callback.rooms and list(restored.episode_rooms) == list(callback.episode_rooms)
    assert restored.max_return == callback.max_return == 2.0
    assert restored.episode_rooms.maxlen == 3  # the window of the callback it is restored into
    model.learn(20, callback=restored, reset_num_timesteps=False)  # counting goes on from the restored counts
    assert restored.rooms == {1, 2, 3, 7} and list(restored.episode_rooms) == [1, 3, 1]

def test_room_info_wrapper_reads_montezumas_room_byte():
    import ale_py

    gym.register_envs(ale_py)
    env = RoomInfoWrapper(gym.make("ALE/MontezumaRevenge-v5"))
    _, info = env.reset(seed=0)
    assert info["room"] == 1  # the game starts in room 1
    env.unwrapped.ale.setRAM(3, 5)
    assert env.room() == 5
    _, _, _, _, info = env.step(0)
    assert info["room"] == env.unwrapped.ale.getRAM()[3]  # after a step too, byte 3 of the RAM as it is then
    env.close()
    with pytest.raises(ValueError, match="no known room byte for Pitfall.*ram_index"):
        RoomInfoWrapper(gym.make("ALE/Pitfall-v5"))
    with pytest.raises(ValueError, match=r"ram_index must be in \[0, 127\]"):
        RoomInfoWrapper(gym.make("ALE/Pitfall-v5"), ram_index=128)
    with pytest.raises(TypeError, match="needs an ale-py env"):
        RoomInfoWrapper(gym.make("CartPole-v1"))


def test_atari_game_from_the_env_id():
    import ale_py

    gym.register_envs(ale_py)
    assert atari_game(gym.make("ALE/MontezumaRevenge-v5")) == "MontezumaRevenge"
    assert atari_game(gym.make("ALE/PrivateEye-v5")) == "PrivateEye"
    with pytest.raises(ValueError, match="window must be >= 1"):
        ExplorationCallback(window=0)
