"""What PPO_GoCu writes to the SB3 logger and the Monitor files: each figure only where it was measured, both value
heads' explained variance, the intrinsic return per episode, and no trace of the random-policy pretraining."""

import csv
import math

from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.logger import Logger

import sb3_gocu  # noqa: F401
from conftest import Capture, TINY_IMAGE_CURIOSITY
from sb3_gocu import PPO_GoCu


class Episodes(BaseCallback):
    def __init__(self):
        super().__init__()
        self.count = 0

    def _on_step(self):
        self.count += sum("episode" in info for info in self.locals["infos"])
        return True


def test_logs_hold_what_each_rollout_measured(tmp_path):
    env = make_vec_env("GoCu/DoorKey-5x5-v0", n_envs=2, seed=0, monitor_dir=str(tmp_path))
    curiosity = {**TINY_IMAGE_CURIOSITY, "pretrain_steps": 1024, "vae_train_freq": 1024, "vae_patience": 1, "predictor_train_freq": 512}
    model = PPO_GoCu("CnnPolicy", env, n_steps=128, batch_size=128, n_epochs=1, seed=0, curiosity_kwargs=curiosity)
    capture = Capture()
    model.set_logger(Logger(folder=None, output_formats=[capture]))
    updates = []
    maybe_train = model.curiosity.maybe_train

    def spy():
        out = maybe_train()
        updates.append(set(out))
        return out

    model.curiosity.maybe_train = spy
    episodes = Episodes()
    started = []  # time/fps's clock as learn() set it, before the pretraining
    setup_learn = model._setup_learn

    def record_start(*args, **kwargs):
        result = setup_learn(*args, **kwargs)
        started.append(model.start_time)
        return result

    model._setup_learn = record_start
    model.learn(2048, callback=episodes)

    records = [r for r in capture.records if any(k.startswith("gocu/") for k in r)]
    assert len(records) == len(updates) == 8
    for record, keys in zip(records, updates):
        assert ("gocu/vae_loss" in record) == ("vae_loss" in keys)
        assert ("gocu/predictor_loss" in record) == ("predictor_loss" in keys)
        assert all(math.isfinite(v) for k, v in record.items() if k.startswith("gocu/")), record
    vae_rollouts = sum("gocu/vae_loss" in r for r in records)
    assert 0 < vae_rollouts < len(records), "a VAE figure is logged in the rollouts that trained the VAE, not in every one"
    assert sum("gocu/pretrain_time_s" in r for r in records) == 1
    assert any("train/explained_variance_intrinsic" in r for r in capture.records)
    returns = [r["rollout/ep_intrinsic_rew_mean"] for r in capture.records if "rollout/ep_intrinsic_rew_mean" in r]
    assert returns and all(v > 0 for v in returns)
    assert all("gocu_r" in ep for ep in model.ep_info_buffer)

    # the pretraining's 1024 random-policy steps: in neither the step count, the fps clock nor the Monitor files
    assert model.num_timesteps == 2048
    pretrain_s = next(r["gocu/pretrain_time_s"] for r in records if "gocu/pretrain_time_s" in r)
    assert model.start_time == started[0] + int(pretrain_s * 1e9), "time/fps's clock moved on by the pretraining"
    rows = 0
    for path in tmp_path.glob("*.monitor.csv"):
        with open(path) as f:
            next(f)  # the JSON header
            rows += len(list(csv.DictReader(f)))
    assert rows == episodes.count > 0
    steps = env.get_attr("total_steps")
    assert sum(steps) == 2048, steps
    assert sum(len(r) for r in env.get_attr("episode_returns")) == episodes.count
