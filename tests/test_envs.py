"""The registered environments: spaces, sparse rewards, episode lengths, and MuJoCo renders that show the arm."""

import os

os.environ.setdefault("MUJOCO_GL", "egl")

import gymnasium as gym
import numpy as np
import pytest

import sb3_gocu  # noqa: F401  (registers the ids)
from sb3_gocu.envs import ATARI_HARD_EXPLORATION, DOORKEY_IDS, GOCU_ENV_IDS, MUJOCO_IDS, register_envs

EPISODE_LENGTH = {
    "GoCu/DoorKey-5x5-v0": 250,
    "GoCu/DoorKey-8x8-v0": 640,
    "GoCu/DoorKey-11x11-v0": 1210,
    "GoCu/DoorKey-16x16-v0": 2560,
    "GoCu/VisualReacher-v0": 50,
    "GoCu/VisualPusher-v0": 100,
}


def test_registration_is_idempotent_and_complete():
    register_envs()
    register_envs()
    for env_id in GOCU_ENV_IDS:
        assert env_id in gym.envs.registry
    assert set(GOCU_ENV_IDS) == set(EPISODE_LENGTH)


@pytest.mark.parametrize("env_id", DOORKEY_IDS)
def test_doorkey_spaces_sparse_reward_and_length(env_id):
    env = gym.make(env_id)
    assert env.observation_space == gym.spaces.Box(0, 255, (32, 32, 3), np.uint8)
    assert env.action_space == gym.spaces.Discrete(7)
    obs, info = env.reset(seed=0)
    assert env.observation_space.contains(obs) and info["is_success"] is False
    size = int(env_id.split("-")[1].split("x")[0])
    assert env.unwrapped.width == size and env.unwrapped.height == size
    # turning left forever never reaches the goal: reward 0 at every step, truncation exactly at max_steps
    frames = set()
    for t in range(1, EPISODE_LENGTH[env_id] + 1):
        obs, reward, terminated, truncated, info = env.step(0)
        assert env.observation_space.contains(obs)
        assert reward == 0 and not terminated and not info["is_success"]
        frames.add(obs.tobytes())
        if truncated:
            break
    assert truncated and t == EPISODE_LENGTH[env_id]
    assert 2 <= len(frames) <= 4, "turning in place shows at most the four views of one cell"
    env.close()


def test_doorkey_goal_gives_the_sparse_success_reward_and_key_changes_the_view():
    env = gym.make("GoCu/DoorKey-5x5-v0")
    env.reset(seed=3)
    base = env.unwrapped
    # stand next to the goal, facing it, and step onto it
    goal = next((x, y) for x in range(base.width) for y in range(base.height) if base.grid.get(x, y) is not None and base.grid.get(x, y).type == "goal")
    base.agent_pos = np.array((goal[0], goal[1] - 1))
    base.agent_dir = 1  # facing down (+y)
    base.step_count = 9
    obs, reward, terminated, truncated, info = env.step(base.actions.forward)
    assert terminated and info["is_success"]
    assert reward == pytest.approx(1 - 0.9 * 10 / 250)

    env.reset(seed=3)
    key_pos = next((x, y) for x in range(base.width) for y in range(base.height) if base.grid.get(x, y) is not None and base.grid.get(x, y).type == "key")
    base.agent_pos = np.array((key_pos[0] - 1, key_pos[1])) if base.grid.get(key_pos[0] - 1, key_pos[1]) is None else np.array((key_pos[0], key_pos[1] - 1))
    base.agent_dir = 0 if base.agent_pos[0] == key_pos[0] - 1 else 1
    obs1, *_ = env.step(base.actions.done)  # a no-op that renders the new pose
    obs2, *_ = env.step(base.actions.pickup)
    assert base.carrying is not None and base.carrying.type == "key"
    assert not np.array_equal(obs1, obs2), "picking up the key changes the observation"
    env.close()


@pytest.mark.parametrize("env_id", MUJOCO_IDS)
def test_mujoco_renders_show_the_arm_and_reward_is_sparse(env_id):
    env = gym.make(env_id)
    assert env.observation_space == gym.spaces.Box(0, 255, (32, 32, 3), np.uint8)
    assert isinstance(env.action_space, gym.spaces.Box)
    obs, info = env.reset(seed=0)
    assert env.observation_space.contains(obs)
    assert obs.astype(np.float64).var() > 0, "the render is not blank"
    assert "distance" in info
    first = obs.copy()
    rewards, t = [], 0
    while True:
        t += 1
        obs, reward, terminated, truncated, info = env.step(env.action_space.high)  # push every joint hard
        rewards.append(reward)
        assert reward in (0.0, 1.0) and (reward == 1.0) == info["is_success"]
        assert info["distance"] >= 0
        if terminated or truncated:
            break
    assert truncated and t == EPISODE_LENGTH[env_id]
    assert not np.array_equal(first, obs), "the arm moved, the render changed"
    assert np.abs(first.astype(int) - obs.astype(int)).sum() > 100
    env.close()


def test_atari_ids_exist():
    import ale_py

    gym.register_envs(ale_py)
    assert len(ATARI_HARD_EXPLORATION) == 3
    env = gym.make(ATARI_HARD_EXPLORATION[0])
    obs, _ = env.reset(seed=0)
    assert obs.shape == (210, 160, 3)
    env.close()
