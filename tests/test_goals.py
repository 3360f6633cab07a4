"""Goal strategies, the novelty filter and the capacity limits of the goal buffer and memory bank."""

import numpy as np
import pytest
import torch as th

from sb3_gocu.curiosity import GoalBuffer, MemoryBank, TrajectoryStore, select_goal_steps
from sb3_gocu.curiosity.episodes import Episodes


def draws(strategy, length=50, n_new=7, n=3000, seed=0):
    rng = np.random.default_rng(seed)
    counts = np.zeros(length)
    for _ in range(n):
        steps = select_goal_steps(length, n_new, strategy, rng)
        assert steps[-1] == length - 1, "the final state is always a candidate"
        assert len(steps) == n_new + 1 and len(set(steps.tolist())) == n_new + 1
        counts[steps] += 1
    return counts / n


def test_random_strategy_is_uniform_over_earlier_steps():
    freq = draws("random")
    assert freq[-1] == 1.0
    # each earlier step is drawn with probability 7 / 49
    assert np.abs(freq[:-1] - 7 / 49).max() < 0.04


def test_proportional_strategy_prefers_late_states():
    freq = draws("proportional")
    early, late = freq[:10].mean(), freq[39:49].mean()
    assert late > 3 * early
    # monotone trend: correlation of frequency with step index is strongly positive
    assert np.corrcoef(np.arange(49), freq[:-1])[0, 1] > 0.9


def test_late_strategy_only_draws_from_last_4l_steps():
    freq = draws("late")
    window = np.arange(49 - 28, 49)
    assert freq[: window[0]].sum() == 0
    assert np.abs(freq[window] - 7 / 28).max() < 0.04


def test_short_episode_and_unknown_strategy():
    rng = np.random.default_rng(0)
    assert select_goal_steps(3, 7, "proportional", rng).tolist() == [0, 1, 2]
    assert select_goal_steps(1, 7, "random", rng).tolist() == [0]
    with pytest.raises(ValueError, match="goal_strategy"):
        select_goal_steps(10, 2, "earliest", rng)


def make_buffer(capacity=4, novelty=0.5):
    return GoalBuffer(capacity, obs_shape=(1,), obs_dtype=np.float32, embed_dim=2, novelty=novelty)


def test_novelty_filter_on_hand_made_buffer():
    rng = np.random.default_rng(0)
    buf = make_buffer(capacity=10, novelty=0.5)
    pts = np.array([[0, 0], [4, 0], [0, 4]], dtype=np.float32)
    assert buf.add(pts[:, :1], th.from_numpy(pts), rng) == 3
    # nearest-neighbour distances: 4, 4, 4 -> median 4 -> threshold 0.5 * 4 = 2
    assert buf.threshold() == pytest.approx(2.0)
    near = np.array([[1.5, 0]], dtype=np.float32)  # 1.5 from (0, 0): refused
    far = np.array([[2.5, 2.5]], dtype=np.float32)  # sqrt(2 * 1.5^2) ~ 2.12 from (4, 0) and (0, 4): kept
    assert buf.add(near[:, :1], th.from_numpy(near), rng) == 0
    assert buf.add(far[:, :1], th.from_numpy(far), rng) == 1
    assert buf.size == 4 and buf.n_refused == 1
    # an exact duplicate is refused even with novelty 0
    buf0 = make_buffer(novelty=0.0)
    assert buf0.add(pts[:2, :1], th.from_numpy(pts[:2]), rng) == 2
    assert buf0.add(pts[:1, :1], th.from_numpy(pts[:1]), rng) == 0


@pytest.mark.parametrize("novelty", [0.1, 0.5])
def test_nearest_neighbour_distances_stay_exact_as_goals_come_and_go(novelty):
    """After every add, each goal's kept distance is its true nearest-neighbour distance: also for the goals
    a new goal comes nearer to, and for those whose nearest neighbour was the goal a full buffer replaced."""
    rng, data = np.random.default_rng(3), np.random.default_rng(4)
    buf = make_buffer(capacity=6, novelty=novelty)
    for _ in range(60):
        pts = data.normal(size=(1, 2)).astype(np.float32)
        buf.add(pts[:, :1], th.from_numpy(pts), rng)
        e = buf.embeddings[: buf.size].double()
        d = th.cdist(e, e)
        d.fill_diagonal_(float("inf"))
        np.testing.assert_allclose(buf.nn_dist[: buf.size], d.min(dim=1).values.numpy(), rtol=1e-6)
    assert buf.size == 6 and buf.n_added > 6  # the buffer was full and replaced goals


def test_goal_buffer_capacity_and_random_replacement():
    rng = np.random.default_rng(1)
    buf = make_buffer(capacity=4, novelty=0.0)
    pts = np.stack([np.arange(10.0), np.zeros(10)], axis=1).astype(np.float32) * 10
    assert buf.add(pts[:, :1], th.from_numpy(pts), rng) == 10
    assert buf.size == 4 and buf.observations.shape[0] == 4
    # the buffer holds 4 distinct goals, and later goals replaced earlier ones
    held = sorted(buf.observations[:, 0].tolist())
    assert len(set(held)) == 4 and max(held) > 30
    assert th.equal(buf.embeddings[:, 0], th.from_numpy(buf.observations[:, 0]))


def test_goal_sampling_without_replacement():
    rng = np.random.default_rng(0)
    buf = make_buffer(capacity=10, novelty=0.0)
    pts = np.stack([np.arange(6.0), np.zeros(6)], axis=1).astype(np.float32)
    buf.add(pts[:, :1], th.from_numpy(pts), rng)
    idx = buf.sample(100, 6, rng)
    assert idx.shape == (100, 6)
    assert all(sorted(row) == list(range(6)) for row in idx.tolist())
    assert buf.sample(3, 8, rng).shape == (3, 8)  # fewer goals than K: with replacement
    assert make_buffer().sample(3, 2, rng).shape == (3, 0)


def test_memory_bank_capacity():
    rng = np.random.default_rng(0)
    bank = MemoryBank(5, (2,), np.uint8)
    bank.add(np.arange(8, dtype=np.uint8)[:, None].repeat(2, 1), rng)
    assert bank.size == 5 and bank.observations.shape == (5, 2)
    for _ in range(50):
        bank.add(np.full((3, 2), 200, np.uint8), rng)
    assert bank.size == 5
    assert (bank.observations == 200).all(axis=1).sum() >= 4  # random replacement reached nearly every slot


def test_trajectory_store_pairs_stay_in_episode_and_capacity():
    rng = np.random.default_rng(0)
    store = TrajectoryStore(total_capacity=40, embed_dim=1, min_per_env=4)
    store.ensure_envs(2)
    assert store.capacity == 20
    for t in range(50):
        episode = np.array([t // 10, 100 + t // 7])
        store.add(th.tensor([[float(t)], [float(t)]]), episode, np.arange(2))
    assert len(store) == 40
    s, g, y = store.sample_pairs(500, max_distance=5, rng=rng)
    assert len(s) == 500
    gap = (g - s)[:, 0]
    assert th.equal(gap, y) and y.min() >= 1 and y.max() <= 5
    # same episode: for env 0 episodes are blocks of 10 steps, for env 1 blocks of 7
    s_np, g_np = s[:, 0].numpy(), g[:, 0].numpy()
    same = (s_np // 10 == g_np // 10) | (s_np // 7 == g_np // 7)
    assert same.all()
    assert s_np.min() >= 30  # only the last 20 steps per env are kept


def test_trajectory_store_capacity_does_not_depend_on_how_envs_are_added():
    """Per-env wrappers add their envs one at a time: the rings are sized for all of them, not for the first."""
    one_by_one, at_once = TrajectoryStore(total_capacity=40, embed_dim=1, min_per_env=4), TrajectoryStore(40, 1, 4)
    for n in range(1, 5):
        one_by_one.ensure_envs(n)
    at_once.ensure_envs(4)
    assert one_by_one.capacity == at_once.capacity == 10
    assert one_by_one.embeddings.shape == (10, 4, 1) and (one_by_one.episode_ids == -1).all()
    # once a state is written, an added env gets a ring of the same length and nothing written is lost
    one_by_one.add(th.tensor([[1.0], [2.0], [3.0], [4.0]]), np.arange(4), np.arange(4))
    one_by_one.ensure_envs(5)
    assert one_by_one.capacity == 10 and one_by_one.embeddings.shape == (10, 5, 1)
    assert one_by_one.embeddings[0, :, 0].tolist() == [1.0, 2.0, 3.0, 4.0, 0.0]
    assert one_by_one.episode_ids[0].tolist() == [0, 1, 2, 3, -1] and len(one_by_one) == 4


def test_first_visit_distance_matches_a_scan_on_wrapped_rings_of_several_envs_and_episodes():
    """The first-visit distance (a binary search over each env's states sorted by embedding) equals a plain scan of
    s_t .. s_{t+y} for every pair, on rings that have wrapped, with episodes of several envs repeating a few states,
    and -0.0 equal to 0.0."""
    rng = np.random.default_rng(3)
    store = TrajectoryStore(total_capacity=90, embed_dim=2, min_per_env=30)
    store.ensure_envs(3)
    episode = np.zeros(3, dtype=np.int64)
    for _ in range(75):  # 75 states per env in rings of 30
        episode += rng.random(3) < 0.1
        phi = th.from_numpy(rng.integers(0, 4, size=(3, 2)).astype(np.float32))
        phi[phi == 0] = -0.0 if rng.random() < 0.5 else 0.0
        store.add(phi, episode.copy(), np.arange(3))
    s, g, d = store.sample_pairs(3000, None, np.random.default_rng(0), first_visit=True)
    env, t, room = store._episode_runs(0, False)
    pick_rng = np.random.default_rng(0)  # the same draws as sample_pairs makes
    ok = room >= 1
    env, t, room = env[ok], t[ok], room[ok]
    pick = pick_rng.integers(len(env), size=3000)
    env, t, room = env[pick], t[pick], room[pick]
    y = 1 + (pick_rng.random(3000) * room).astype(np.int64)
    for e, ti, yi, di in zip(env, t, y, d.tolist()):
        ring = store.embeddings[(store.count[e] - 30 + np.arange(30)) % 30, e]
        expected = next(k for k in range(yi + 1) if th.equal(ring[ti + k] + 0.0, ring[ti + yi] + 0.0))
        assert di == expected
    assert (d < th.from_numpy(y).float()).float().mean() > 0.15  # revisits are common here (19%): the check has teeth


def test_first_visit_distance_is_the_earliest_visit_of_the_goal():
    """Trajectory (one env, one episode) 0 1 1 1 2 1 3: a pair (s, g) gets the steps until g is first seen after s."""
    traj = [0.0, 1.0, 1.0, 1.0, 2.0, 1.0, 3.0]
    store = TrajectoryStore(total_capacity=16, embed_dim=1, min_per_env=16)
    store.ensure_envs(1)
    for v in traj:
        store.add(th.tensor([[v]]), np.array([7]), np.arange(1))
    rng = np.random.default_rng(0)
    s, g, d = store.sample_pairs(2000, max_distance=6, rng=rng, first_visit=True)
    s_plain, g_plain, y = store.sample_pairs(2000, max_distance=6, rng=np.random.default_rng(0))
    assert th.equal(s, s_plain) and th.equal(g, g_plain)  # same pairs, only the distance differs
    seen = set()
    for sv, gv, dv, yv in zip(s[:, 0].tolist(), g[:, 0].tolist(), d.tolist(), y.tolist()):
        # recover t from the pair: s index t with traj[t] == sv and traj[t + y] == gv
        starts = [t for t in range(len(traj)) if traj[t] == sv and t + yv < len(traj) and traj[t + int(yv)] == gv]
        expected = {next(k for k in range(int(yv) + 1) if traj[t + k] == gv) for t in starts}
        assert dv in expected
        seen.add((sv, gv, dv, yv))
    assert (1.0, 1.0, 0.0, 2.0) in seen  # (s_1, s_3): the goal (1) is the start state itself
    assert (1.0, 1.0, 0.0, 4.0) in seen  # (s_1, s_5): left and came back; still distance 0
    assert (0.0, 1.0, 1.0, 5.0) in seen  # (s_0, s_5): state 1 was first reached at step 1
    assert (1.0, 2.0, 3.0, 3.0) in seen  # (s_1, s_4): nothing earlier; plain gap
    assert (d <= y).all() and (d < y).any()


def test_predictor_pairs_are_deduplicated_with_their_multiplicity_as_weight():
    """The distinct pairs, weighted by how often each was drawn, give the same loss as the whole draw, and the
    update sees each distinct pair once per epoch."""
    from gymnasium import spaces

    from sb3_gocu.curiosity import GoalCuriosityModule

    space = spaces.Box(-10, 10, (1,), np.float32)
    kwargs = dict(n_goals=1, goal_buffer_size=4, embed_dim=1, predictor_hidden=(8,), predictor_pairs=400, max_distance=3, pair_labels="eq16",
                  predictor_epochs=1)
    mod = GoalCuriosityModule(space, seed=0, **kwargs)
    mod.trajectories.ensure_envs(1)
    for v in [0.0, 0.0, 0.0, 1.0, 1.0, 2.0, 0.0, 0.0, 1.0, 2.0, 2.0, 2.0] * 3:  # one episode with many repeats
        mod.trajectories.add(th.tensor([[v]]), np.array([5]), np.arange(1))
    state = mod.rng.bit_generator.state
    s_all, g_all, d_all = mod.trajectories.sample_pairs(400, 3, mod.rng, first_visit=True, holdout=mod.predictor_holdout())
    mod.rng.bit_generator.state = state
    job = mod.predictor_job()
    assert job.drawn == len(s_all) == 400
    distinct = {(a, b, c) for a, b, c in zip(s_all[:, 0].tolist(), g_all[:, 0].tolist(), d_all.tolist())}
    assert len(job.phi_s) == len(distinct) < 40  # at most 3 x 3 x 4 triples exist
    assert job.weights.mean().item() == pytest.approx(1.0)
    # weight of each distinct pair = its count in the draw x n_distinct / n_drawn
    for a, b, c, w in zip(job.phi_s[:, 0].tolist(), job.phi_g[:, 0].tolist(), job.dist.tolist(), job.weights.tolist()):
        count = int(((s_all[:, 0] == a) & (g_all[:, 0] == b) & (d_all == c)).sum())
        assert w == pytest.approx(count * len(distinct) / 400, rel=1e-6)
    # the weighted mean of any per-pair value over the distinct pairs equals its plain mean over the draw
    f = lambda s, g, d: s * 3 + g * 0.5 - d  # noqa: E731
    full = f(s_all[:, 0], g_all[:, 0], d_all).mean()
    weighted = (job.weights * f(job.phi_s[:, 0], job.phi_g[:, 0], job.dist)).mean()
    assert weighted.item() == pytest.approx(full.item(), rel=1e-5)


def test_every_finished_episode_waits_for_goal_selection():
    """A rollout of many short episodes (here 3,000 of 2 steps) keeps each of them for goal selection."""
    episodes = Episodes(n_goals=2, raw_shape=(3,), raw_dtype=np.dtype(np.float32), goal_part_size=4)
    episodes.grow(1)
    for i in range(3000):
        episodes.states[0].extend([np.full(3, i, np.float32), np.full(3, i + 0.5, np.float32)])
        episodes.restart(0, recording=True)
    assert len(episodes.finished) == 3000
    assert episodes.finished[0][0, 0] == 0 and episodes.finished[-1][1, 0] == 2999.5  # the first and the last, in order
