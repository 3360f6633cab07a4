"""rl-zoo3 integration: the launchers (train, enjoy, record_video), the config files, -i, -optimize with a
shared journal storage, and plot_train.

The launchers run as subprocesses (``python -m sb3_gocu.train ...``) with tiny budgets; one PPO_GoCu run on
DoorKey-5x5 is trained once per module and shared. About 2-3 minutes on 2 cores.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import io
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import optuna
import pytest
import yaml

from sb3_gocu import PAPER_N_ENVS, PAPER_PPO_KWARGS
from sb3_gocu.zoo import (
    GOCU_IMAGE_TRIAL_PARAMS,
    GOCU_TRIAL_PARAMS,
    convert_ppo_gocu_params,
    default_conf_file,
    register_zoo,
    sample_ppo_gocu_params,
    with_default_conf,
)

REPO = Path(__file__).resolve().parents[1]
HYPERPARAMS = REPO / "sb3_gocu" / "hyperparams"
DOORKEY = "GoCu/DoorKey-5x5-v0"
DOORKEY_DIR = "GoCu-DoorKey-5x5-v0"  # the zoo's folder name for the id
ENV_IDS = (
    "GoCu/DoorKey-5x5-v0",
    "GoCu/DoorKey-8x8-v0",
    "GoCu/DoorKey-11x11-v0",
    "GoCu/DoorKey-16x16-v0",
    "GoCu/VisualReacher-v0",
    "GoCu/VisualPusher-v0",
    "GoCu/VisualSawyerReacher-v1",
    "GoCu/VisualSawyerDoorHook-v1",
    "GoCu/VisualSawyerPusher-v1",
    "GoCu/VisualSawyerMultiObjectPusher-v1",
    "GoCu/VisualSawyerPickAndPlace-v1",
    "ALE/MontezumaRevenge-v5",
    "ALE/PrivateEye-v5",
    "ALE/Pitfall-v5",
)
TINY_CURIOSITY = (
    "dict(pretrain_steps=128, predictor_train_freq=256, vae_epochs=1, vae_update_epochs=1, predictor_pairs=256, predictor_epochs=1, "
    "predictor_hidden=(64, 64))"
)
TINY = ["--num-threads", "1", "--eval-freq", "-1", "--hyperparams", "n_envs:2", "n_steps:64", "batch_size:64"]
TINY_GOCU = [*TINY, f"curiosity_kwargs:{TINY_CURIOSITY}"]


def run(module: str, *args: str, cwd: Path, timeout: float = 240) -> str:
    """Run ``python -m module args`` in ``cwd`` on one thread; fail with its output unless it exits with 0."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "MPLBACKEND": "Agg"}
    proc = subprocess.run(
        [sys.executable, "-m", module, *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout
    )
    assert proc.returncode == 0, f"{module} {' '.join(args)} failed:\n{proc.stdout[-4000:]}\n{proc.stderr[-4000:]}"
    return proc.stdout


@pytest.fixture(scope="module")
def gocu_run(tmp_path_factory):
    """One PPO_GoCu run trained by the zoo: (work dir, log folder, model zip, train stdout)."""
    work = tmp_path_factory.mktemp("zoo")
    out = run("sb3_gocu.train", "--algo", "ppo_gocu", "--env", DOORKEY, "-n", "2048", "-f", "logs", "--seed", "0", *TINY_GOCU, cwd=work)
    model = work / "logs" / "ppo_gocu" / f"{DOORKEY_DIR}_1" / f"{DOORKEY_DIR}.zip"
    return work, work / "logs", model, out


# ------------------------------------------------------------------------------------------ in-process checks
def test_register_zoo_is_idempotent():
    import rl_zoo3
    from rl_zoo3.hyperparams_opt import HYPERPARAMS_CONVERTER, HYPERPARAMS_SAMPLER
    from rl_zoo3.utils import ALGOS

    from sb3_gocu import PPO_GoCu

    register_zoo()
    ppo_sampler = HYPERPARAMS_SAMPLER["ppo"]
    register_zoo()
    assert ALGOS["ppo_gocu"] is PPO_GoCu and rl_zoo3.ALGOS["ppo_gocu"] is PPO_GoCu
    assert HYPERPARAMS_SAMPLER["ppo_gocu"] is sample_ppo_gocu_params
    assert HYPERPARAMS_CONVERTER["ppo_gocu"] is convert_ppo_gocu_params
    assert HYPERPARAMS_SAMPLER["ppo"] is ppo_sampler, "the ppo sampler is wrapped once, not once per call"
    assert ppo_sampler._sb3_gocu_wrapped.__name__ == "sample_ppo_params"


def test_default_conf_file():
    gocu, ppo = str(HYPERPARAMS / "ppo_gocu.yml"), str(HYPERPARAMS / "ppo.yml")
    assert with_default_conf(["--algo", "ppo_gocu", "--env", DOORKEY, "-n", "10"]) == ["--algo", "ppo_gocu", "--env", DOORKEY, "-n", "10", "--conf-file", gocu]
    assert with_default_conf(["--algo", "ppo", "--env=ALE/Pitfall-v5"])[-2:] == ["--conf-file", ppo]
    # ppo on an id our ppo.yml does not list keeps the zoo's own file
    assert with_default_conf(["--algo", "ppo", "--env", "CartPole-v1"]) == ["--algo", "ppo", "--env", "CartPole-v1"]
    assert default_conf_file("a2c", DOORKEY) == HYPERPARAMS / "a2c.yml"
    assert default_conf_file("dqn", DOORKEY) == HYPERPARAMS / "dqn.yml"
    assert default_conf_file("a2c", "CartPole-v1") is None and default_conf_file("sac", DOORKEY) is None
    # a given config file wins, long or short flag
    for flag in ("--conf-file", "-conf"):
        argv = ["--algo", "ppo_gocu", "--env", DOORKEY, flag, "x.yml"]
        assert with_default_conf(argv) == argv


def test_config_files_hold_the_paper_values():
    files = {name: yaml.safe_load((HYPERPARAMS / f"{name}.yml").read_text()) for name in ("ppo_gocu", "ppo", "ppo_dropin")}
    ppo_keys = dict(n_envs=PAPER_N_ENVS, **PAPER_PPO_KWARGS, policy="CnnPolicy")
    budgets = {"5x5": 5e5, "8x8": 2e6, "11x11": 4e6, "16x16": 5e6, "Visual": 5e5}
    paper_gocu = dict(n_goals=50, goal_buffer_size=1500, new_goals_per_episode=7, goal_strategy="proportional", reward_scale=10, prior_weight=3, distance_weight=1, label_threshold=15, label_slope=0.8)
    for name, entries in files.items():
        for env_id in ENV_IDS:
            assert env_id in entries, f"{env_id} missing in {name}.yml"
            entry = entries[env_id]
            if env_id.startswith("GoCu/"):
                assert {k: entry[k] for k in ppo_keys} == ppo_keys, (name, env_id)
                assert entry["n_timesteps"] == next(v for k, v in budgets.items() if k in env_id)
            else:
                assert entry["frame_stack"] == 4 and entry["n_envs"] == 8 and entry["policy"] == "CnnPolicy"
                rooms = ["sb3_gocu.RoomInfoWrapper"] if "Montezuma" in env_id else []  # Montezuma's room byte
                assert entry["env_wrapper"] == ["stable_baselines3.common.atari_wrappers.AtariWrapper", *rooms]
                callbacks = entry["callback"] if isinstance(entry["callback"], list) else [entry["callback"]]
                assert "sb3_gocu.ExplorationCallback" in callbacks
                assert entry["env_kwargs"] == {"frameskip": 1, "repeat_action_probability": 0.0}
            if name == "ppo":
                assert "curiosity_kwargs" not in entry and "vec_env_wrapper" not in entry
                assert entry.get("callback", "sb3_gocu.ExplorationCallback") == "sb3_gocu.ExplorationCallback"  # no GoCu
            if name == "ppo_dropin":
                (wrapper,) = entry["vec_env_wrapper"]
                callbacks = entry["callback"] if isinstance(entry["callback"], list) else [entry["callback"]]
                assert wrapper["sb3_gocu.GoCuVecEnvWrapper"]["mode"] == "sum" and callbacks[0] == "sb3_gocu.GoCuCallback"
    gocu = files["ppo_gocu"]
    for env_id in ENV_IDS[:4]:
        assert gocu[env_id]["intrinsic_coef"] == 0.25 and gocu[env_id]["curiosity_kwargs"] == paper_gocu
    for env_id in ENV_IDS[4:11]:
        assert gocu[env_id]["curiosity_kwargs"] == {**paper_gocu, "n_goals": 25, "goal_buffer_size": 1000, "predictor_hidden": [512, 512, 512], "predictor_lr": 3e-4, "predictor_batch_size": 64}
    for env_id in ENV_IDS[11:]:
        assert gocu[env_id]["curiosity_kwargs"]["image_channels"] == 1
    # the curiosity stream stops at each lost life on Atari only (docs/results.md: running across lives paid for dying)
    assert [gocu[env_id].get("intrinsic_episodic", False) for env_id in ENV_IDS] == [False] * 11 + [True] * 3


def _setup(algo, env_id, conf, tmp_path):
    """The zoo's ExperimentManager for ``<conf>.yml``'s entry of ``env_id`` (2 envs, seed 0) and the model it builds."""
    from rl_zoo3.exp_manager import ExperimentManager

    manager = ExperimentManager(
        argparse.Namespace(), algo, env_id, str(tmp_path), eval_freq=-1, hyperparams={"n_envs": 2},
        config=str(HYPERPARAMS / f"{conf}.yml"), verbose=0, seed=0,
    )
    with contextlib.redirect_stdout(io.StringIO()):
        model, _ = manager.setup_experiment()
    return manager, model


@pytest.mark.parametrize("conf", ["ppo_gocu", "ppo", "ppo_dropin"])
def test_every_entry_builds_its_model(conf, tmp_path):
    """The zoo's ExperimentManager builds each entry's env and model (n_envs overridden to 2)."""
    from stable_baselines3 import PPO

    from sb3_gocu import ExplorationCallback, GoCuCallback, PaperCNN, PPO_GoCu, RoomInfoWrapper
    from sb3_gocu.wrappers import find_gocu_module

    register_zoo()
    algo = "ppo" if conf == "ppo_dropin" else conf
    for env_id in ENV_IDS:
        manager, model = _setup(algo, env_id, conf, tmp_path)
        try:
            assert type(model) is (PPO_GoCu if conf == "ppo_gocu" else PPO)
            atari = env_id.startswith("ALE/")
            assert model.observation_space.shape == ((4, 84, 84) if atari else (3, 32, 32))
            assert isinstance(model.policy.features_extractor, PaperCNN) != atari
            if atari:  # the exploration measures: every Atari entry logs them; Montezuma's env reports its room
                assert any(isinstance(cb, ExplorationCallback) for cb in manager.callbacks)
                assert model.env.env_is_wrapped(RoomInfoWrapper) == [("Montezuma" in env_id)] * 2
            found = find_gocu_module(model.env)
            if conf == "ppo":
                assert found is None
                continue
            module, mode = found
            assert mode == ("separate" if conf == "ppo_gocu" else "sum")
            if conf == "ppo_gocu":
                assert module is model.curiosity and model.intrinsic_coef == 0.25
                assert model.intrinsic_episodic == atari  # the stream stops at each lost life on Atari only
                # the module embeds the newest frame of the stack on Atari, averaged down to 42x42; the RGB view elsewhere
                assert module.adapter.input_shape == ((1, 42, 42) if atari else (3, 32, 32))
            else:
                assert any(isinstance(cb, GoCuCallback) for cb in manager.callbacks)
                assert module.adapter.input_shape == ((1, 42, 42) if atari else (3, 32, 32))
            assert module.n_goals == (25 if "Visual" in env_id else 50)
        finally:
            model.env.close()


@pytest.mark.parametrize("algo", ["a2c", "dqn"])
def test_other_learners_files_build_plain_and_dropin(algo, tmp_path):
    """a2c.yml / dqn.yml (the paper's Fig. 6) build SB3's A2C / DQN on the paper's CNN; their _dropin files hold the
    same settings plus the sum-mode wrapper and the GoCu callback."""
    from stable_baselines3 import A2C, DQN

    from sb3_gocu import GoCuCallback, PaperCNN
    from sb3_gocu.wrappers import find_gocu_module

    plain = yaml.safe_load((HYPERPARAMS / f"{algo}.yml").read_text())
    dropin = yaml.safe_load((HYPERPARAMS / f"{algo}_dropin.yml").read_text())
    assert set(plain) == set(dropin) == {f"GoCu/DoorKey-{n}-v0" for n in ("5x5", "8x8", "11x11", "16x16")}
    for env_id, entry in dropin.items():
        (wrapper,) = entry.pop("vec_env_wrapper")
        assert wrapper == {"sb3_gocu.GoCuVecEnvWrapper": {"mode": "sum", "centred": True, "intrinsic_coef": 0.25}}
        assert entry.pop("callback") == "sb3_gocu.GoCuCallback" and entry == plain[env_id]
    assert plain["GoCu/DoorKey-8x8-v0"]["n_timesteps"] == 1e6  # the budget of the paper's Fig. 6 runs here
    for conf in (algo, f"{algo}_dropin"):
        manager, model = _setup(algo, DOORKEY, conf, tmp_path)
        try:
            assert type(model) is {"a2c": A2C, "dqn": DQN}[algo]
            extractor = model.q_net.features_extractor if algo == "dqn" else model.policy.features_extractor
            assert isinstance(extractor, PaperCNN)
            found = find_gocu_module(model.env)
            if conf == algo:
                assert found is None
            else:
                assert found[1] == "sum" and any(isinstance(cb, GoCuCallback) for cb in manager.callbacks)
        finally:
            model.env.close()


class _FakeManagerCall:
    """Calls a sampler the way ExperimentManager.objective does: with an ExperimentManager as ``self``."""

    def __init__(self, hyperparams):
        from rl_zoo3.exp_manager import ExperimentManager

        self.manager = ExperimentManager(argparse.Namespace(), "ppo_gocu", DOORKEY, "unused")
        self.manager._hyperparams = hyperparams

    def __call__(self, sampler, trial):
        return _objective_like(self.manager, sampler, trial)


def _objective_like(self, sampler, trial):  # noqa: ANN001  (``self`` as in ExperimentManager.objective)
    return sampler(trial, 0, 2, {})


def test_sampler_merges_into_the_configured_settings():
    from rl_zoo3.hyperparams_opt import HYPERPARAMS_SAMPLER

    from sb3_gocu import PaperCNN

    register_zoo()
    configured = {
        "curiosity_kwargs": {"image_channels": 1, "pretrain_steps": 64, "goal_buffer_size": 20, "distance_weight": 2.0},
        "policy_kwargs": {"features_extractor_class": PaperCNN},
    }
    call = _FakeManagerCall(configured)
    study = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=0))
    for _ in range(5):
        trial = study.ask()
        params = call(HYPERPARAMS_SAMPLER["ppo_gocu"], trial)
        curiosity = params["curiosity_kwargs"]
        # configured keys survive, sampled keys are added
        assert curiosity["image_channels"] == 1 and curiosity["pretrain_steps"] == 64
        for key in GOCU_TRIAL_PARAMS:
            if key != "intrinsic_coef":
                assert key in curiosity, key
        assert curiosity["n_goals"] <= 20, "K is capped at the configured goal buffer"
        assert 0.01 <= params["intrinsic_coef"] <= 1.0
        assert params["policy_kwargs"]["features_extractor_class"] is PaperCNN and "net_arch" in params["policy_kwargs"]
        assert {"learning_rate", "n_steps", "batch_size", "gamma"} <= params.keys()
        study.tell(trial, 0.0)
        # the converter (``--trial-id``) turns the stored raw parameters into the same arguments
        stored = study.trials[-1].params
        assert call(lambda *_: convert_ppo_gocu_params(stored), trial) == params

    # the zoo's ppo sampler keeps the configured features extractor (NatureCNN cannot take 32x32)
    ppo_params = call(HYPERPARAMS_SAMPLER["ppo"], study.ask())
    assert ppo_params["policy_kwargs"]["features_extractor_class"] is PaperCNN
    # without a manager on the stack there is nothing to merge
    assert sample_ppo_gocu_params(study.ask(), 0, 2, {})["curiosity_kwargs"].keys() >= {"n_goals"}


@pytest.mark.parametrize("policy, images", [("CnnPolicy", True), ("MlpPolicy", False), (None, False)])
def test_sampler_draws_the_pixel_weighting_only_for_images(policy, images):
    """``vae_pixel_weighting`` is sampled (over [0, 1]) when the configured policy takes images, and neither
    sampled nor set otherwise (the module refuses a value above 0 with vector observations)."""
    from rl_zoo3.hyperparams_opt import HYPERPARAMS_SAMPLER

    register_zoo()
    configured = {"curiosity_kwargs": {"pretrain_steps": 64}} | ({"policy": policy} if policy else {})
    call = _FakeManagerCall(configured)
    study = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=1))
    drawn = []
    for _ in range(8):
        trial = study.ask()
        params = call(HYPERPARAMS_SAMPLER["ppo_gocu"], trial)
        assert ("vae_pixel_weighting" in trial.params) is images
        assert ("vae_pixel_weighting" in params["curiosity_kwargs"]) is images
        if images:
            value = params["curiosity_kwargs"]["vae_pixel_weighting"]
            assert 0.0 <= value <= 1.0 and value == trial.params["vae_pixel_weighting"]
            drawn.append(value)
        study.tell(trial, 0.0)
        # the converter puts it back into curiosity_kwargs, not among the PPO arguments
        converted = call(lambda *_: convert_ppo_gocu_params(study.trials[-1].params), trial)
        assert converted == params and not set(GOCU_IMAGE_TRIAL_PARAMS) & converted.keys()
    if images:
        assert len(set(drawn)) == len(drawn), "a float drawn afresh for each trial"


# ------------------------------------------------------------------------------------------ launchers
def test_train_then_enjoy_ppo_gocu(gocu_run):
    from sb3_gocu import PPO_GoCu

    work, logs, model_path, out = gocu_run
    assert f"Loading hyperparameters from: {HYPERPARAMS / 'ppo_gocu.yml'}" in out
    assert "GoCu: pretrained the VAE" in out
    assert model_path.is_file()
    model = PPO_GoCu.load(model_path)
    module = model.curiosity
    assert module.pretrained and module.goal_buffer.size > 0 and module.memory.size > 0
    assert module.n_recorded_steps == 2048 + 128, "2048 training steps and 128 pretraining steps recorded"
    assert module.last_predictor_update > 0
    assert model.curiosity_kwargs["pretrain_steps"] == 128
    out = run("sb3_gocu.enjoy", "--algo", "ppo_gocu", "--env", DOORKEY, "-f", "logs", "-n", "300", "--no-render", "--num-threads", "1", cwd=work)
    assert f"Loading logs/ppo_gocu/{DOORKEY_DIR}_1/{DOORKEY_DIR}.zip" in out
    assert "Episode Length" in out, "at least one episode finished within 300 steps (DoorKey-5x5 stops at 250)"


def test_continue_training_keeps_the_curiosity_state(gocu_run):
    from sb3_gocu import PPO_GoCu

    work, logs, model_path, _ = gocu_run
    before = PPO_GoCu.load(model_path).curiosity
    out = run("sb3_gocu.train", "--algo", "ppo_gocu", "--env", DOORKEY, "-n", "1024", "-f", "logs", "-i", str(model_path), *TINY_GOCU, cwd=work)
    assert "Loading pretrained agent" in out
    assert "GoCu: pretrained the VAE" not in out, "the loaded module is not pretrained again"
    after = PPO_GoCu.load(logs / "ppo_gocu" / f"{DOORKEY_DIR}_2" / f"{DOORKEY_DIR}.zip").curiosity
    assert after.pretrained
    assert after.n_recorded_steps == before.n_recorded_steps + 1024
    assert after.last_predictor_update > before.last_predictor_update


def test_record_video(gocu_run):
    work, *_ = gocu_run
    videos = work / "videos"
    run("sb3_gocu.record_video", "--algo", "ppo_gocu", "--env", DOORKEY, "-f", "logs", "--exp-id", "1", "-n", "20", "-o", str(videos), cwd=work)
    (video,) = videos.glob("*.mp4")
    assert video.stat().st_size > 1000


def test_plain_ppo_with_its_config(tmp_path):
    from stable_baselines3 import PPO

    from sb3_gocu import PaperCNN

    out = run("sb3_gocu.train", "--algo", "ppo", "--env", DOORKEY, "-n", "1024", "-f", "logs", *TINY, cwd=tmp_path)
    assert f"Loading hyperparameters from: {HYPERPARAMS / 'ppo.yml'}" in out
    model = PPO.load(tmp_path / "logs" / "ppo" / f"{DOORKEY_DIR}_1" / f"{DOORKEY_DIR}.zip")
    assert isinstance(model.policy.features_extractor, PaperCNN)
    assert model.num_timesteps == 1024
    out = run("sb3_gocu.enjoy", "--algo", "ppo", "--env", DOORKEY, "-f", "logs", "-n", "260", "--no-render", cwd=tmp_path)
    assert "Episode Length" in out


def test_dropin_config(tmp_path):
    from stable_baselines3 import PPO

    wrapper = f"vec_env_wrapper:[{{'sb3_gocu.GoCuVecEnvWrapper': dict(mode='sum', intrinsic_coef=0.25, curiosity_kwargs={TINY_CURIOSITY})}}]"
    callback = "callback:[{'sb3_gocu.GoCuCallback': dict(verbose=1)}]"
    out = run(
        "sb3_gocu.train", "--algo", "ppo", "--env", DOORKEY, "-n", "1024", "-f", "logs",
        "--conf-file", str(HYPERPARAMS / "ppo_dropin.yml"), *TINY, wrapper, callback, cwd=tmp_path,
    )
    assert f"Loading hyperparameters from: {HYPERPARAMS / 'ppo_dropin.yml'}" in out
    assert "GoCu: pretrained the VAE on 128 random-policy observations" in out
    assert "intrinsic_reward_mean" in out, "the GoCu callback logged the curiosity statistics"
    run_dir = tmp_path / "logs" / "ppo" / f"{DOORKEY_DIR}_1"
    config = yaml.load((run_dir / DOORKEY_DIR / "config.yml").read_text(), Loader=yaml.UnsafeLoader)
    assert "sb3_gocu.GoCuVecEnvWrapper" in config["vec_env_wrapper"][0]
    assert PPO.load(run_dir / f"{DOORKEY_DIR}.zip").num_timesteps == 1024
    out = run("sb3_gocu.enjoy", "--algo", "ppo", "--env", DOORKEY, "-f", "logs", "-n", "260", "--no-render", cwd=tmp_path)
    assert "Episode Length" in out


def test_optimize_two_workers_share_one_journal_study(tmp_path):
    """Two ``-optimize`` processes started at once on one journal file fill one study."""
    common = [
        "-m", "sb3_gocu.train", "--algo", "ppo_gocu", "--env", DOORKEY, "-n", "512", "-f", "logs", "--num-threads", "1",
        "-optimize", "--storage", "logs/study.log", "--study-name", "gocu-test", "--n-trials", "2",
        "--n-startup-trials", "1", "--n-evaluations", "1", "--eval-episodes", "1", "--no-optim-plots",
        # seeded random sampling: cheap PPO draws (n_steps <= 128) for these two seeds
        "--sampler", "random", "--hyperparams", "n_envs:2", f"curiosity_kwargs:{TINY_CURIOSITY}",
    ]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    procs = [
        subprocess.Popen([sys.executable, *common, "--seed", seed], cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        for seed in ("11", "6")
    ]
    outputs = [p.communicate(timeout=240)[0] for p in procs]
    for p, out in zip(procs, outputs):
        assert p.returncode == 0, out[-4000:]
        assert "Number of finished trials" in out
    storage = optuna.storages.JournalStorage(optuna.storages.journal.JournalFileBackend(str(tmp_path / "logs" / "study.log")))
    study = optuna.load_study(study_name="gocu-test", storage=storage)
    done = [t for t in study.trials if t.state in (optuna.trial.TrialState.COMPLETE, optuna.trial.TrialState.PRUNED)]
    # one study, no trial lost or counted twice: trial numbers 0-3, each worker ("host:pid") ran its --n-trials 2
    assert len(done) == len(study.trials) and sorted(t.number for t in study.trials) == [0, 1, 2, 3]
    per_worker = collections.Counter(int(t.user_attrs["worker"].rsplit(":", 1)[1]) for t in done)
    assert per_worker == {p.pid: 2 for p in procs}, f"trials per worker pid: {dict(per_worker)}"
    for t in done:
        assert set(GOCU_TRIAL_PARAMS) <= t.params.keys(), "the ppo_gocu sampler drew the GoCu parameters"
        # the zoo's manager hands the sampler the configured CnnPolicy: the image-only parameter is drawn too
        assert set(GOCU_IMAGE_TRIAL_PARAMS) <= t.params.keys()


PLOT_TRAIN = textwrap.dedent(
    """
    import json, sys
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    out = sys.argv.pop(1)

    def show(*args, **kwargs):  # plot_train ends with plt.show(): save the figure and its lines instead
        fig = plt.gcf()
        fig.savefig(out + ".png")
        lines = [dict(label=l.get_label(), x=[float(v) for v in l.get_xdata()], y=[float(v) for v in l.get_ydata()]) for l in fig.axes[0].lines]
        with open(out + ".json", "w") as f:
            json.dump(lines, f)

    plt.show = show
    from rl_zoo3.plots.plot_train import plot_train
    plot_train()
    """
)


def test_plot_train_draws_the_training_curve(gocu_run):
    pytest.importorskip("seaborn", reason="rl_zoo3.plots needs seaborn (the rl_zoo3[plots] extra)")
    from stable_baselines3.common.monitor import load_results

    work, logs, model_path, _ = gocu_run
    script = work / "plot_train.py"
    script.write_text(PLOT_TRAIN)
    env = {**os.environ, "MPLBACKEND": "Agg"}
    proc = subprocess.run(
        [sys.executable, str(script), str(work / "curve"), "-a", "ppo_gocu", "-e", DOORKEY_DIR, "-f", str(logs), "-w", "1"],
        cwd=work, env=env, capture_output=True, text=True, timeout=120,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert (work / "curve.png").stat().st_size > 1000
    lines = {line["label"]: line for line in json.loads((work / "curve.json").read_text())}
    run_dir = model_path.parent
    assert run_dir.name in lines
    # the curve is the monitor files' episodes: x = cumulated episode lengths, y = extrinsic returns
    monitor = load_results(str(run_dir))
    assert len(monitor) >= 8, "DoorKey-5x5 episodes end within 250 steps: 2048 steps give at least 8"
    np.testing.assert_allclose(lines[run_dir.name]["x"], np.cumsum(monitor.l.values))
    np.testing.assert_allclose(lines[run_dir.name]["y"], monitor.r.values)


#: two values of each GoCu setting the ppo_gocu sampler draws for the curiosity module, from its ranges
SAMPLED_PAIRS = {
    "n_goals": (4, 10),
    "new_goals_per_episode": (1, 15),
    "goal_strategy": ("random", "late"),
    "revisit_decay": ("none", "first_visit"),
    "max_distance": (10, 30),
    "vae_pixel_weighting": (0.0, 1.0),
}


def normalised_rewards(**settings) -> np.ndarray:
    """The normalised r_gc (what the learner is paid) of a fixed batch of observations, after a fixed history of
    recorded episodes (two envs, each a random walk of 100 steps among 64 places), the pretraining
    after 200 steps and an update round after 400 more (goals from the finished episodes, a predictor update)."""
    from gymnasium import spaces

    from sb3_gocu.curiosity import GoalCuriosityModule

    from conftest import SMALL_CURIOSITY

    base = {**SMALL_CURIOSITY, "goal_buffer_size": 64, "n_goals": 4, "predictor_train_freq": 400, "max_distance": 20}
    module = GoalCuriosityModule(spaces.Box(0, 255, (16, 16, 3), np.uint8), seed=0, **{**base, **settings})
    frames = np.zeros((64, 16, 16, 3), dtype=np.uint8)  # a bright 2x2 square at each of 8x8 places
    for place in range(64):
        y, x = divmod(place, 8)
        frames[place, 2 * y : 2 * y + 2, 2 * x : 2 * x + 2] = 255
    rng = np.random.default_rng(0)
    places = np.zeros(2, dtype=np.int64)
    module.recording = True
    for t in range(600):  # each env walks among the places, back to the corner at each new episode
        y, x = np.divmod(places, 8)
        step = rng.integers(4, size=2)
        places = np.clip(y + (step == 0) - (step == 1), 0, 7) * 8 + np.clip(x + (step == 2) - (step == 3), 0, 7)
        done = t % 100 == 99
        module.step(frames[places], np.full(2, done))
        places = places * (not done)
        if t == 199:
            module.pretrain()
    module.maybe_train()
    module.begin_episodes(np.arange(2))
    return np.concatenate([module.step(frames[[t, 63 - t]], np.zeros(2, bool))[1] for t in range(40)])


def test_every_sampled_curiosity_setting_acts_on_the_rewards():
    """A setting the search draws must change what the learner is paid; delta (reward_scale), which eq 14's
    normalisation cancels, is the check's teeth: it changes the config and not the normalised rewards."""
    assert set(SAMPLED_PAIRS) == (set(GOCU_TRIAL_PARAMS) - {"intrinsic_coef"}) | set(GOCU_IMAGE_TRIAL_PARAMS)
    for name, (a, b) in SAMPLED_PAIRS.items():
        assert not np.allclose(normalised_rewards(**{name: a}), normalised_rewards(**{name: b}), rtol=1e-5, atol=0), name
    assert np.allclose(normalised_rewards(reward_scale=1.0), normalised_rewards(reward_scale=20.0), rtol=1e-5, atol=0)
