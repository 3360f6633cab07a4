"""Scoring in the worker thread (``submit``): the same values as scoring in the caller, bit for bit."""


import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.env_util import make_vec_env

from sb3_gocu import GoalCuriosityModule, PPO_GoCu

from conftest import SMALL_CURIOSITY, ChainEnv

SPACE = spaces.Box(0, 255, (16, 16, 3), np.uint8)


def frames_with_repeats(n_steps: int, n_envs: int, seed: int) -> np.ndarray:
    """Frames drawn from a small pool, so that states recur within and across envs and steps (memo hits,
    rows embedded by an earlier ticket still in flight)."""
    rng = np.random.default_rng(seed)
    pool = rng.integers(0, 256, (12, 16, 16, 3), dtype=np.uint8)
    return pool[rng.integers(0, len(pool), (n_steps, n_envs))]


def run_module(mode: str, frames: np.ndarray, dones: np.ndarray, in_flight: int, **kwargs) -> tuple[list, GoalCuriosityModule]:
    """Feed the frames through a fresh module: ``sync`` (step) or ``worker`` (submit, with up to ``in_flight``
    tickets outstanding); a predictor and a VAE update halfway (new encoder, folded predictor and goal halves).
    ``kwargs``: more module keywords."""
    module = GoalCuriosityModule(SPACE, **SMALL_CURIOSITY, revisit_decay="none", seed=3, **kwargs)
    module.recording = True
    module.pretrain()
    out, tickets = [], []
    for t, (f, d) in enumerate(zip(frames, dones)):
        if t == len(frames) // 4:  # goals from the episodes so far: later episodes are scored against them
            module.collect_all()
            module.add_finished_episode_goals()
        if t == len(frames) // 2:
            module.collect_all()
            module.train_predictor()
            module.train_vae()
        if mode == "sync":
            out.append(module.step(f, d))
            continue
        tickets.append(module.submit(f, d))
        if len(tickets) > in_flight:
            out.append(module.collect(tickets.pop(0)))
    out += [module.collect(t) for t in tickets]
    return out, module


def test_module_scores_the_same_in_the_worker_as_in_the_caller():
    frames = frames_with_repeats(120, 3, seed=0)
    dones = np.random.default_rng(1).random((120, 3)) < 0.08
    sync, m_sync = run_module("sync", frames, dones, 0)
    for mode, in_flight in (("worker", 1), ("worker", 4)):
        other, m_other = run_module(mode, frames, dones, in_flight)
        for (r1, n1), (r2, n2) in zip(sync, other):
            assert np.array_equal(r1, r2) and np.array_equal(n1, n2), mode
        assert np.array_equal(m_sync.episodes.goal_parts.numpy(), m_other.episodes.goal_parts.numpy())
        assert m_sync.scorer.cache_hits == m_other.scorer.cache_hits > 0
    r = np.concatenate([r for r, _ in sync])
    assert len(np.unique(r)) > 5  # the rewards vary: a constant would match trivially
    assert m_other.scorer.time_in_worker > 0


def test_phi_of_a_ticket_in_flight_is_taken_from_the_worker():
    """A state new to the embedding memo, seen again in the next ticket before the first is collected, is
    embedded once (by the first ticket) and the second ticket's phi comes from it."""
    module = GoalCuriosityModule(SPACE, **SMALL_CURIOSITY, seed=0)
    module.pretrain()
    frame = np.random.default_rng(5).integers(0, 256, (1, 16, 16, 3), dtype=np.uint8)
    other = np.random.default_rng(6).integers(0, 256, (1, 16, 16, 3), dtype=np.uint8)
    first = module.submit(np.concatenate([frame, other]), np.zeros(2, bool))
    second = module.submit(np.concatenate([other, frame]), np.zeros(2, bool))  # each env sees the other's state
    assert len(second.phi_from) == 2 and len(second.embed_rows) == 0
    module.collect(second)
    expected = module.embed(np.concatenate([frame, other])).numpy()
    assert np.array_equal(first.phi, expected) and np.array_equal(second.phi, expected[::-1])
    assert np.array_equal(second.rewards, module.score_states(np.concatenate([other, frame])))


def chain_run(before_learning=None, **kwargs) -> PPO_GoCu:
    """PPO_GoCu on 2 ChainEnvs, 640 steps (a predictor update every 128), seed 0; ``before_learning(model)`` runs
    just before ``learn``."""
    th.manual_seed(0)
    env = make_vec_env(lambda: ChainEnv(), n_envs=2, seed=0)
    curiosity = {**SMALL_CURIOSITY, "predictor_train_freq": 128}
    model = PPO_GoCu("MlpPolicy", env, n_steps=64, batch_size=64, n_epochs=2, seed=0, curiosity_kwargs=curiosity, **kwargs)
    if before_learning is not None:
        before_learning(model)
    model.learn(640)
    return model


def assert_same_training(a: PPO_GoCu, b: PPO_GoCu) -> None:
    """The same intrinsic rewards in the last rollout, policy weights and VAE and predictor weights, to the bit."""
    assert np.array_equal(a.rollout_buffer.intrinsic_rewards, b.rollout_buffer.intrinsic_rewards)
    for (k, v), (k2, v2) in zip(a.policy.state_dict().items(), b.policy.state_dict().items()):
        assert k == k2 and th.equal(v, v2), k
    sa, sb = a.curiosity.state_dict(), b.curiosity.state_dict()
    for net in ("vae", "predictor"):
        assert all(th.equal(sa[net][k], sb[net][k]) for k in sa[net]), net


def in_caller(model: PPO_GoCu) -> None:
    """Every ticket of ``model``'s module scored in the training thread."""
    scorer = model.curiosity.scorer
    dispatch = scorer.dispatch
    scorer.dispatch = lambda ticket, background: dispatch(ticket, False)


def test_ppo_gocu_with_the_scoring_worker_matches_scoring_in_the_training_thread():
    """A step in flight while the envs take the next, collected in order across the rollout's end: the same training
    as every step scored in the training thread."""
    runs = []
    for in_worker in (False, True):
        in_flight = []  # tickets outstanding at each collection

        def before_learning(model, in_flight=in_flight, in_worker=in_worker):
            if not in_worker:
                in_caller(model)
            collect = model.curiosity.collect
            model.curiosity.collect = lambda ticket: in_flight.append(len(model.curiosity.scorer.outstanding)) or collect(ticket)

        model = chain_run(before_learning)
        model.max_in_flight = max(in_flight, default=0)
        runs.append(model)
    a, b = runs
    assert a.rollout_buffer.intrinsic_rewards.any()
    assert a.curiosity.scorer.worker is None and b.curiosity.scorer.worker is not None
    assert_same_training(a, b)
    assert b.max_in_flight == 2  # the step just submitted and the one before it


def test_the_worker_computes_with_the_callers_thread_count():
    th.set_num_threads(1)
    module = GoalCuriosityModule(SPACE, **SMALL_CURIOSITY, seed=0)
    module.collect(module.submit(frames_with_repeats(1, 2, seed=4)[0], np.zeros(2, bool)))
    assert module.scorer.worker.submit(th.get_num_threads).result() == 1


def test_a_failure_in_the_worker_is_raised_where_the_scores_are_taken():
    module = GoalCuriosityModule(SPACE, **SMALL_CURIOSITY, seed=0)
    small = GoalCuriosityModule(spaces.Box(0, 255, (8, 8, 3), np.uint8), **SMALL_CURIOSITY, seed=0)
    module.vae = small.vae  # built for 8x8 frames: its fully connected layer refuses 16x16 ones
    module.refresh()  # the scoring takes it into use
    ticket = module.submit(frames_with_repeats(1, 2, seed=4)[0], np.zeros(2, bool))
    assert ticket.future is not None
    with pytest.raises(RuntimeError, match="mat1 and mat2"):
        module.collect(ticket)
