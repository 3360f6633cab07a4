"""PPO_GoCu save/load round trips, and the drop-in path with plain SB3 algorithms."""

import threading

import numpy as np
import pytest
import torch as th
from stable_baselines3 import A2C, PPO
from stable_baselines3.common.atari_wrappers import EpisodicLifeEnv, FireResetEnv
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import DummyVecEnv, VecMonitor

from sb3_gocu import PAPER_PPO_KWARGS, GoalCuriosityModule, GoCuCallback, GoCuVecEnvWrapper, GoCuWrapper, PPO_GoCu

from conftest import SMALL_CURIOSITY, ChainEnv, LivesEnv, record_steps


def chain_venv(n_envs=2, seed=0):
    return make_vec_env(lambda: ChainEnv(), n_envs=n_envs, seed=seed)


def flat_tensors(obj, prefix=""):
    """Every tensor of a nested state_dict, by path."""
    out = {}
    if isinstance(obj, th.Tensor):
        out[prefix] = obj
    elif isinstance(obj, dict):
        for k, v in obj.items():
            out.update(flat_tensors(v, f"{prefix}/{k}"))
    elif isinstance(obj, (list, tuple)):
        for i, v in enumerate(obj):
            out.update(flat_tensors(v, f"{prefix}/{i}"))
    return out


def test_save_load_round_trip_and_continue(tmp_path):
    model = PPO_GoCu("MlpPolicy", chain_venv(), n_steps=64, batch_size=64, n_epochs=2, seed=0, curiosity_kwargs=SMALL_CURIOSITY)
    model.learn(512)
    module = model.curiosity
    assert module.pretrained and module.goal_buffer.size > 0 and module.memory.size > 0
    assert module.last_predictor_update > 0, "the predictor was trained at least once"
    path = tmp_path / "gocu.zip"
    model.save(path)

    loaded = PPO_GoCu.load(path, env=chain_venv(seed=1))
    before, after = flat_tensors(module.state_dict()), flat_tensors(loaded.curiosity.state_dict())
    assert before.keys() == after.keys()
    assert len(before) > 20
    for key in before:
        assert th.equal(before[key], after[key]), key
    assert loaded.curiosity.goal_buffer.size == module.goal_buffer.size
    assert loaded.curiosity.n_recorded_steps == module.n_recorded_steps
    assert loaded.curiosity_kwargs == {**SMALL_CURIOSITY, "predictor_hidden": [32, 32]} and loaded.intrinsic_coef == model.intrinsic_coef
    # the loaded env's wrapper uses the loaded module
    assert loaded.env.module is loaded.curiosity or loaded.env.venv.module is loaded.curiosity

    steps_before = loaded.curiosity.n_recorded_steps
    vae_before = {k: v.clone() for k, v in loaded.curiosity.vae.state_dict().items()}
    loaded.learn(512, reset_num_timesteps=False)
    assert loaded.num_timesteps == 1024
    assert loaded.curiosity.n_recorded_steps == steps_before + 512, "no second pretraining after load"
    vae_after = loaded.curiosity.vae.state_dict()
    assert any(not th.equal(vae_before[k], vae_after[k]) for k in vae_before), "the VAE kept training"


def test_module_state_loads_with_weights_only(tmp_path):
    module = GoalCuriosityModule(ChainEnv().observation_space, **SMALL_CURIOSITY, seed=3)
    module.recording = True
    rng = np.random.default_rng(0)
    for _ in range(40):
        module.step(rng.random((2, 2)).astype(np.float32), rng.random(2) < 0.2)
    module.add_finished_episode_goals()
    th.save(module.state_dict(), tmp_path / "m.pt")
    state = th.load(tmp_path / "m.pt", weights_only=True)
    other = GoalCuriosityModule(ChainEnv().observation_space, **SMALL_CURIOSITY, seed=4)
    other.load_state_dict(state)
    for key, value in flat_tensors(module.state_dict()).items():
        assert th.equal(value, flat_tensors(other.state_dict())[key]), key
    # same generator state: the next goal draws agree
    assert module.rng.random() == other.rng.random()


@pytest.mark.parametrize("algo", [PPO, A2C])
def test_plain_sb3_algorithms_train_with_sum_mode(algo):
    venv = GoCuVecEnvWrapper(chain_venv(), mode="sum", curiosity_kwargs=SMALL_CURIOSITY)
    seen = []

    class Spy(GoCuCallback):
        def _on_step(self):
            infos, rewards = self.locals["infos"], self.locals["rewards"]
            seen.append((np.array(rewards, dtype=np.float64), np.array([i["extrinsic_reward"] for i in infos]), np.array([i["gocu_reward"] for i in infos])))
            return True

    kwargs = dict(n_steps=32) if algo is PPO else dict(n_steps=8)
    model = algo("MlpPolicy", venv, seed=0, **kwargs)
    model.learn(640, callback=Spy())
    assert venv.module.pretrained and venv.module.last_predictor_update > 0
    rewards, extrinsic, intrinsic = map(np.stack, zip(*seen))
    # what the algorithm sees differs from the extrinsic reward by sigma x the reported r_gc less its running mean, one
    # mean for all envs of a step (sigma 0.25 by default)
    assert venv.intrinsic_coef == PPO_GoCu("MlpPolicy", chain_venv()).intrinsic_coef == 0.25
    shift = rewards - extrinsic - 0.25 * intrinsic
    assert np.allclose(shift, shift[:, :1], atol=1e-6) and (shift < -1e-4).all()
    assert np.abs(intrinsic).max() > 0


def test_ppo_settings_default_to_the_papers_and_given_ones_win():
    def settings(model):
        return dict(n_steps=model.n_steps, batch_size=model.batch_size, n_epochs=model.n_epochs, learning_rate=model.learning_rate,
                    ent_coef=model.ent_coef, gamma=model.gamma, vf_coef=model.vf_coef, clip_range=model.clip_range(1.0))

    assert PAPER_PPO_KWARGS == dict(n_steps=128, batch_size=256, n_epochs=4, learning_rate=1e-4, ent_coef=0.01, gamma=0.99, vf_coef=0.5, clip_range=0.2)
    sb3 = PPO("MlpPolicy", chain_venv())
    assert settings(sb3)["n_steps"] == 2048 and settings(sb3)["ent_coef"] == 0.0  # SB3's, not the paper's
    assert settings(PPO_GoCu("MlpPolicy", chain_venv(), curiosity_kwargs=SMALL_CURIOSITY)) == PAPER_PPO_KWARGS
    # given ones win, by keyword or by position (learning_rate, n_steps are PPO's first two after env)
    model = PPO_GoCu("MlpPolicy", chain_venv(), 3e-4, 64, batch_size=32, ent_coef=0.0, curiosity_kwargs=SMALL_CURIOSITY)
    assert settings(model) == {**PAPER_PPO_KWARGS, "learning_rate": 3e-4, "n_steps": 64, "batch_size": 32, "ent_coef": 0.0}


@pytest.mark.parametrize("fire", [False, True])
@pytest.mark.parametrize("vectorised", [True, False])
def test_a_lost_life_ends_the_learners_episode_not_the_curiositys(vectorised, fire):
    """Under SB3's EpisodicLifeEnv a lost life is a done for the learner; the curiosity's episode (its id, goals and
    first-visit memory) goes on to the end of the game, for both wrappers; also under FireResetEnv, whose steps in the
    reset overwrite EpisodicLifeEnv's ``was_real_done`` (AtariWrapper's order: Monitor below, FireResetEnv above)."""
    make = lambda: (FireResetEnv if fire else lambda e: e)(EpisodicLifeEnv(Monitor(LivesEnv())))
    if vectorised:
        venv = GoCuVecEnvWrapper(DummyVecEnv([make]), curiosity_kwargs=SMALL_CURIOSITY)
        module = venv.module
    else:
        module = GoalCuriosityModule(LivesEnv().observation_space, **SMALL_CURIOSITY, seed=0)
        venv = DummyVecEnv([lambda: GoCuWrapper(make(), module=module)])
    venv.reset()
    episode, dones, games = int(module.episodes.ids[0]), 0, 0
    for _ in range(30):
        _, _, done, infos = venv.step(np.ones(1, dtype=np.int64))
        game_over = "episode" in infos[0]  # Monitor, below EpisodicLifeEnv: the game's end
        assert (int(module.episodes.ids[0]) != episode) == game_over
        episode, dones, games = int(module.episodes.ids[0]), dones + done[0], games + game_over
    # both kinds of done happened: three lives a game (FireResetEnv's reset steps spend some of them)
    assert games >= 3 and dones >= 2 * games


@pytest.mark.filterwarnings("ignore:The environment is already wrapped with a `Monitor`")
def test_lives_without_a_monitor_beneath_are_refused():
    """GoCuVecEnvWrapper tells a game's end by the Monitor beneath EpisodicLifeEnv: without one (or with one above, or a
    VecMonitor, which end an episode at every lost life) it says so at construction, naming the fix."""
    with pytest.raises(ValueError, match="Monitor before AtariWrapper"):
        GoCuVecEnvWrapper(DummyVecEnv([lambda: EpisodicLifeEnv(LivesEnv())]), curiosity_kwargs=SMALL_CURIOSITY)
    with pytest.raises(ValueError, match="not after it"):  # as SB3 wraps a gym env given to PPO: Monitor on top
        GoCuVecEnvWrapper(DummyVecEnv([lambda: Monitor(EpisodicLifeEnv(LivesEnv()))]), curiosity_kwargs=SMALL_CURIOSITY)
    with pytest.raises(ValueError, match="nor in a VecMonitor"):
        GoCuVecEnvWrapper(VecMonitor(DummyVecEnv([lambda: EpisodicLifeEnv(Monitor(LivesEnv()))])), curiosity_kwargs=SMALL_CURIOSITY)
    GoCuVecEnvWrapper(DummyVecEnv([lambda: EpisodicLifeEnv(Monitor(LivesEnv()))]), curiosity_kwargs=SMALL_CURIOSITY)


def test_monitor_return_stays_extrinsic_and_gym_wrapper_matches():
    module = GoalCuriosityModule(ChainEnv().observation_space, **SMALL_CURIOSITY, seed=0)
    venv = DummyVecEnv([lambda: GoCuWrapper(Monitor(ChainEnv()), module=module, mode="sum") for _ in range(2)])
    assert module.n_envs == 2
    # the envs registered one at a time share the store's P_m states, as one VecEnv wrapper's would
    vec_module = GoCuVecEnvWrapper(chain_venv(), curiosity_kwargs=SMALL_CURIOSITY).module
    assert vec_module.n_envs == 2 and module.trajectories.capacity == vec_module.trajectories.capacity
    assert module.trajectories.capacity == max(-(-module.predictor_train_freq // 2), 2 * module.max_distance)
    venv.seed(0)
    venv.reset()
    total, extrinsic, episodes = 0.0, 0.0, 0
    episode_sums = np.zeros((2, 2))  # env -> (extrinsic, normalised r_gc) summed over its current episode
    for _ in range(30):
        _, r, _, infos = venv.step(np.ones(2, dtype=np.int64))
        total += r.sum()
        extrinsic += sum(i["extrinsic_reward"] for i in infos)
        assert np.allclose(r, [i["extrinsic_reward"] + 0.25 * i["gocu_reward"] for i in infos], atol=1e-6)
        for env, info in enumerate(infos):
            episode_sums[env] += (info["extrinsic_reward"], info["gocu_reward"])
            if "episode" in info:  # Monitor's return is the extrinsic one; the wrapper adds the episode's r_gc
                assert info["episode"]["r"] == pytest.approx(episode_sums[env, 0]) == 1.0
                assert info["episode"]["gocu_r"] == pytest.approx(episode_sums[env, 1]) and episode_sums[env, 1] != 0
                episode_sums[env], episodes = 0.0, episodes + 1
    assert total > extrinsic and episodes == 2 * 5  # ChainEnv ends every 6 steps going right
    # PPO_GoCu with a sum-mode wrapper would count curiosity twice: refused
    with pytest.raises(ValueError, match="separate"):
        PPO_GoCu("MlpPolicy", GoCuVecEnvWrapper(chain_venv(), mode="sum", curiosity_kwargs=SMALL_CURIOSITY))


def two_modules_after_steps() -> tuple[GoalCuriosityModule, GoalCuriosityModule]:
    """Two modules with one seed after the same 160 recorded steps of 2 envs (a predictor and a VAE update due)."""
    space = ChainEnv().observation_space
    settings = {**SMALL_CURIOSITY, "vae_train_freq": 256}
    modules = GoalCuriosityModule(space, **settings, seed=5), GoalCuriosityModule(space, **settings, seed=5)
    rng = np.random.default_rng(0)
    batches = [(rng.random((2, 2)).astype(np.float32), rng.random(2) < 0.1) for _ in range(160)]
    for module in modules:
        record_steps(module, batches)
    return modules


def test_maybe_train_runs_the_updates_due_predictor_first():
    """maybe_train adds the finished episodes' goals and runs the updates due, the predictor before the VAE: the same
    networks, rewards and statistics as train_predictor then train_vae."""
    by_hand, scheduled = two_modules_after_steps()
    by_hand.add_finished_episode_goals()
    expected = {**by_hand.train_predictor(), **by_hand.train_vae()}
    out = scheduled.maybe_train()
    assert out["goals_added"] > 0 and out["predictor_loss"] == expected["predictor_loss"] and out["vae_loss"] == expected["vae_loss"]
    obs = np.array([[0.3, 0.09], [0.6, 0.36]], dtype=np.float32)
    assert np.array_equal(by_hand.step(obs, np.zeros(2, bool))[0], scheduled.step(obs, np.zeros(2, bool))[0])
    for name in ("vae", "predictor"):
        a, b = getattr(by_hand, name).state_dict(), getattr(scheduled, name).state_dict()
        assert all(th.equal(a[k], b[k]) for k in a), name
    assert "predictor_loss" not in scheduled.maybe_train(), "nothing due right after"


@pytest.mark.parametrize("caller", [1, 2])
def test_updates_run_in_the_caller_with_its_thread_count(caller, monkeypatch):
    """Every epoch of both fits runs in the calling thread with its thread count, which is the same afterwards."""
    th.set_num_threads(caller)
    _, module = two_modules_after_steps()
    seen: list[tuple[str, int, int]] = []
    trainer = module.trainer
    for name, fit in (("vae", trainer.fit_vae), ("predictor", trainer.fit_predictor)):
        def spy(job, on_epoch=None, fit=fit, name=name):
            return fit(job, on_epoch=lambda epoch: seen.append((name, th.get_num_threads(), threading.get_ident())))
        monkeypatch.setattr(trainer, f"fit_{name}", spy)
    module.maybe_train()
    assert th.get_num_threads() == caller
    assert {name for name, _, _ in seen} == {"vae", "predictor"}
    assert {(n, ident) for _, n, ident in seen} == {(caller, threading.get_ident())}


def test_a_separate_mode_wrapper_pays_extrinsic_rewards_even_holding_a_coefficient():
    """An env stack pickled by an older version holds intrinsic_coef 0.25 in mode="separate" too: the reward the
    algorithm sees stays extrinsic (PPO_GoCu adds the curiosity itself), whatever the coefficient."""
    venv = GoCuVecEnvWrapper(chain_venv(), mode="separate", curiosity_kwargs=SMALL_CURIOSITY)
    assert venv.intrinsic_coef is None
    venv.intrinsic_coef = 0.25  # as unpickled from an older checkpoint
    venv.module.pretrain()
    venv.reset()
    for _ in range(10):
        _, rewards, _, infos = venv.step(np.ones(2, dtype=np.int64))
        assert np.array_equal(rewards, [i["extrinsic_reward"] for i in infos])
    assert any(i["gocu_reward"] != 0 for i in infos)


@pytest.mark.parametrize("centred", [True, False])
def test_sum_mode_pays_r_gc_less_its_running_mean_of_the_steps_before(centred):
    """mode="sum" pays r_e + sigma (r_gc - the mean of the normalised r_gc recorded before this step), by hand; centred=False
    the paper's r_e + sigma r_gc. The mean is the module's (saved with it), updated only while recording."""
    venv = GoCuVecEnvWrapper(chain_venv(), mode="sum", curiosity_kwargs=SMALL_CURIOSITY, centred=centred)
    venv.module.pretrain()
    venv.module.recording = True
    venv.reset()
    paid: list[float] = []
    rng = np.random.default_rng(0)
    for _ in range(40):
        _, rewards, _, infos = venv.step(rng.integers(2, size=2))
        centre = float(np.mean(paid)) if paid and centred else 0.0
        expected = [i["extrinsic_reward"] + 0.25 * (i["gocu_reward"] - centre) for i in infos]
        assert np.allclose(rewards, expected, atol=1e-6)
        paid += [i["gocu_reward"] for i in infos]
    assert venv.module.reward_centre.mean == pytest.approx(np.mean(paid)) and np.mean(paid) > 0
    other = GoalCuriosityModule(ChainEnv().observation_space, **SMALL_CURIOSITY)
    other.load_state_dict(venv.module.state_dict())
    assert other.reward_centre.mean == venv.module.reward_centre.mean and other.reward_centre.count == 80
    venv.module.recording = False
    venv.step(np.ones(2, dtype=np.int64))
    assert venv.module.reward_centre.count == 80


def test_centred_is_checked():
    with pytest.raises(ValueError, match="centred must be True or False"):
        GoCuVecEnvWrapper(chain_venv(), curiosity_kwargs=SMALL_CURIOSITY, centred=1)
    with pytest.raises(ValueError, match="centred applies to mode='sum'"):
        GoCuVecEnvWrapper(chain_venv(), mode="separate", curiosity_kwargs=SMALL_CURIOSITY, centred=True)
    assert GoCuVecEnvWrapper(chain_venv(), curiosity_kwargs=SMALL_CURIOSITY).centred
    assert not GoCuVecEnvWrapper(chain_venv(), mode="separate", curiosity_kwargs=SMALL_CURIOSITY).centred
