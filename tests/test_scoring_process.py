"""Scoring in the worker process (a CPU module, ``submit``): the same values as scoring in the caller, bit for bit."""

import threading

import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.env_util import make_vec_env

from sb3_gocu import GoalCuriosityModule, PPO_GoCu
from sb3_gocu.ppo_gocu import SCORING_LAG
from sb3_gocu.curiosity.process import ProcessScorer

from conftest import SMALL_CURIOSITY, ChainEnv

SPACE = spaces.Box(0, 255, (16, 16, 3), np.uint8)


def frames_with_repeats(n_steps: int, n_envs: int, seed: int) -> np.ndarray:
    """Frames drawn from a small pool, so that states recur within and across envs and steps (memo hits,
    rows embedded by an earlier ticket still in flight)."""
    rng = np.random.default_rng(seed)
    pool = rng.integers(0, 256, (12, 16, 16, 3), dtype=np.uint8)
    return pool[rng.integers(0, len(pool), (n_steps, n_envs))]


def run_module(mode: str, frames: np.ndarray, dones: np.ndarray, in_flight: int, **kwargs) -> tuple[list, GoalCuriosityModule]:
    """Feed the frames through a fresh module: ``sync`` (step) or ``process`` (submit, with up to ``in_flight``
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


def test_module_scores_the_same_in_a_process_as_in_the_caller():
    frames = frames_with_repeats(120, 3, seed=0)
    dones = np.random.default_rng(1).random((120, 3)) < 0.08
    sync, m_sync = run_module("sync", frames, dones, 0)
    for mode, in_flight in (("process", 1), ("process", 4)):
        other, m_other = run_module(mode, frames, dones, in_flight)
        for (r1, n1), (r2, n2) in zip(sync, other):
            assert np.array_equal(r1, r2) and np.array_equal(n1, n2), mode
        assert np.array_equal(m_sync.episodes.goal_parts.numpy(), m_other.episodes.goal_parts.numpy())
        assert m_sync.scorer.cache_hits == m_other.scorer.cache_hits > 0
    r = np.concatenate([r for r, _ in sync])
    assert len(np.unique(r)) > 5  # the rewards vary: a constant would match trivially
    assert m_other.scorer.time_in_process > 0 and m_other.scorer.cpu_in_process > 0


def test_many_tickets_in_flight_do_not_block_the_pipes():
    """The answers not read yet stay below ``max_answer_bytes``: a caller that submits many tickets before it
    collects is not stuck writing to a child stuck writing its answers.
    Here 40 tickets of 64 new frames each are in flight, about 3.3 KB of answer each: 130 KB in all, twice the
    answer pipe's 64 KiB."""
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 256, (40, 64, 16, 16, 3), dtype=np.uint8)  # all new: every row embedded and scored
    dones = np.zeros((40, 64), dtype=bool)
    result: dict = {}
    worker = threading.Thread(target=lambda: result.update(out=run_module("process", frames, dones, 40)), daemon=True)
    worker.start()
    worker.join(timeout=120)
    assert not worker.is_alive(), "the caller and the scoring process blocked each other"
    sync, _ = run_module("sync", frames, dones, 0)
    for (r1, n1), (r2, n2) in zip(sync, result["out"][0]):
        assert np.array_equal(r1, r2) and np.array_equal(n1, n2)
    assert result["out"][1].scorer.process._answer_bytes == 0


def test_phi_of_a_ticket_in_flight_is_taken_from_the_process():
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


def test_ppo_gocu_with_a_scoring_process_matches_scoring_in_the_training_thread():
    """Up to SCORING_LAG steps in flight, collected in order across the rollout's end, and spilled steps scored in the
    training thread: the same training as every step scored in the training thread."""
    runs = []
    for in_process in (False, True):
        in_flight = []  # tickets outstanding at each collection

        def before_learning(model, in_flight=in_flight, in_process=in_process):
            model.curiosity.scorer.use_process = in_process
            collect = model.curiosity.collect
            model.curiosity.collect = lambda ticket: in_flight.append(len(model.curiosity.scorer.outstanding)) or collect(ticket)

        model = chain_run(before_learning)
        model.max_in_flight = max(in_flight, default=0)
        runs.append(model)
    a, b = runs
    assert a.rollout_buffer.intrinsic_rewards.any()
    assert a.curiosity.scorer.process is None and b.curiosity.scorer.process is not None
    assert_same_training(a, b)
    assert b.max_in_flight == SCORING_LAG + 1  # the step just submitted and SCORING_LAG before it


def test_spilled_tickets_give_the_same_rewards(monkeypatch):
    """Tickets scored in the training thread instead of the process (here every other ticket, forced) give the same
    rewards and networks as the run that sends every ticket it can to the process."""
    calls = [0]
    unanswered = ProcessScorer.unanswered

    def every_other(self):
        calls[0] += 1
        return 10**6 if calls[0] % 2 else 0  # as if the process were far behind, or not at all

    def never(self):
        return 0

    a = chain_run(lambda _: monkeypatch.setattr(ProcessScorer, "unanswered", never))
    spilled_a, sent_a = a.curiosity.scorer.spilled_tickets, a.curiosity.scorer.process.bytes_sent
    b = chain_run(lambda _: monkeypatch.setattr(ProcessScorer, "unanswered", every_other))
    assert unanswered is not ProcessScorer.unanswered
    assert b.curiosity.scorer.spilled_tickets > 10 + spilled_a
    assert b.curiosity.scorer.process.bytes_sent < sent_a  # fewer tickets went to the process
    assert b.curiosity.scorer.spill is None  # only during rollouts
    assert a.rollout_buffer.intrinsic_rewards.any()
    assert_same_training(a, b)


def test_a_dead_scoring_process_is_a_clear_error():
    module = GoalCuriosityModule(SPACE, **SMALL_CURIOSITY, seed=0)
    frames = frames_with_repeats(2, 2, seed=2)
    module.collect(module.submit(frames[0], np.zeros(2, bool)))
    module.scorer.process._proc.kill()
    module.scorer.process._proc.wait()
    with pytest.raises(RuntimeError, match="scoring process ended"):
        module.collect(module.submit(frames_with_repeats(1, 2, seed=9)[0], np.zeros(2, bool)))


def test_the_scoring_process_is_a_cpu_modules_and_starts_with_learn():
    """A CPU module on this (POSIX) machine scores in a process; PPO_GoCu starts it at learn's start (beside
    pretraining). A module that scores in the caller (on a GPU, tests/test_device.py) refuses to start one."""
    assert GoalCuriosityModule(SPACE, **SMALL_CURIOSITY).scorer.use_process
    env = make_vec_env(lambda: ChainEnv(), n_envs=2, seed=0)
    model = PPO_GoCu("MlpPolicy", env, n_steps=64, batch_size=64, n_epochs=1, seed=0, curiosity_kwargs=SMALL_CURIOSITY)
    assert model.curiosity.scorer.process is None
    model.learn(64)
    assert model.curiosity.scorer.process is not None and model.curiosity.scorer.process.bytes_sent > 0
    in_caller = GoalCuriosityModule(SPACE, **SMALL_CURIOSITY)
    in_caller.scorer.use_process = False
    with pytest.raises(ValueError, match="scores in the caller"):
        in_caller.start_scoring_process()
    with pytest.raises(ValueError, match="num_threads must be >= 1"):
        ProcessScorer(None, num_threads=0)


def test_a_failure_in_the_scoring_process_is_raised_with_its_traceback():
    """The worker catches the error and sends its traceback; the training process raises it at collect."""
    module = GoalCuriosityModule(SPACE, **SMALL_CURIOSITY, seed=0)
    small = GoalCuriosityModule(spaces.Box(0, 255, (8, 8, 3), np.uint8), **SMALL_CURIOSITY, seed=0)
    module.vae = small.vae  # built for 8x8 frames: its fully connected layer refuses 16x16 ones
    module.refresh()  # the scoring takes it into use
    ticket = module.submit(frames_with_repeats(1, 2, seed=4)[0], np.zeros(2, bool))
    with pytest.raises(RuntimeError, match=r"scoring process failed:\n(.|\n)*Traceback(.|\n)*mat1 and mat2"):
        module.collect(ticket)
