"""What a model file holds: each distinct observation once, no curiosity state when excluded, and SB3's
CheckpointCallback arguments with their meaning in GoCuCheckpointCallback."""

import io
import zipfile

import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import VecNormalize

from conftest import SMALL_CURIOSITY, TINY_IMAGE_CURIOSITY, ChainEnv
from sb3_gocu import PPO_GoCu
from sb3_gocu.checkpoints import GoCuCheckpointCallback, list_checkpoints
from sb3_gocu.curiosity import GoalCuriosityModule
from sb3_gocu.curiosity.persistence import _decompressed, unpack


def same(a, b):
    if isinstance(a, th.Tensor):
        return a.dtype == b.dtype and a.shape == b.shape and th.equal(a, b)
    if isinstance(a, dict):
        return set(a) == set(b) and all(same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b))
    return a == b


def test_the_saved_state_holds_each_distinct_observation_once():
    space = spaces.Box(0, 255, (32, 32, 3), np.uint8)
    module = GoalCuriosityModule(space, seed=0, **TINY_IMAGE_CURIOSITY)
    rng = np.random.default_rng(0)
    pool = rng.integers(0, 256, (6, 32, 32, 3), dtype=np.uint8)
    module.recording = True
    for t in range(400):  # 1,600 observations of 6 distinct ones: memory bank, goals, episodes
        module.step(pool[rng.integers(0, 6, 4)], rng.random(4) < 0.05)
        if t == 100:
            module.pretrain()
        if t % 64 == 0:
            module.maybe_train()
    state = module.state_dict()
    assert module.memory.size == 512 and module.goal_buffer.size > 0
    assert _decompressed(state["observation_table"]).shape == (6, 32, 32, 3)
    assert state["memory"]["observations"].dtype == th.int32 and state["memory"]["observations"].shape == (512,)
    packed, full = io.BytesIO(), io.BytesIO()
    th.save(state, packed)
    th.save(unpack(module.state_dict()), full)
    assert len(packed.getvalue()) < len(full.getvalue()) - 500 * 32 * 32 * 3  # the bank's 512 images went
    restored = GoalCuriosityModule(space, seed=1, **TINY_IMAGE_CURIOSITY)
    restored.load_state_dict(th.load(io.BytesIO(packed.getvalue()), weights_only=True))
    assert same(unpack(restored.state_dict()), unpack(module.state_dict()))


def small_model(env=None):
    env = env or make_vec_env(ChainEnv, n_envs=2, seed=0)
    return PPO_GoCu("MlpPolicy", env, n_steps=64, batch_size=64, n_epochs=1, seed=0, curiosity_kwargs=SMALL_CURIOSITY)


def test_save_without_the_curiosity_state_and_load_to_act(tmp_path):
    model = small_model()
    model.learn(256)
    model.save(tmp_path / "full")
    model.save(tmp_path / "policy", exclude=["curiosity"])
    with zipfile.ZipFile(tmp_path / "policy.zip") as archive:
        names = archive.namelist()
    assert "curiosity.pth" not in names and "policy.pth" in names and "global_rng.pth" in names
    assert (tmp_path / "policy.zip").stat().st_size < (tmp_path / "full.zip").stat().st_size

    with pytest.warns(UserWarning, match="no curiosity state"):
        fresh = PPO_GoCu.load(tmp_path / "policy.zip")
    assert not fresh.curiosity.pretrained
    acting = PPO_GoCu.load(tmp_path / "full.zip", curiosity=False)  # the file's curiosity state is not read
    assert acting.curiosity is None
    with pytest.raises(ValueError, match="loaded with curiosity=False"):
        acting.learn(64)
    full = PPO_GoCu.load(tmp_path / "full.zip")
    assert full.curiosity.pretrained
    for loaded in (fresh, acting):
        assert all(th.equal(a, b) for a, b in zip(loaded.policy.state_dict().values(), full.policy.state_dict().values()))
    obs = np.zeros((1, *model.observation_space.shape), dtype=np.float32)
    assert acting.predict(obs, deterministic=True)[0] == full.predict(obs, deterministic=True)[0]
    with pytest.raises(ValueError, match="needs the curiosity state"):
        PPO_GoCu.load(tmp_path / "full.zip", curiosity=False, restore_env=True)


def test_checkpoint_callback_keeps_sb3_arguments(tmp_path):
    env = VecNormalize(make_vec_env(ChainEnv, n_envs=2, seed=0))
    model = small_model(env)
    callback = GoCuCheckpointCallback(save_freq=96, save_path=tmp_path, name_prefix="run", save_vecnormalize=True)
    model.learn(512, callback=callback)
    # due at calls 96 and 192 (in the rollouts of calls 65-128 and 129-192; a rollout is 64 calls, 128 env steps),
    # written at the next rollout boundary: 256 and 384 env steps
    assert [s for s, _ in list_checkpoints(tmp_path, "run")] == [256, 384]
    assert sorted(p.name for p in tmp_path.glob("*.pkl")) == ["run_vecnormalize_256_steps.pkl", "run_vecnormalize_384_steps.pkl"]
