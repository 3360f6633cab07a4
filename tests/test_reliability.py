"""Reliability (issue 5): validation, non-finite values, exact resumption, crash safety, determinism, bounded
memory, safe loading. See docs/reliability.md for the guarantees these tests pin down."""

import copy
import os
import re
import shutil
import signal
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.logger import Logger

from sb3_gocu import GoalCuriosityModule, GoCuVecEnvWrapper, GoCuWrapper, PPO_GoCu
from sb3_gocu.checkpoints import (
    GoCuCheckpointCallback,
    check_model_file,
    latest_checkpoint,
    list_checkpoints,
    remove_stale_temporaries,
)
from sb3_gocu.curiosity import checks, episodes, scoring
from sb3_gocu.curiosity.config import VAE_HOLDOUT
from sb3_gocu.curiosity.networks import FoldedPredictor, MasteryPredictor
from sb3_gocu.curiosity.stores import observation_key
from sb3_gocu.curiosity.training import nonfinite_entries

from conftest import Capture, SMALL_CURIOSITY, ChainEnv

TESTS_DIR = os.path.dirname(os.path.abspath(__file__))


class ImageChainEnv(gym.Env):
    """ChainEnv seen as a small RGB image (HWC or CHW, uint8 in [0, 255] or float in [0, 1]): a red column at the
    position and a green row at the time step."""

    def __init__(self, layout="hwc", dtype=np.uint8, size=16, length=6, max_steps=20):
        self.layout, self.dtype, self.size, self.length, self.max_steps = layout, np.dtype(dtype), size, length, max_steps
        shape = (size, size, 3) if layout == "hwc" else (3, size, size)
        self.observation_space = spaces.Box(0, 255 if self.dtype == np.uint8 else 1.0, shape, self.dtype)
        self.action_space = spaces.Discrete(2)
        self.pos = self.t = 0

    def _obs(self):
        img = np.zeros((self.size, self.size, 3), dtype=np.float32)
        img[:, int(self.pos * (self.size - 1) / self.length), 0] = 1.0
        img[self.t % self.size, :, 1] = 0.5
        if self.layout == "chw":
            img = img.transpose(2, 0, 1)
        return (img * 255).astype(np.uint8) if self.dtype == np.uint8 else img.astype(self.dtype)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.pos = self.t = 0
        return self._obs(), {}

    def step(self, action):
        self.t += 1
        self.pos = int(np.clip(self.pos + (1 if action == 1 else -1), 0, self.length))
        terminated = self.pos == self.length
        return self._obs(), float(terminated), terminated, not terminated and self.t >= self.max_steps, {}


def chain_venv(n_envs=2, seed=0):
    return make_vec_env(lambda: ChainEnv(), n_envs=n_envs, seed=seed)


def small_model(env=None, seed=0, policy="MlpPolicy", curiosity=None, **kwargs):
    settings = dict(n_steps=64, batch_size=64, n_epochs=2, seed=seed)
    settings.update(kwargs)
    return PPO_GoCu(policy, env if env is not None else chain_venv(), curiosity_kwargs={**SMALL_CURIOSITY, **(curiosity or {})}, **settings)


def differences(a, b, path=""):
    """Paths where two nested states (tensors, arrays, numbers, dicts, lists) differ, bit for bit."""
    if isinstance(a, th.Tensor):
        same = isinstance(b, th.Tensor) and a.dtype == b.dtype and a.shape == b.shape and th.equal(a, b)
        return [] if same else [path]
    if isinstance(a, np.ndarray):
        return [] if isinstance(b, np.ndarray) and a.dtype == b.dtype and np.array_equal(a, b) else [path]
    if isinstance(a, dict):
        if not isinstance(b, dict) or set(a) != set(b):
            return [f"{path} (keys)"]
        return [d for k in a for d in differences(a[k], b[k], f"{path}/{k}")]
    if isinstance(a, (list, tuple)):
        if not isinstance(b, (list, tuple)) or len(a) != len(b):
            return [f"{path} (length)"]
        return [d for i, (x, y) in enumerate(zip(a, b)) for d in differences(x, y, f"{path}/{i}")]
    return [] if type(a) is type(b) and a == b else [path]


def parameters(model):
    return {k: v.clone() for k, v in model.policy.state_dict().items()}


# ============================================================================================ 1. validation
BOX = ChainEnv().observation_space


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(n_goals=0), r"n_goals \(K\) must be in \[1, goal_buffer_size=32\]"),
        (dict(n_goals=33), r"n_goals \(K\) must be in \[1, goal_buffer_size=32\], got 33"),
        (dict(n_goals=2.5), r"n_goals must be an integer"),
        (dict(reward_scale=0.0), r"reward_scale \(delta\) must be > 0"),
        (dict(reward_scale=-1.0), r"reward_scale \(delta\) must be > 0"),
        (dict(reward_scale=float("nan")), r"reward_scale must be a finite number, got nan"),
        (dict(reward_scale=float("inf")), r"reward_scale must be a finite number, got inf"),
        (dict(vae_lr=float("inf")), r"vae_lr must be a finite number, got inf"),
        (dict(image_channels=True), r"image_channels must be None or an integer >= 1, got True"),
        (dict(image_channels=2.0), r"image_channels must be None or an integer >= 1, got 2.0"),
        (dict(obs_key=0), r"obs_key must be None or a string, got 0"),
        (dict(goal_strategy="newest"), r"goal_strategy must be one of \('random', 'proportional', 'late'\)"),
        (dict(aggregation="min"), r"aggregation \(h\) must be one of"),
        (dict(max_distance=0), r"max_distance \(d_max\) must be >= 1"),
        (dict(label_slope=0.0), r"label_slope \(b\) must be > 0"),
        (dict(label_slope=-0.8), r"label_slope \(b\) must be > 0"),
        (dict(goal_buffer_size=0, n_goals=1), r"goal_buffer_size must be >= 1"),
        (dict(memory_size=0), r"memory_size must be >= 1"),
        (dict(predictor_hidden=(32, 0)), r"predictor_hidden must be a non-empty sequence of integers >= 1"),
        (dict(predictor_train_freq=0), r"predictor_train_freq must be >= 1"),
        (dict(vae_update_epochs=-1), r"vae_update_epochs must be >= 0, got -1"),
        (dict(vae_update_epochs=2.0), r"vae_update_epochs must be an integer, got 2.0"),
        (dict(alpha=float("inf")), r"alpha must be a finite number"),
        (dict(revisit_decay="half"), r"revisit_decay must be one of \('none', 'inverse_sqrt', 'first_visit'\), got 'half'"),
        # types: a bool is not an integer, a string not a number, a number not a flag
        (dict(n_goals=True), r"n_goals must be an integer, got True"),
        (dict(memory_size=np.float64(1e4)), r"memory_size must be an integer, got "),
        (dict(reward_scale="10"), r"reward_scale must be a finite number, got '10'"),
        (dict(label_threshold=None), r"label_threshold must be a finite number, got None"),
        (dict(alpha=True), r"alpha must be a finite number, got True"),
        (dict(vae_lr=[1e-3]), r"vae_lr must be a finite number, got \[0.001\]"),
        (dict(vae_dedupe="no"), r"vae_dedupe must be True or False, got 'no'"),
        (dict(vae_dedupe=None), r"vae_dedupe must be True or False, got None"),
        (dict(first_visit_distance=1), r"first_visit_distance must be True or False, got 1"),
    ],
)
def test_module_refuses_invalid_settings(kwargs, match):
    with pytest.raises(ValueError, match=match):
        GoalCuriosityModule(BOX, **{**SMALL_CURIOSITY, **kwargs})
    # the same error at PPO_GoCu's construction, not at the first step
    with pytest.raises(ValueError, match=match):
        PPO_GoCu("MlpPolicy", chain_venv(1), curiosity_kwargs={**SMALL_CURIOSITY, **kwargs})


#: 32x32 RGB frames: 3,072 bytes each
FRAMES = spaces.Box(0, 255, (32, 32, 3), np.uint8)


@pytest.mark.parametrize(
    "kwargs, store",
    [
        (dict(memory_size=10**9), "memory bank"),
        (dict(goal_buffer_size=10**9), "goal buffer"),
        (dict(predictor_train_freq=10**12), "trajectory store"),
        (dict(pretrain_steps=10**9), "pretraining's episodes"),
    ],
)
def test_a_setting_that_would_exhaust_memory_is_refused_before_allocating(kwargs, store, monkeypatch):
    """Refused with the setting's name, the bytes the stores would need and the memory available, before numpy tries."""
    monkeypatch.setattr(checks, "available_memory", lambda: 8 * 10**9)
    (name, value), = kwargs.items()
    with pytest.raises(ValueError, match=rf"^{name}={value}: the curiosity module's stores would need [0-9.]+ GB \({store}: [0-9.]+ GB\), "
                                         rf"more than the 8\.00 GB of memory available; lower {name}$"):
        GoalCuriosityModule(FRAMES, **kwargs)


def test_goals_for_more_envs_than_memory_holds_are_refused_with_n_goals(monkeypatch):
    """Each env's episode keeps its K goals' frames: K x n_envs frames, checked as the envs arrive."""
    monkeypatch.setattr(checks, "available_memory", lambda: 8 * 10**8)
    module = GoalCuriosityModule(FRAMES, n_goals=10**4, goal_buffer_size=10**4)  # 0.03 GB of goal buffer: fits
    module.ensure_envs(16)  # 16 x 10^4 frames: 0.49 GB, fits
    with pytest.raises(ValueError, match=r"^n_goals=10000 with 32 envs: .* \(goals of the episodes: 0\.98 GB\), more than the 0\.80 GB"):
        module.ensure_envs(32)
    assert module.n_envs == 16


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: PPO_GoCu("MlpPolicy", chain_venv(1), intrinsic_coef=-0.25), r"intrinsic_coef \(sigma\) must be a finite number >= 0, got -0.25"),
        (lambda: PPO_GoCu("MlpPolicy", chain_venv(1), intrinsic_coef=float("nan")), r"intrinsic_coef \(sigma\) must be a finite number >= 0"),
        (lambda: PPO_GoCu("MlpPolicy", chain_venv(1), intrinsic_coef=float("inf")), r"intrinsic_coef \(sigma\) must be a finite number >= 0, got inf"),
        (lambda: PPO_GoCu("MlpPolicy", chain_venv(1), intrinsic_coef="0.25"), r"intrinsic_coef \(sigma\) must be a finite number >= 0, got '0.25'"),
        (lambda: PPO_GoCu("MlpPolicy", chain_venv(1), intrinsic_episodic="yes"), r"intrinsic_episodic must be True or False, got 'yes'"),
        (lambda: GoCuVecEnvWrapper(chain_venv(1), mode="add"), r"mode must be one of \('sum', 'separate'\), got 'add'"),
        (lambda: GoCuWrapper(ChainEnv(), mode="add"), r"mode must be one of \('sum', 'separate'\)"),
        (lambda: GoCuVecEnvWrapper(chain_venv(1), intrinsic_coef=-1.0), r"intrinsic_coef \(sigma\) must be a finite number >= 0, got -1.0"),
        (lambda: GoCuWrapper(ChainEnv(), intrinsic_coef=-1.0), r"intrinsic_coef \(sigma\) must be a finite number >= 0"),
        (lambda: GoCuWrapper(ChainEnv(), intrinsic_coef="0.5"), r"intrinsic_coef \(sigma\) must be a finite number >= 0, got '0.5'"),
        (lambda: GoCuVecEnvWrapper(chain_venv(1), mode="separate", intrinsic_coef=0.5), r"mode='sum' only.*PPO_GoCu\(intrinsic_coef"),
        (lambda: GoCuCheckpointCallback(True, "unused"), r"save_freq must be an integer >= 1, got True"),
    ],
)
def test_algorithm_and_wrappers_refuse_invalid_settings(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_callback_and_wrappers_refuse_what_is_not_theirs():
    """An unwrapped VecEnv handed to GoCuCallback, or a dict handed to a wrapper as its module, is refused at
    construction, naming the type."""
    from sb3_gocu import GoCuCallback

    with pytest.raises(TypeError, match="gocu must be a GoCuVecEnvWrapper, a GoCuWrapper, a GoalCuriosityModule or None, got DummyVecEnv"):
        GoCuCallback(chain_venv(1))
    with pytest.raises(TypeError, match="module must be a GoalCuriosityModule or None, got dict"):
        GoCuVecEnvWrapper(chain_venv(1), module={"n_goals": 3})
    with pytest.raises(TypeError, match="module must be a GoalCuriosityModule or None, got dict"):
        GoCuWrapper(ChainEnv(), module={"n_goals": 3})
    module = GoalCuriosityModule(BOX, **SMALL_CURIOSITY)
    assert GoCuCallback(module).module is module
    assert GoCuCallback(GoCuVecEnvWrapper(chain_venv(1), module=module)).module is module


def test_numpy_scalars_are_accepted_as_settings():
    """A sweep or a config hands numpy scalars: they pass the type checks and mean their values."""
    module = GoalCuriosityModule(BOX, **{**SMALL_CURIOSITY, "n_goals": np.int64(3), "reward_scale": np.float32(4.0),
                                        "vae_dedupe": np.bool_(False), "vae_beta": np.float64(0.2)})
    assert (module.n_goals, module.reward_scale, module.vae_dedupe, module.vae_beta) == (3, 4.0, False, 0.2)
    model = PPO_GoCu("MlpPolicy", chain_venv(1), n_steps=np.int64(8), batch_size=8, intrinsic_coef=np.float64(0.5),
                     curiosity_kwargs=SMALL_CURIOSITY)
    assert (model.intrinsic_coef, model.n_steps) == (0.5, 8)


@pytest.mark.parametrize(
    "space",
    [spaces.Box(-1.0, 1.0, (8, 8, 3), np.float32), spaces.Box(0.0, np.inf, (3, 8, 8), np.float32)],
    ids=["negative-low", "unbounded-high"],
)
def test_float_images_outside_the_vae_range_are_refused(space):
    with pytest.raises(ValueError, match=r"observation_space: a float32 image Box needs finite bounds with low >= 0"):
        GoalCuriosityModule(space)
    # inside it, the values reach the VAE divided by the largest high
    module = GoalCuriosityModule(spaces.Box(0.0, 4.0, (8, 8, 3), np.float32))
    x = module.adapter.to_tensor(np.full((1, 8, 8, 3), 2.0, np.float32))
    assert x.shape == (1, 3, 8, 8) and th.all(x == 0.5)


@pytest.mark.parametrize(
    "space",
    [
        spaces.Discrete(5),
        spaces.MultiDiscrete([3, 4]),
        spaces.Dict({"direction": spaces.Discrete(4), "mission": spaces.MultiBinary(3)}),
        spaces.Box(0, 1, (2, 3, 8, 8), np.float32),
    ],
    ids=["Discrete", "MultiDiscrete", "Dict-without-image-or-vector", "Box-4d"],
)
def test_unembeddable_observation_spaces_are_refused_with_what_is_supported(space):
    with pytest.raises(ValueError, match=r"observation_space: GoCu cannot embed .*Supported: Box images .*1-D Box vectors, or a Dict"):
        GoalCuriosityModule(space, **SMALL_CURIOSITY)


@pytest.mark.parametrize(
    "shape, dtype",
    [((16, 16, 3), np.uint8), ((3, 16, 16), np.uint8), ((16, 16, 3), np.float32), ((3, 16, 16), np.float32), ((16, 16), np.uint8)],
    ids=["HWC-uint8", "CHW-uint8", "HWC-float", "CHW-float", "HW-uint8"],
)
def test_images_in_any_layout_and_dtype_embed_with_finite_rewards(shape, dtype):
    high = 255 if dtype == np.uint8 else 1.0
    space = spaces.Box(0, high, shape, dtype)
    module = GoalCuriosityModule(space, **SMALL_CURIOSITY, seed=0)
    assert module.adapter.is_image and module.adapter.input_shape == ((3, 16, 16) if len(shape) == 3 else (1, 16, 16))
    module.recording = True
    rng = np.random.default_rng(0)
    rewards = []
    for t in range(60):
        obs = space.sample() if dtype == np.uint8 else rng.random((2, *shape)).astype(dtype)
        obs = np.stack([space.sample(), space.sample()]) if dtype == np.uint8 else obs
        raw, normalized = module.step(obs, np.array([t % 9 == 8, t % 13 == 12]))
        rewards.append((raw, normalized))
        if t == 30:
            module.add_finished_episode_goals()
            module.train_vae(epochs=1)
    phi = module.embed(module.memory.observations[:4])
    assert phi.shape == (4, SMALL_CURIOSITY["embed_dim"]) and th.isfinite(phi).all()
    assert module.goal_buffer.size > 0
    raw, normalized = map(np.concatenate, zip(*rewards))
    assert np.isfinite(raw).all() and np.isfinite(normalized).all() and raw.max() > 0


@pytest.mark.parametrize("layout, dtype", [("chw", np.float32), ("hwc", np.uint8)], ids=["CHW-float", "HWC-uint8"])
def test_ppo_gocu_trains_on_images(layout, dtype):
    env = make_vec_env(lambda: ImageChainEnv(layout, dtype), n_envs=2, seed=0)
    model = small_model(env, policy="CnnPolicy", n_steps=32, batch_size=32, n_epochs=1)
    model.learn(128)
    assert model.num_timesteps == 128 and model.curiosity.pretrained
    assert np.isfinite(model.rollout_buffer.intrinsic_rewards).all() and model.rollout_buffer.intrinsic_rewards.max() > 0
    assert all(th.isfinite(p).all() for p in model.policy.parameters())


# ============================================================================================ 2. non-finite values
def test_nan_rewards_and_losses_never_reach_the_rollout_buffer(monkeypatch):
    nan_mastery = lambda self, state_part, goal_part: th.full(goal_part.shape[:2], float("nan"))  # noqa: E731
    nan_logits = lambda self, phi_s, phi_g: th.full((len(phi_s), 2), float("nan"), requires_grad=True)  # noqa: E731
    monkeypatch.setattr(FoldedPredictor, "mastery_from_parts", nan_mastery)
    monkeypatch.setattr(MasteryPredictor, "forward", nan_logits)
    model = small_model(curiosity=dict(predictor_train_freq=128))
    capture = Capture()
    model.set_logger(Logger(folder=None, output_formats=[capture]))
    seen = []

    class Spy(BaseCallback):
        def _on_rollout_end(self):
            seen.append(self.model.rollout_buffer.intrinsic_rewards.copy())

        def _on_step(self):
            return True

    model.learn(256, callback=Spy())
    assert len(seen) == 2 and all(np.isfinite(r).all() for r in seen)
    assert np.isfinite(model.rollout_buffer.advantages).all() and np.isfinite(model.rollout_buffer.intrinsic_returns).all()
    stats = model.curiosity.stats
    assert stats["nonfinite_rewards"] > 0, "the NaN rewards were counted"
    assert stats["predictor_skipped_updates"] > 0 and stats["predictor_skipped_updates_total"] > 0, "the NaN losses were skipped"
    logged = {k for record in capture.records for k in record}
    assert {"gocu/nonfinite_rewards", "gocu/predictor_skipped_updates", "gocu/predictor_skipped_updates_total"} <= logged
    assert all(th.isfinite(p).all() for p in model.policy.parameters())


def recorded_module(seed=0, steps=80, **kwargs):
    module = GoalCuriosityModule(BOX, **{**SMALL_CURIOSITY, **kwargs}, seed=seed)
    module.recording = True
    rng = np.random.default_rng(seed)
    for t in range(steps):
        module.step(rng.random((2, 2)).astype(np.float32), np.array([t % 10 == 9, t % 7 == 6]))
    module.add_finished_episode_goals()
    return module


@pytest.mark.parametrize("name", ["vae", "predictor"])
def test_an_update_that_makes_weights_nonfinite_is_rolled_back(name):
    module = recorded_module(vae_patience=0)  # early stopping would keep the starting weights by itself
    network, optimizer = getattr(module, name), getattr(module.trainer, f"{name}_optimizer")
    before = copy.deepcopy(network.state_dict())
    real_step = optimizer.step

    def overflowing_step(*args, **kwargs):  # a finite loss whose step overflows a weight
        real_step(*args, **kwargs)
        with th.no_grad():
            next(network.parameters()).view(-1)[0] = float("inf")

    optimizer.step = overflowing_step
    with pytest.warns(UserWarning, match=f"{name} update made .* non-finite; the update was rolled back"):
        module.train_vae() if name == "vae" else module.train_predictor()
    assert not differences(before, network.state_dict()), "the weights of before the update are back"
    assert module.stats[f"{name}_restored_updates"] == 1
    assert not nonfinite_entries(network.state_dict())
    raw, _ = module.step(np.random.default_rng(1).random((2, 2)).astype(np.float32), np.zeros(2, bool))
    assert np.isfinite(raw).all()


def scripted_vae_update(losses, patience=1, epochs=6):
    """A VAE update whose held-out losses are ``losses`` (before the update, then after each epoch); returns the
    module, its statistics, the weights before the update and after each epoch."""
    module = recorded_module(vae_patience=patience, vae_update_epochs=epochs)
    script = iter(losses)
    module.trainer.vae_val_loss = lambda data, weights, pixel_weights=None: next(script)
    states = [copy.deepcopy(module.vae.state_dict())]
    job = module.vae_job()
    fit = module.trainer.fit_vae(job, on_epoch=lambda epoch: states.append(copy.deepcopy(module.vae.state_dict())))
    return module, fit, states


def test_vae_early_stopping_keeps_the_best_epoch():
    # before 10, then 9, 8, 8.5 (no new best: patience 1 stops), 7 never measured
    module, fit, states = scripted_vae_update([10.0, 9.0, 8.0, 8.5, 7.0], patience=1)
    assert (fit.epochs_run, fit.best_epoch, fit.val_loss, fit.val_loss_start) == (3, 2, 8.0, 10.0)
    assert len(states) == 4
    assert not differences(states[2], module.vae.state_dict()), "the weights of epoch 2"
    assert differences(states[3], module.vae.state_dict()), "not those of the last epoch run"
    # patience 2 goes on through one more epoch without a new best, and takes epoch 4's
    module, fit, states = scripted_vae_update([10.0, 9.0, 8.0, 8.5, 7.0, 7.5, 7.6], patience=2)
    assert (fit.epochs_run, fit.best_epoch) == (6, 4)
    assert not differences(states[4], module.vae.state_dict())


def test_vae_update_without_a_better_epoch_changes_nothing():
    module, fit, states = scripted_vae_update([5.0, 6.0, 7.0], patience=1)
    assert (fit.epochs_run, fit.best_epoch) == (1, 0)
    assert not differences(states[0], module.vae.state_dict()), "back to the starting weights"
    n_pairs = len(module.trajectories)
    phi_goals = module.goal_buffer.embeddings.clone()
    encoder = module.encoder
    out = module.use_fits([fit])
    assert out["vae_best_epoch"] == 0 and out["vae_epochs_run"] == 1
    assert module.encoder is encoder and len(module.trajectories) == n_pairs > 0, "embeddings still valid: kept"
    assert th.equal(module.goal_buffer.embeddings, phi_goals)
    # an update with a better epoch re-embeds and clears the predictor's trajectories
    module, fit, _ = scripted_vae_update([5.0, 4.0, 4.5], patience=1)
    assert len(module.trajectories) > 0
    module.use_fits([fit])
    assert len(module.trajectories) == 0


def test_vae_holdout_split_and_patience_zero():
    module = recorded_module(vae_patience=1)
    distinct = {observation_key(x) for x in module.memory.observations[: module.memory.size]}
    job = module.vae_job()
    train = {observation_key(x) for x in job.data}
    val = {observation_key(x) for x in job.val_data}
    assert not train & val and train | val == distinct
    assert len(val) == round(VAE_HOLDOUT * len(distinct)) > 0
    assert np.isclose(job.weights.sum() + job.val_weights.sum(), len(distinct), rtol=1e-5)
    module = recorded_module(vae_patience=0, vae_update_epochs=3)
    job = module.vae_job()
    assert job.val_data is None and len(job.data) == len(distinct)
    fit = module.trainer.fit_vae(job)
    assert fit.epochs_run == fit.best_epoch == 3


def test_pretraining_runs_every_epoch():
    """The pretraining runs every one of its ``vae_epochs`` on the whole bank (no held-out loss measured), and the
    updates after it stop early with vae_patience, after at most ``vae_update_epochs``."""
    module = recorded_module(vae_patience=1, vae_epochs=4)
    script = iter([10.0, 11.0, 12.0])
    module.trainer.vae_val_loss = lambda data, weights, pixel_weights=None: next(script)
    out = module.pretrain()
    assert (out["vae_epochs_run"], out["vae_best_epoch"]) == (4, 4) and module.pretrained
    assert next(script) == 10.0, "no held-out loss measured in the pretraining"
    script = iter([10.0, 11.0, 12.0])
    out = module.train_vae()
    assert (out["vae_epochs_run"], out["vae_best_epoch"]) == (1, 0), "the later update: patience 1"
    module = recorded_module(vae_patience=1, vae_epochs=4, vae_update_epochs=2)
    script = iter([10.0, 9.0, 8.0, 7.0])
    module.pretrain()
    module.trainer.vae_val_loss = lambda data, weights, pixel_weights=None: next(script)
    out = module.train_vae()
    assert (out["vae_epochs_run"], out["vae_best_epoch"]) == (2, 2), "still improving: stopped by vae_update_epochs"


@pytest.mark.parametrize("kwargs, message", [
    (dict(vae_patience=-1), r"vae_patience must be >= 0, got -1"),
    (dict(vae_patience=1.5), r"vae_patience must be an integer"),
])
def test_vae_early_stopping_settings_are_checked(kwargs, message):
    with pytest.raises(ValueError, match=message):
        GoalCuriosityModule(BOX, **{**SMALL_CURIOSITY, **kwargs})


def test_nonfinite_gradients_skip_the_step():
    module = recorded_module()
    before = copy.deepcopy(module.predictor.state_dict())
    hook = next(module.predictor.parameters()).register_hook(lambda g: g * float("nan"))
    out = module.train_predictor()
    hook.remove()
    assert out["predictor_skipped_updates"] > 0 and np.isnan(out["predictor_loss"])
    after = module.predictor.state_dict()
    assert all(th.equal(before[k], after[k]) for k in before if "running" not in k and "num_batches" not in k), "no step was taken"
    assert module.stats.get("predictor_restored_updates", 0) == 0


def test_a_nan_weight_set_by_hand_is_loud_not_silent(tmp_path):
    module = recorded_module()
    with th.no_grad():
        module.vae.encoder[0].weight[0, 0] = float("nan")
    with th.no_grad():  # inference embeds with a copy of the VAE taken after each update: broken too
        module.encoder.encoder[0].weight[0, 0] = float("nan")
    module.begin_episodes(np.arange(2))  # both envs have goals: their rewards go through the broken VAE
    assert module.episodes.has_goals.all()
    raw, normalized = module.step(np.full((2, 2), 0.3, np.float32), np.zeros(2, bool))
    assert np.array_equal(raw, [0, 0]) and np.isfinite(normalized).all(), "no NaN bonus, the reward is 0"
    assert module.stats["nonfinite_rewards"] == 2
    with pytest.warns(UserWarning, match="vae holds non-finite values .* nothing finite to restore"):
        module.train_vae()
    assert module.stats["vae_nonfinite_parameters"] > 0
    # and such a state is refused when loaded, with the tensor named
    th.save(module.state_dict(), tmp_path / "broken.pt")
    fresh = GoalCuriosityModule(BOX, **SMALL_CURIOSITY, seed=1)
    with pytest.raises(ValueError, match=r"the vae holds non-finite values in \['encoder.0.weight'"):
        fresh.load_state_dict(th.load(tmp_path / "broken.pt", weights_only=True))


# ============================================================================================ 3. exact resumption
N = 512  # 4 rollouts of n_steps 64 x 2 envs; the VAE (P_vae 512) and the predictor (P_m 256) retrain on both sides


def make_resume_model(kind):
    if kind == "image":
        env, policy = make_vec_env(lambda: ImageChainEnv(), n_envs=2, seed=0), "CnnPolicy"
    else:
        env, policy = chain_venv(), "MlpPolicy"
    return small_model(env, policy=policy, learning_rate=lambda progress: 3e-4 * progress)  # a schedule, on purpose


@pytest.mark.parametrize("kind", ["vector", "image"])
def test_resume_from_a_checkpoint_matches_the_uninterrupted_run_bit_for_bit(kind, tmp_path):
    saved_state = {}

    class GrabAtSave(BaseCallback):
        def _on_rollout_start(self):
            if self.model.num_timesteps == N:
                saved_state.update(copy.deepcopy(self.model.curiosity.state_dict()))

        def _on_step(self):
            return True

    uninterrupted = make_resume_model(kind)
    checkpoints = GoCuCheckpointCallback(N // 2, tmp_path, save_env=True)  # calls of 2 envs: N env steps
    uninterrupted.learn(2 * N, callback=[checkpoints, GrabAtSave()])
    assert [steps for steps, _ in list_checkpoints(tmp_path)] == [N, 2 * N]

    resumed = PPO_GoCu.load(tmp_path / f"rl_model_{N}_steps.zip", restore_env=True)
    # the curiosity module at the save, bit for bit: networks, optimisers, goal buffer, memory bank, normaliser,
    # trajectory store, goal-sampling generators, per-env goals and episodes, memoised values
    assert not differences(saved_state, resumed.curiosity.state_dict())
    assert resumed.num_timesteps == N and resumed.env.module is resumed.curiosity
    resumed.learn(N, reset_num_timesteps=False)

    assert resumed.num_timesteps == uninterrupted.num_timesteps == 2 * N
    assert not differences(parameters(uninterrupted), parameters(resumed))
    assert not differences(uninterrupted.policy.optimizer.state_dict(), resumed.policy.optimizer.state_dict())
    assert not differences(uninterrupted.curiosity.state_dict(), resumed.curiosity.state_dict())
    assert np.array_equal(uninterrupted.rollout_buffer.intrinsic_rewards, resumed.rollout_buffer.intrinsic_rewards)


def test_learn_save_load_learn_matches_one_learn_call(tmp_path):
    """learn(N); save(save_env=True); load(restore_env=True); learn(N, reset_num_timesteps=False) == learn(2N), with
    constant schedules (the first learn(N) sees total_timesteps = N, not 2N)."""
    reference = small_model()
    reference.learn(2 * N)
    first = small_model()
    first.learn(N)
    first.save(tmp_path / "half", save_env=True)
    del first
    resumed = PPO_GoCu.load(tmp_path / "half", restore_env=True)
    resumed.learn(N, reset_num_timesteps=False)
    assert not differences(parameters(reference), parameters(resumed))
    assert not differences(reference.curiosity.state_dict(), resumed.curiosity.state_dict())


# ============================================================================================ 4. crash safety
CRASH_SCRIPT = """
import sys
import torch as th
th.set_num_threads(1)
sys.path.insert(0, {tests_dir!r})
from conftest import ChainEnv, SMALL_CURIOSITY
from stable_baselines3.common.callbacks import CheckpointCallback
from stable_baselines3.common.env_util import make_vec_env
from sb3_gocu import PPO_GoCu
from sb3_gocu.checkpoints import GoCuCheckpointCallback

model = PPO_GoCu("MlpPolicy", make_vec_env(ChainEnv, n_envs=2, seed=0), n_steps=64, batch_size=64, n_epochs=2, seed=0,
                 curiosity_kwargs=SMALL_CURIOSITY)
callbacks = [GoCuCheckpointCallback(128, {ckpt!r}, name_prefix="gocu", save_env=True),  # ours: at rollout boundaries
             CheckpointCallback(save_freq=100, save_path={ckpt!r}, name_prefix="rl_model")]  # SB3's / the zoo's --save-freq
print("training", flush=True)
model.learn(10**9, callback=callbacks)
"""


def test_a_run_killed_with_sigkill_resumes_from_its_last_checkpoint(tmp_path):
    ckpt = tmp_path / "checkpoints"
    script = tmp_path / "train.py"
    script.write_text(CRASH_SCRIPT.format(tests_dir=TESTS_DIR, ckpt=str(ckpt)))
    proc = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        deadline = time.time() + 600  # a hang guard, not a speed check: the run takes seconds
        while time.time() < deadline and proc.poll() is None:
            if len(list_checkpoints(ckpt, "gocu")) >= 3 and list_checkpoints(ckpt, "rl_model"):
                break
            time.sleep(0.05)
        assert proc.poll() is None, proc.stdout.read().decode()[-3000:]
        assert len(list_checkpoints(ckpt, "gocu")) >= 3, "no checkpoint within 600 s"
    finally:
        os.kill(proc.pid, signal.SIGKILL)  # mid-run: possibly mid-save
        proc.wait()
    assert proc.returncode == -signal.SIGKILL

    # every file with a checkpoint's name is complete; a temporary of a save cut short is cleaned up
    for path in ckpt.glob("*.zip"):
        check_model_file(path)
    remove_stale_temporaries(ckpt, "gocu")
    remove_stale_temporaries(ckpt, "rl_model")
    assert not list(ckpt.glob(".*.tmp"))

    path = latest_checkpoint(ckpt, "gocu")
    steps = int(re.search(r"_(\d+)_steps", path.name).group(1))
    model = PPO_GoCu.load(path, restore_env=True)
    assert model.num_timesteps == steps and steps % 256 == 0
    assert model.curiosity.pretrained and model.curiosity.n_recorded_steps > steps and model.curiosity.goal_buffer.size > 0
    model.learn(256, reset_num_timesteps=False)
    assert model.num_timesteps == steps + 256

    # SB3's CheckpointCallback (the zoo's --save-freq) wrote atomic PPO_GoCu files with the curiosity state too
    sb3_path = latest_checkpoint(ckpt, "rl_model")
    sb3_model = PPO_GoCu.load(sb3_path, env=chain_venv())
    assert sb3_model.curiosity.pretrained and sb3_model.curiosity.memory.size > 0
    sb3_model.learn(128, reset_num_timesteps=False)


def test_a_failed_save_leaves_the_previous_file_whole(tmp_path, monkeypatch):
    model = small_model()
    model.learn(128)
    path = tmp_path / "model.zip"
    model.save(path)
    good = path.read_bytes()

    def crash_midway(self, f, exclude=None, include=None):
        f.write(b"PK\x03\x04 half a zip")
        raise KeyboardInterrupt

    monkeypatch.setattr(BaseAlgorithm, "save", crash_midway)
    with pytest.raises(KeyboardInterrupt):
        model.save(path)
    assert path.read_bytes() == good and os.listdir(tmp_path) == ["model.zip"]


def test_latest_checkpoint_skips_an_unreadable_newest_file(tmp_path):
    model = small_model()
    callback = GoCuCheckpointCallback(64, tmp_path)  # 64 calls of 2 envs: every 128 env steps, as SB3's would
    model.learn(512, callback=callback)
    assert [s for s, _ in list_checkpoints(tmp_path)] == [128, 256, 384, 512]
    (tmp_path / "rl_model_640_steps.zip").write_bytes(b"PK\x03\x04 not finished")
    with pytest.warns(UserWarning, match="skipping an unreadable checkpoint"):
        assert latest_checkpoint(tmp_path).name == "rl_model_512_steps.zip"


# ============================================================================================ 5. determinism
def test_two_runs_with_one_seed_give_identical_updates_and_rewards():
    runs = []
    for seed in (0, 0, 1):
        th.manual_seed(1000 + len(runs))  # a different global state before each run: the seed alone must decide
        model = small_model(seed=seed, curiosity=dict(predictor_train_freq=128))
        model.learn(256)  # pretraining, 2 rollouts, 2 PPO updates, 1 predictor update
        runs.append(model)
    a, b, c = runs
    assert not differences(parameters(a), parameters(b))
    assert not differences(a.curiosity.state_dict(), b.curiosity.state_dict())
    assert np.array_equal(a.rollout_buffer.intrinsic_rewards, b.rollout_buffer.intrinsic_rewards)
    assert differences(parameters(a), parameters(c)), "another seed gives another run"


def test_module_initial_weights_depend_on_its_seed_alone():
    th.manual_seed(1)
    a = GoalCuriosityModule(BOX, **SMALL_CURIOSITY, seed=7)
    th.manual_seed(2)
    b = GoalCuriosityModule(BOX, **SMALL_CURIOSITY, seed=7)
    assert not differences(a.state_dict(), b.state_dict())


# ============================================================================================ 6. bounded memory
def test_stores_stay_at_their_capacities(monkeypatch):
    monkeypatch.setattr(episodes, "EPISODE_MEMORY", 10)
    monkeypatch.setattr(scoring, "PHI_MEMO_SIZE", 50)
    caps = dict(goal_buffer_size=6, n_goals=3, memory_size=20, predictor_train_freq=40, max_distance=6,
                vae_train_freq=200, new_goals_per_episode=3, goal_novelty=0.0)
    module = GoalCuriosityModule(BOX, **{**SMALL_CURIOSITY, **caps}, seed=0)
    module.recording = True
    n_envs, rng = 4, np.random.default_rng(0)
    module.ensure_envs(n_envs)
    sizes = lambda: (module.goal_buffer.observations.nbytes, module.memory.observations.nbytes,  # noqa: E731
                     module.trajectories.embeddings.numel(), module.normalizer.returns.size)
    for t in range(1500):
        module.step(rng.random((n_envs, 2)).astype(np.float32), rng.random(n_envs) < 0.08)
        if t == 0:
            first = sizes()
        if t % 64 == 63:
            module.maybe_train()
        assert module.goal_buffer.size <= 6 and module.memory.size <= 20
        assert len(module.trajectories) <= module.trajectories.capacity * n_envs <= max(40, 2 * 6 * n_envs)
        assert all(len(c) <= 10 for c in module.episodes.rewards) and all(len(e) <= 10 for e in module.episodes.states)
        assert len(module.scorer.phi_memo) <= 50
        # the episodes ended since the last drain: per env, its steps since then and the episode memory before them
        assert sum(len(e) for e in module.episodes.finished) <= n_envs * (64 + 10)
    assert sizes() == first, "no store grew"
    assert module.goal_buffer.size == 6 and module.goal_buffer.n_added > 6, "the goal buffer filled and replaced goals"
    assert module.memory.size == 20 and module.n_recorded_steps == 1500 * n_envs


# ============================================================================================ 7. loading
def test_every_tensor_file_in_a_model_loads_with_weights_only(tmp_path):
    model = small_model()
    model.learn(256)
    model.save(tmp_path / "m.zip")
    with zipfile.ZipFile(tmp_path / "m.zip") as archive:
        tensor_files = [n for n in archive.namelist() if n.endswith(".pth")]
        assert {"curiosity.pth", "global_rng.pth", "policy.pth"} <= set(tensor_files)
        for name in tensor_files:
            with archive.open(name) as f:
                th.load(f, weights_only=True)


def corrupt(path, how):
    data = bytearray(path.read_bytes())
    if how == "truncated":
        data = data[: len(data) // 2]
    elif how == "flipped-member-byte":
        with zipfile.ZipFile(path) as archive:
            info = archive.getinfo("curiosity.pth")
        i = info.header_offset + 100 + info.compress_size // 2
        data[i] ^= 0xFF
    elif how == "flipped-directory-bytes":
        for i in range(len(data) - 22, len(data) - 18):  # the end-of-central-directory signature
            data[i] ^= 0xFF
    elif how == "empty":
        data = bytearray()
    path.write_bytes(bytes(data))


@pytest.fixture(scope="module")
def saved_model(tmp_path_factory) -> Path:
    """A PPO_GoCu file after 128 training steps, saved once for the corruption tests to copy."""
    model = small_model()
    model.learn(128)
    path = tmp_path_factory.mktemp("saved") / "model.zip"
    model.save(path)
    return path


@pytest.mark.parametrize("how", ["truncated", "flipped-member-byte", "flipped-directory-bytes", "empty"])
def test_a_corrupt_or_truncated_model_file_gives_a_clear_error(tmp_path, saved_model, how):
    path = tmp_path / "model.zip"
    shutil.copyfile(saved_model, path)
    corrupt(path, how)
    with pytest.raises(ValueError, match=rf"{re.escape(str(path))}: .*(corrupt|truncated)"):
        PPO_GoCu.load(path, env=chain_venv())
    with pytest.raises(ValueError, match=r"corrupt|truncated"):
        PPO_GoCu.load(str(path)[: -len(".zip")])  # the SB3 way, without the suffix


@pytest.mark.parametrize("decay", ["none", "inverse_sqrt"])
def test_a_loaded_module_gives_the_same_rewards_bit_for_bit(tmp_path, decay):
    """Memoised embeddings and rewards are part of the state: recomputing them in another batch can change their
    last bits (a row computed alone is not bit-identical to the same row computed in a batch of two). So are the
    visit counts of the episodes in progress (``revisit_decay``)."""
    space = spaces.Box(0, 255, (16, 16, 3), np.uint8)
    module = GoalCuriosityModule(space, **SMALL_CURIOSITY, seed=0, revisit_decay=decay)
    module.recording = True
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 256, (12, 16, 16, 3), dtype=np.uint8)
    for t in range(40):
        module.step(frames[rng.integers(12, size=2)], np.array([t % 9 == 8, t % 11 == 10]))
    module.add_finished_episode_goals()
    module.begin_episodes(np.arange(2))
    module.step(frames[:1], np.zeros(1, bool), env_indices=np.array([0]))  # frame 0 computed alone, memoised
    th.save(module.state_dict(), tmp_path / "module.pt")
    loaded = GoalCuriosityModule(space, **SMALL_CURIOSITY, seed=1, revisit_decay=decay)
    loaded.load_state_dict(th.load(tmp_path / "module.pt", weights_only=True))
    assert not differences(module.state_dict(), loaded.state_dict())
    for m in (module, loaded):
        m.recording = True
    for t in range(30):
        batch, dones = frames[rng.integers(12, size=2)], np.array([t % 7 == 6, False])
        batch[0] = frames[0] if t == 0 else batch[0]
        r1, n1 = module.step(batch, dones)
        r2, n2 = loaded.step(batch, dones)
        assert np.array_equal(r1, r2) and np.array_equal(n1, n2), t
    assert not differences(module.state_dict(), loaded.state_dict())


def test_an_update_that_embeds_every_observation_to_one_point_is_rolled_back():
    module = recorded_module(vae_patience=0)
    before = copy.deepcopy(module.vae.state_dict())
    real_step, dense = module.trainer.vae_optimizer.step, module.vae.encoder[2]

    def killing_step(*args, **kwargs):  # every unit of the embedding layer negative on every observation
        real_step(*args, **kwargs)
        with th.no_grad():
            dense.weight.zero_()
            dense.bias.fill_(-1.0)

    module.trainer.vae_optimizer.step = killing_step
    with pytest.warns(UserWarning, match="embedded every frame to one point"):
        out = module.train_vae()
    assert not differences(before, module.vae.state_dict()), "the encoder of before the update is back"
    assert out["vae_collapsed"] == 1 and out["vae_best_epoch"] == 0
    assert module.stats["vae_collapsed_updates"] == 1
    phi = module.embed(module.memory.observations[: module.memory.size])
    assert len(th.unique(phi, dim=0)) > 1
