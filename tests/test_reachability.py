"""The mastery predictor learns reachability: held-out AUCs on a synthetic task whose reachability is known, and the
pieces that measure it (the AUC, the pairs, the held-out split)."""

from __future__ import annotations

import numpy as np
import pytest
import torch as th
from gymnasium import spaces

from sb3_gocu.curiosity import GoalCuriosityModule
from sb3_gocu.curiosity.reachability import auc, reachability_pairs
from sb3_gocu.curiosity.stores import TrajectoryStore

RING = 48  # positions on the ring
SIDE = 8  # the image is SIDE x SIDE
UPDATES = 4  # predictor updates of 6,144 steps


def render(layout: np.ndarray, position: np.ndarray) -> np.ndarray:
    """Images (n, 8, 8, 3) of a ring walk: the position lights 8 consecutive cells of the first 6 rows' 48 in grey,
    and the layout (0..7) one cell of the last row in white: each episode has a layout of its own, and a view of
    another layout differs from one of this layout in that cell alone (as DoorKey's partial views of other layouts)."""
    n = len(layout)
    img = np.zeros((n, SIDE, SIDE, 3), dtype=np.uint8)
    for k in range(SIDE):  # the view: the 8 cells from the position on, as near positions share part of a view
        cell = (position + k) % RING
        img[np.arange(n), cell // SIDE, cell % SIDE] = 160
    img[np.arange(n), SIDE - 1, layout] = 255
    return img


def walk_module(pair_labels: str, seed: int = 0) -> GoalCuriosityModule:
    """A module that recorded 16 envs walking the ring from position 0 (forward or staying, at random) for 4 predictor
    updates of 6,144 steps, in episodes of 96 steps with a new layout each, and trained its predictor after each. Every
    episode walks through the same positions, so the goals of other episodes look like this episode's states but for
    the layout's cell, as DoorKey's phases repeat from layout to layout."""
    space = spaces.Box(0, 255, (SIDE, SIDE, 3), np.uint8)
    mod = GoalCuriosityModule(space, seed=seed, pair_labels=pair_labels, predictor_train_freq=6144, predictor_pairs=16384,
                              pretrain_steps=2048, vae_epochs=20, goal_buffer_size=200, n_goals=5, predictor_hidden=(256, 256))
    rng = np.random.default_rng(seed)
    n_envs, length = 16, 96
    layout, pos, t = rng.integers(8, size=n_envs), np.zeros(n_envs, dtype=np.int64), np.zeros(n_envs, dtype=np.int64)
    # the VAE's pretraining frames: random positions and layouts
    mod.memory.add(render(rng.integers(8, size=2048), rng.integers(RING, size=2048)), mod.rng)
    mod.pretrain()
    mod.recording = True
    for _ in range(UPDATES * 6144 // n_envs):
        pos = (pos + rng.choice([1, 1, 0], size=n_envs)) % RING
        t += 1
        done = t == length
        mod.step(render(layout, pos), done)
        layout[done], pos[done], t[done] = rng.integers(8, size=done.sum()), 0, 0
        if mod.n_recorded_steps % 6144 == 0:
            mod.maybe_train()
    return mod


@pytest.fixture(scope="module")
def trained() -> dict[str, GoalCuriosityModule]:
    return {labels: walk_module(labels) for labels in ("reachability", "eq16")}


def test_reachability_pairs_make_the_predictor_tell_near_goals_from_far_ones_and_from_the_buffers(trained):
    """Held out, after the fourth update (each about 80 Adam steps of batch 128 on the distinct pairs): near goals
    (<= 5 steps ahead) against goals first seen 30+ steps later, and against the goal buffer's goals (other
    episodes, other layouts). Trained on pairs of one episode labelled by eq 15-16, the predictor never meets a goal
    of another episode, and scores too many of them as near (0.85-0.86 on seeds 0 and 1, against 0.92-0.94)."""
    stats = trained["reachability"].stats
    assert stats["predictor_adam_steps"] >= 60
    assert stats["predictor_auc_far"] >= 0.9, stats
    assert stats["predictor_auc_goals"] >= 0.9, stats
    eq16 = trained["eq16"].stats
    assert eq16["predictor_auc_goals"] < 0.9, eq16  # the same test fails on the pairs of eq 15-16
    popped = trained["reachability"].pop_reward_stats()
    assert popped["predictor_auc_far"] == stats["predictor_auc_far"] and popped["predictor_auc_goals"] == stats["predictor_auc_goals"]


def test_auc_is_the_chance_that_a_positive_outscores_a_negative():
    rng = np.random.default_rng(0)
    pos, neg = rng.integers(0, 5, 60), rng.integers(0, 4, 50)
    brute = np.mean([(a > b) + 0.5 * (a == b) for a in pos for b in neg])
    assert auc(pos, neg) == pytest.approx(brute)
    assert auc([2.0, 3.0], [1.0]) == 1.0 and auc([1.0], [2.0, 3.0]) == 0.0 and auc([1.0], [1.0]) == 0.5
    assert np.isnan(auc([], [1.0]))


def store_of(episodes: list[int]) -> TrajectoryStore:
    """One env whose states are 0, 1, 2, ... (phi = the step), in episodes of the given lengths."""
    store = TrajectoryStore(sum(episodes), embed_dim=1)
    store.ensure_envs(1)
    step = 0
    for ep, n in enumerate(episodes):
        for _ in range(n):
            store.add(th.tensor([[float(step)]]), np.array([ep]), np.arange(1))
            step += 1
    return store


def test_pairs_stay_in_their_episode_and_part():
    store = store_of([50, 70, 80])  # states 0-49, 50-119, 120-199
    rng = np.random.default_rng(0)
    s, g, d = store.sample_pairs(2000, 5, rng, holdout=40)
    assert ((g - s)[:, 0] == d).all() and d.min() >= 1 and d.max() <= 5
    assert g.max() < 160  # the newest 40 states are held out
    assert not ((s < 50) & (g >= 50)).any() and not ((s < 120) & (g >= 120)).any()
    s, g, d = store.sample_pairs(2000, None, rng, min_distance=30, holdout=40, held_out=True)
    assert s.min() >= 160 and d.min() >= 30 and g.max() <= 199
    s, g, d = store.sample_pairs(100, None, rng, min_distance=60, holdout=40)
    assert len(s) == 100 and s.min() >= 50 and s.max() <= 59 and d.min() >= 60  # only the second episode has room for 60
    with pytest.raises(ValueError, match="max_distance must be >= min_distance"):
        store.sample_pairs(100, 10, rng, min_distance=60)


def test_reachability_pairs_are_labelled_by_their_gap():
    from sb3_gocu.curiosity.goals import GoalBuffer

    store = store_of([200])
    goals = GoalBuffer(8, (1,), np.dtype(np.float32), 1, 0.0)
    goals.add(np.full((8, 1), -5, np.float32) - np.arange(8)[:, None], -5.0 - th.arange(8.0)[:, None], np.random.default_rng(0))
    s, g, dist, target = reachability_pairs(store, goals, 4000, 5, 30, np.random.default_rng(0), holdout=0)
    gap = (g - s)[:, 0]
    near, against_goal = target == 1, dist == -1
    assert near.float().mean() == pytest.approx(0.5, abs=0.01) and against_goal.float().mean() == pytest.approx(0.25, abs=0.01)
    assert (gap[near] >= 1).all() and (gap[near] <= 5).all()
    assert (gap[~near & ~against_goal] >= 30).all()
    assert (g[against_goal] <= -5).all()  # goals of the buffer
