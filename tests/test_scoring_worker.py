"""Scoring in the worker thread (``submit``): the same values as scoring in the caller, bit for bit (a whole
PPO_GoCu run scored either way: tests/test_reliability.py)."""


import numpy as np
import pytest
import torch as th
from gymnasium import spaces

from sb3_gocu import GoalCuriosityModule

from conftest import SMALL_CURIOSITY

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
