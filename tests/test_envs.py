"""Tests of the GoCu/* environments (sb3_gocu.envs). Fast: a few seconds in total."""

import os

os.environ.setdefault("MUJOCO_GL", "egl")  # must precede any import of mujoco

import subprocess
import sys
from pathlib import Path

import cv2
import gymnasium as gym
import numpy as np
import pytest
from minigrid.core.constants import DIR_TO_VEC

from sb3_gocu.envs import (
    ATARI_HARD_EXPLORATION,
    DOORKEY_IDS,
    GOCU_ENV_IDS,
    MUJOCO_IDS,
    SAWYER_LENGTHS,
    register_envs,
)

REPO_ROOT = Path(__file__).resolve().parents[1]
DOORKEY_SIZES = {"GoCu/DoorKey-5x5-v0": 5, "GoCu/DoorKey-8x8-v0": 8, "GoCu/DoorKey-11x11-v0": 11, "GoCu/DoorKey-16x16-v0": 16}
MUJOCO_LENGTHS = {"GoCu/VisualReacher-v0": 50, "GoCu/VisualPusher-v0": 100}
IMAGE_SPACE = gym.spaces.Box(0, 255, (32, 32, 3), np.uint8)


def _pov_frame(env: gym.Env) -> np.ndarray:
    """The observation as specified: agent-POV frame (8 px tiles) resized to 32x32 with INTER_AREA."""
    frame = env.unwrapped.get_frame(tile_size=8, agent_pov=True)
    assert frame.shape == (56, 56, 3)
    return cv2.resize(frame, (32, 32), interpolation=cv2.INTER_AREA)


# ---------------------------------------------------------------- registration


def test_register_envs_idempotent():
    register_envs()
    register_envs()  # must not raise (gymnasium warns/raises on re-registration otherwise)
    for env_id in GOCU_ENV_IDS:
        spec = gym.spec(env_id)
        assert isinstance(spec.entry_point, str) and spec.entry_point.startswith("sb3_gocu.envs.")
    assert set(GOCU_ENV_IDS) == set(DOORKEY_SIZES) | set(MUJOCO_LENGTHS) | set(SAWYER_LENGTHS)
    assert all(gym.spec(env_id).max_episode_steps == n for env_id, n in SAWYER_LENGTHS.items())
    assert gym.spec("GoCu/VisualReacher-v0").max_episode_steps == 50
    assert gym.spec("GoCu/VisualPusher-v0").max_episode_steps == 100


def test_import_does_not_import_mujoco_and_module_prefix_works():
    """Registration is lazy: importing sb3_gocu.envs (and making a DoorKey env) never imports mujoco."""
    code = (
        "import sys, gymnasium as gym\n"
        "env = gym.make('sb3_gocu.envs:GoCu/DoorKey-5x5-v0')\n"
        "obs, _ = env.reset(seed=0)\n"
        "assert obs.shape == (32, 32, 3), obs.shape\n"
        "assert 'mujoco' not in sys.modules, 'mujoco was imported'\n"
        "print('ok')\n"
    )
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO_ROOT), os.environ.get("PYTHONPATH", "")]))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip().endswith("ok")


# ---------------------------------------------------------------- DoorKey


@pytest.mark.parametrize("env_id", DOORKEY_IDS)
def test_doorkey_spaces_grid_and_sparse_reward(env_id):
    size = DOORKEY_SIZES[env_id]
    env = gym.make(env_id)
    assert env.observation_space == IMAGE_SPACE
    assert env.action_space == gym.spaces.Discrete(7)
    assert env.unwrapped.width == size and env.unwrapped.height == size
    assert env.unwrapped.max_steps == 10 * size * size
    env.action_space.seed(0)
    obs, info = env.reset(seed=0)
    assert env.observation_space.contains(obs) and info["is_success"] is False
    assert obs.std() > 0
    for _ in range(300):
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        assert env.observation_space.contains(obs)
        if terminated:
            assert reward > 0 and info["is_success"] is True
        else:
            assert reward == 0 and info["is_success"] is False
        if terminated or truncated:
            obs, info = env.reset()
    env.close()


def test_doorkey_obs_is_resized_agent_pov_frame():
    """The (memoised) observation equals cv2.resize(get_frame(tile_size=8, agent_pov=True)), step after step."""
    env = gym.make("GoCu/DoorKey-8x8-v0")
    env.action_space.seed(1)
    obs, _ = env.reset(seed=1)
    np.testing.assert_array_equal(obs, _pov_frame(env))
    seen = set()
    for _ in range(200):
        obs, _, terminated, truncated, _ = env.step(env.action_space.sample())
        np.testing.assert_array_equal(obs, _pov_frame(env))
        seen.add(obs.tobytes())
        if terminated or truncated:
            obs, _ = env.reset()
            np.testing.assert_array_equal(obs, _pov_frame(env))
    assert len(seen) > 5  # the view does change
    obs.fill(0)  # observations handed out are writable copies: mutating one must not corrupt the cache
    obs2, _, _, _, _ = env.step(6)  # "done" is a no-op in DoorKey
    np.testing.assert_array_equal(obs2, _pov_frame(env))
    env.close()


@pytest.mark.parametrize("env_id", DOORKEY_IDS)
def test_doorkey_turning_left_truncates_at_max_steps(env_id):
    """Turning in place never reaches the goal: reward 0 every step, truncation exactly at 10 * size**2."""
    size = DOORKEY_SIZES[env_id]
    env = gym.make(env_id)
    env.reset(seed=0)
    frames = set()
    for t in range(1, 10 * size * size + 1):
        obs, reward, terminated, truncated, info = env.step(0)  # turn left forever
        assert not terminated and reward == 0 and info["is_success"] is False
        assert truncated == (t == 10 * size * size), t
        frames.add(obs.tobytes())
    assert 2 <= len(frames) <= 4, "turning in place shows at most the four views of one cell"
    env.close()


def test_doorkey_custom_max_steps_kwarg():
    env = gym.make("GoCu/DoorKey-5x5-v0", max_steps=7, render_mode="rgb_array")
    env.reset(seed=0)
    truncs = [env.step(1)[3] for _ in range(7)]
    assert truncs == [False] * 6 + [True]
    assert env.render().shape == (5 * 32, 5 * 32, 3)  # full-grid MiniGrid frame for videos
    env.close()


def test_doorkey_pickup_key_changes_observation():
    env = gym.make("GoCu/DoorKey-8x8-v0")
    env.reset(seed=2)
    base = env.unwrapped
    key_pos = next(
        (i, j) for i in range(base.width) for j in range(base.height)
        if base.grid.get(i, j) is not None and base.grid.get(i, j).type == "key"
    )
    for direction in range(4):
        pos = np.array(key_pos) - DIR_TO_VEC[direction]
        if base.grid.get(*pos) is None:
            base.agent_pos, base.agent_dir = tuple(int(v) for v in pos), direction
            break
    else:
        pytest.fail("no free cell next to the key")
    before, *_ = env.step(6)  # no-op, to get the observation in front of the key
    after, reward, terminated, _, _ = env.step(3)  # pickup
    assert base.carrying is not None and base.carrying.type == "key"
    assert reward == 0 and not terminated
    assert np.abs(after.astype(int) - before.astype(int)).sum() > 0
    env.close()


@pytest.mark.parametrize("env_id", ["GoCu/DoorKey-5x5-v0", "GoCu/DoorKey-11x11-v0"])
def test_doorkey_forced_success(env_id):
    size = DOORKEY_SIZES[env_id]
    env = gym.make(env_id)
    env.reset(seed=0)
    base = env.unwrapped
    # Goal is at (size-2, size-2); the cell above it is on the goal's side of the wall and empty.
    base.agent_pos, base.agent_dir = (size - 2, size - 3), 1  # facing down (+y)
    assert base.grid.get(size - 2, size - 2).type == "goal"
    _, reward, terminated, truncated, info = env.step(2)  # forward
    assert terminated and not truncated
    assert info["is_success"] is True
    assert reward == pytest.approx(1 - 0.9 * 1 / (10 * size * size))
    env.close()


# ---------------------------------------------------------------- MuJoCo


@pytest.mark.parametrize("env_id", MUJOCO_IDS)
def test_mujoco_spaces_length_sparse_reward_and_renders(env_id):
    env = gym.make(env_id)
    assert env.observation_space == IMAGE_SPACE
    original = {"GoCu/VisualReacher-v0": "Reacher-v5", "GoCu/VisualPusher-v0": "Pusher-v5"}[env_id]
    assert env.action_space == gym.make(original).action_space
    wrapper = env.env
    while not hasattr(wrapper, "distance_threshold"):
        wrapper = wrapper.env
    threshold = wrapper.distance_threshold
    env.action_space.seed(0)
    obs0, info = env.reset(seed=0)
    assert env.observation_space.contains(obs0)
    assert obs0.astype(float).var() > 0  # not blank
    assert info["distance"] > threshold and info["is_success"] is False
    t, obs = 0, obs0
    while True:
        t += 1
        action = env.action_space.high if t <= 10 else env.action_space.sample()  # large actions first
        obs, reward, terminated, truncated, info = env.step(action)
        assert env.observation_space.contains(obs)
        assert reward in (0.0, 1.0)
        assert reward == float(info["distance"] < threshold) == float(info["is_success"])
        assert not terminated
        if t == 10:
            assert np.abs(obs.astype(int) - obs0.astype(int)).mean() > 0.5, "render did not change when the arm moved"
        if truncated:
            break
        assert t < 1000
    assert t == MUJOCO_LENGTHS[env_id]
    env.close()


def test_visual_reacher_forced_success():
    env = gym.make("GoCu/VisualReacher-v0")
    env.reset(seed=0)
    base = env.unwrapped
    qpos, qvel = base.data.qpos.copy(), np.zeros_like(base.data.qvel)
    qpos[-2:] = base.get_body_com("fingertip")[:2]  # move the target onto the fingertip
    base.set_state(qpos, qvel)
    _, reward, _, _, info = env.step(np.zeros(2, dtype=np.float32))
    assert info["distance"] < 0.02 and info["is_success"] is True and reward == 1.0
    env.close()


def test_visual_pusher_forced_success_uses_planar_distance():
    env = gym.make("GoCu/VisualPusher-v0")
    env.reset(seed=0)
    base = env.unwrapped
    qpos, qvel = base.data.qpos.copy(), np.zeros_like(base.data.qvel)
    qpos[-4:-2] = qpos[-2:]  # object slide joints := goal slide joints (same body origin)
    base.set_state(qpos, qvel)
    _, reward, _, _, info = env.step(np.zeros(7, dtype=np.float32))
    assert info["distance"] < 0.01 and info["is_success"] is True and reward == 1.0
    # the 3-D distance is stuck at ~0.048 m (object centre above the goal disc): not what we use
    assert np.linalg.norm(base.get_body_com("object") - base.get_body_com("goal")) > 0.04
    env.close()


def test_mujoco_kwargs_and_render_mode():
    env = gym.make("GoCu/VisualReacher-v0", distance_threshold=0.5, render_mode="rgb_array")
    env.reset(seed=0)
    # target within 0.2 m of the base, fingertip 0.21 m from it: always closer than 0.5 m
    _, reward, _, _, info = env.step(np.zeros(2, dtype=np.float32))
    assert reward == 1.0 and info["is_success"] is True
    frame = env.render()
    assert frame.shape == (480, 480, 3) and frame.std() > 0
    env.close()
    with pytest.raises(ValueError):
        gym.make("GoCu/VisualPusher-v0", distance_threshold=0.0)


def test_sb3_check_env():
    from stable_baselines3.common.env_checker import check_env

    for env_id in ("GoCu/DoorKey-5x5-v0", "GoCu/VisualReacher-v0"):
        env = gym.make(env_id)
        check_env(env, warn=False, skip_render_check=True)
        env.close()


# ---------------------------------------------------------------- Atari


def test_atari_ids_available():
    ale_py = pytest.importorskip("ale_py")
    gym.register_envs(ale_py)
    assert ATARI_HARD_EXPLORATION == ("ALE/MontezumaRevenge-v5", "ALE/PrivateEye-v5", "ALE/Pitfall-v5")
    env = gym.make("ALE/MontezumaRevenge-v5")
    obs, _ = env.reset(seed=0)
    assert obs.shape == (210, 160, 3)
    env.close()
