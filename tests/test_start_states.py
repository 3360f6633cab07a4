"""record_start_states: the first observation of each episode (s_0) is recorded like the states reached by a step
(memory bank, goal candidates, trajectory store, visit counts) but pays no reward and counts as no env step."""

import numpy as np
import pytest
from stable_baselines3.common.env_util import make_vec_env

from sb3_gocu import GoalCuriosityModule, GoCuVecEnvWrapper

from conftest import SMALL_CURIOSITY, ChainEnv

SPACE = ChainEnv().observation_space


def rows(*values):
    return np.array([[v, v * v] for v in values], dtype=np.float32)


def stepped_module(record: bool) -> tuple[GoalCuriosityModule, list[np.ndarray]]:
    """Two envs: both start at 0.0; env 0 goes 0.1, 0.2 (episode ends; the next starts at 0.0 again), env 1 goes
    0.1 and back to its start 0.0. Returns the module and each step's raw r_gc."""
    module = GoalCuriosityModule(SPACE, **{**SMALL_CURIOSITY, "record_start_states": record}, seed=0)
    module.recording = True
    module.begin_episodes(np.arange(2), rows(0.0, 0.0))
    raws = [module.step(rows(0.1, 0.1), np.array([False, False]))[0]]
    raws.append(module.step(rows(0.2, 0.0), np.array([True, False]), next_observations=rows(0.0, 0.0))[0])
    module.collect_all()
    return module, raws


def test_start_states_are_recorded_but_pay_nothing_and_count_no_step():
    module, raws = stepped_module(record=True)
    assert module.n_recorded_steps == 4  # 2 steps x 2 envs; the 3 first observations are not steps
    assert module.memory.size == 7  # 4 reached + 3 first observations
    store = module.trajectories
    assert store.count.tolist() == [4, 3]
    # env 0: s_0, s_1, its terminal state, then the next episode's s_0, with their episode ids
    np.testing.assert_allclose(store.embeddings[:4, 0], module.embed(rows(0.0, 0.1, 0.2, 0.0)), rtol=0, atol=1e-6)
    ids = store.episode_ids[:4, 0]
    assert ids[0] == ids[1] == ids[2] != ids[3]
    # the finished episode's goal candidates start at s_0
    np.testing.assert_array_equal(module.finished_episodes[0], rows(0.0, 0.1, 0.2))
    # the normaliser and the reward statistics saw the 4 step rewards only
    assert module._reward_count == 4
    # env 1 came back to its first observation: a revisit under first_visit, so it pays 0
    assert raws[1][1] == 0.0 and raws[1][0] > 0.0


def test_without_the_option_first_states_are_not_recorded():
    module, raws = stepped_module(record=False)
    assert module.n_recorded_steps == 4 and module.memory.size == 4
    assert module.trajectories.count.tolist() == [2, 2]
    np.testing.assert_array_equal(module.finished_episodes[0], rows(0.1, 0.2))
    assert raws[1][1] > 0.0  # the start was never counted: coming back to it is a first visit
    # the step rewards that do not involve the start are the same either way
    recorded, raws_recorded = stepped_module(record=True)
    np.testing.assert_array_equal(raws[0], raws_recorded[0])
    assert raws[1][0] == raws_recorded[1][0]


@pytest.mark.parametrize("deferred", [False, True], ids=["step", "submit-collect"])
def test_the_vecenv_wrapper_records_each_reset_observation(deferred):
    """Through the wrapper, in both of its paths: every episode's recorded states start with its reset observation
    (ChainEnv resets to position 0), also after an automatic reset."""
    venv = GoCuVecEnvWrapper(
        make_vec_env(lambda: ChainEnv(length=3, max_steps=4), n_envs=2, seed=0),
        mode="separate", curiosity_kwargs={**SMALL_CURIOSITY, "record_start_states": True, "scoring_process": False},
    )
    module = venv.module
    module.recording = True
    venv.reset()
    steps, episodes = 9, np.ones(2, dtype=int)
    for _ in range(steps):
        venv.defer = deferred
        _, _, dones, _ = venv.step(np.ones(2, dtype=np.int64))  # always right: episodes of 3 steps
        if deferred:
            venv.take_deferred(venv.deferred)
        episodes += dones
    module.collect_all()
    assert module.n_recorded_steps == 2 * steps
    assert module.trajectories.count.tolist() == (steps + episodes).tolist()
    start = module.embed(rows(0.0))[0]
    ids = module.trajectories.episode_ids[:, 0][: module.trajectories.count[0]]
    firsts = np.flatnonzero(np.r_[True, ids[1:] != ids[:-1]])  # ring positions where an episode begins
    assert len(firsts) == episodes[0]
    for t in firsts:
        np.testing.assert_allclose(module.trajectories.embeddings[t, 0], start, rtol=0, atol=1e-6)


def chain_model(record: bool, scoring_process: bool):
    """PPO_GoCu on two ChainEnvs of 3 cells and at most 4 steps, rollouts of 16 steps per env."""
    from sb3_gocu import PPO_GoCu

    env = make_vec_env(lambda: ChainEnv(length=3, max_steps=4), n_envs=2, seed=0)
    kwargs = {**SMALL_CURIOSITY, "record_start_states": record, "scoring_process": scoring_process}
    return PPO_GoCu("MlpPolicy", env, n_steps=16, batch_size=32, seed=0, curiosity_kwargs=kwargs)


def test_ppo_gocu_records_the_reset_observations_through_the_scoring_process():
    model = chain_model(record=True, scoring_process=True)
    model.learn(160)
    module = model.curiosity
    module.collect_all()
    store, start = module.trajectories, module.embed(rows(0.0))[0]
    for e in range(2):
        ids = store.episode_ids[: store.count[e], e]
        assert len(ids) > 8
        firsts = np.flatnonzero(ids[1:] != ids[:-1]) + 1  # where an episode begins after another in the ring
        assert len(firsts) >= 2
        for t in firsts:
            np.testing.assert_allclose(store.embeddings[t, e], start, rtol=0, atol=1e-6)


def test_first_observations_of_a_reset_before_recording_are_recorded_when_it_starts():
    """SB3's learn resets the env before the callback switches recording on: those first observations wait and are
    recorded by start_recording, unless their episode took a step (or ended) while recording was off."""
    module = GoalCuriosityModule(SPACE, **{**SMALL_CURIOSITY, "record_start_states": True}, seed=0)
    module.begin_episodes(np.arange(3), rows(0.0, 0.1, 0.2))  # not recording: nothing recorded yet
    assert module.memory.size == 0 and module.trajectories.count.tolist() == [0, 0, 0]
    module.step(rows(0.3), np.array([False]), env_indices=np.array([1]))  # env 1's episode goes on unrecorded
    module.begin_episodes(np.array([2]), rows(0.4))  # env 2 starts again: its earlier s_0 is gone
    module.start_recording()
    module.collect_all()
    assert module.recording and module.n_recorded_steps == 0
    assert module.trajectories.count.tolist() == [1, 0, 1]
    np.testing.assert_allclose(module.trajectories.embeddings[0, [0, 2]], module.embed(rows(0.0, 0.4)), rtol=0, atol=1e-6)
    assert module.memory.size == 2
    module.start_recording()  # nothing left to record
    module.collect_all()
    assert module.trajectories.count.tolist() == [1, 0, 1]


@pytest.mark.parametrize("record", [True, False])
def test_a_second_learn_records_the_first_observations_of_its_reset(record):
    """Every episode of the second learn() has its s_0 in the trajectory store, the first one (begun by learn's own
    reset, before the callback starts) included; without the option none has."""
    model = chain_model(record=record, scoring_process=False)
    model.learn(32)
    module = model.curiosity
    module.collect_all()
    store = module.trajectories
    before = store.count.copy()
    model.learn(32)  # reset_num_timesteps=True: learn resets the env again
    module.collect_all()
    start = module.embed(rows(0.0))[0]
    for e in range(2):
        ids = store.episode_ids[before[e] : store.count[e], e]
        episodes = len(np.unique(ids))
        assert store.count[e] - before[e] == 16 + (episodes if record else 0)
        if record:
            np.testing.assert_allclose(store.embeddings[before[e], e], start, rtol=0, atol=1e-6)
