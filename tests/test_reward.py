"""The reward formulas (eq 13-16) and the fast predictor path against numbers computed by hand."""

import copy
import math

import numpy as np
import pytest
import torch as th
from gymnasium import spaces

from sb3_gocu.curiosity import (
    GoalCuriosityModule,
    IntrinsicReturnNormalizer,
    MasteryPredictor,
    RunningMean,
    complexity_score,
    curiosity_reward,
    mastered_probability,
    mastery_loss,
    revisit_factor,
)


def sigmoid(x):
    return 1 / (1 + math.exp(-x))


def tiny_predictor() -> MasteryPredictor:
    """embed_dim 1, one hidden unit: logit_1 - logit_0 = 2 * relu(0.5 s + 0.25 g) - 1 (BN is the identity)."""
    p = MasteryPredictor(embed_dim=1, hidden_sizes=(1,))
    lin, bn = p.hidden[0], p.hidden[1]
    with th.no_grad():
        lin.weight[:] = th.tensor([[0.5, 0.25]])
        lin.bias[:] = 0.0
        bn.weight[:] = 1.0
        bn.bias[:] = 0.0
        bn.running_mean[:] = 0.0
        bn.running_var[:] = 1.0
        bn.eps = 0.0
        p.out.weight[:] = th.tensor([[0.0], [2.0]])
        p.out.bias[:] = th.tensor([0.0, -1.0])
    return p.eval()


def test_tiny_predictor_by_hand():
    p = tiny_predictor()
    s = th.tensor([[1.0], [2.0], [-4.0]])
    g = th.tensor([[2.0], [0.0], [1.0]])
    # hidden = relu(0.5 s + 0.25 g): 1.0, 1.0, 0.0 -> logit difference 1, 1, -1
    expected = [sigmoid(1.0), sigmoid(1.0), sigmoid(-1.0)]
    assert p.mastery(s, g).tolist() == pytest.approx(expected, abs=1e-6)
    assert p.fold().mastery(s, g).tolist() == pytest.approx(expected, abs=1e-6)


def test_folded_predictor_equals_eval_module():
    th.manual_seed(0)
    p = MasteryPredictor(embed_dim=16, hidden_sizes=(64, 64, 64))
    p.train()
    for _ in range(3):  # give batch norm non-trivial running statistics
        p(th.randn(32, 16) * 3 + 1, th.randn(32, 16))
    p.eval()
    s, g = th.randn(5, 16), th.randn(5, 7, 16)
    folded = p.fold()
    fast = folded.mastery_from_parts(folded.state_part(s), folded.goal_part(g))
    slow = p.mastery(s[:, None].expand(5, 7, 16).reshape(-1, 16), g.reshape(-1, 16)).view(5, 7)
    assert fast.shape == (5, 7)
    assert th.allclose(fast, slow, atol=1e-6)


def test_curiosity_reward_eq13_by_hand():
    m = th.tensor([[0.2, 0.9, 0.5], [0.1, 0.1, 0.4]])
    assert curiosity_reward(m, alpha=1.0, aggregation="max", scale=10.0).tolist() == pytest.approx([0.01, 0.06])
    assert curiosity_reward(m, alpha=1.0, aggregation="mean", scale=10.0).tolist() == pytest.approx([(1 - 1.6 / 3) / 10, 0.08])
    assert curiosity_reward(m[:, :0], 1.0, "max", 10.0).tolist() == pytest.approx([0.1, 0.1])  # no goal: h = 0
    with pytest.raises(ValueError, match="aggregation"):
        curiosity_reward(m, aggregation="min")


def test_module_scores_envs_with_and_without_goals_in_one_batch():
    """score_states on a batch mixing envs that have goals and envs that have none yet: alpha / delta for the latter,
    eq 13 over the env's own K goals for the former (against the unfolded predictor)."""
    space = spaces.Box(0, 255, (8, 8, 3), np.uint8)
    module = GoalCuriosityModule(space, n_goals=3, goal_buffer_size=10, embed_dim=4, latent_dim=2, predictor_hidden=(8, 8), seed=0)
    module.ensure_envs(3)
    rng = np.random.default_rng(0)
    goals = rng.integers(0, 256, (5, 8, 8, 3), dtype=np.uint8)
    assert module.goal_buffer.add(goals, module.embed(goals), rng) == 5
    module.sample_goals(np.array([0, 2]))  # env 1 keeps no goals
    assert module.episodes.has_goals.tolist() == [True, False, True]
    states = rng.integers(0, 256, (3, 8, 8, 3), dtype=np.uint8)
    got = module.score_states(states)
    with th.no_grad():
        for e in range(3):
            if e == 1:
                assert got[e] == pytest.approx(module.alpha / module.reward_scale)
                continue
            phi_s, phi_g = module.embed(states[e : e + 1]), module.embed(module.episodes.goal_obs[e])
            h = copy.deepcopy(module.predictor).eval().mastery(phi_s.expand(3, -1), phi_g).max()
            assert got[e] == pytest.approx(float((module.alpha - h) / module.reward_scale), abs=1e-6)
    assert np.array_equal(module.score_states(states[[0, 2]], np.array([0, 2])), got[[0, 2]])


def test_labels_eq15_eq16_by_hand():
    prior = th.tensor([0.0, 0.5, 1.0])
    dist = th.tensor([3.0, 15.0, 30.0])
    sc = complexity_score(prior, dist, prior_weight=3.0, distance_weight=1.0)
    assert sc.tolist() == pytest.approx([3.0, 16.5, 33.0])
    p = mastered_probability(sc, threshold=15.0, slope=0.8)
    expected = [1 - 1 / (1 + math.exp(-0.8 * (x - 15.0))) for x in (3.0, 16.5, 33.0)]
    assert p.tolist() == pytest.approx(expected, abs=1e-6)
    assert expected[0] > 0.99 and expected[2] < 1e-5  # near skills are mastered, far ones are not


def test_mastery_loss_by_hand():
    """The predictor's loss: weighted mean cross-entropy of softmax(logits)[1] against the targets."""
    logits = th.tensor([[0.0, 1.0], [2.0, 0.0], [0.0, 0.0]])
    target = th.tensor([1.0, 0.25, 0.5])
    # p(mastered) = sigmoid(logit_1 - logit_0): sigmoid(1), sigmoid(-2), 1/2
    ll = [math.log(sigmoid(1.0)), 0.25 * math.log(sigmoid(-2.0)) + 0.75 * math.log(sigmoid(2.0)), math.log(0.5)]
    loss, logp = mastery_loss(logits, target)
    assert loss.item() == pytest.approx(-sum(ll) / 3, abs=1e-6)
    assert logp[:, 1].exp().tolist() == pytest.approx([sigmoid(1.0), sigmoid(-2.0), 0.5], abs=1e-6)
    weights = th.tensor([2.0, 0.5, 0.5])  # mean 1, as the module's de-duplicated draws
    assert mastery_loss(logits, target, weights)[0].item() == pytest.approx(-(2 * ll[0] + 0.5 * ll[1] + 0.5 * ll[2]) / 3, abs=1e-6)
    assert mastery_loss(logits, target, th.ones(3))[0].item() == loss.item()  # unit weights: the unweighted loss


def test_normalizer_eq14_by_hand():
    norm = IntrinsicReturnNormalizer(gamma=0.5, epsilon=0.0)
    norm.ensure_envs(2)
    envs = np.arange(2)
    out1 = norm(np.array([1.0, 3.0]), envs)
    # returns [1, 3]; running stats from (count 1e-4, mean 0, var 1) merged with batch (mean 2, var 1)
    c = 1e-4
    mean1 = 2 * 2 / (c + 2)
    var1 = (1 * c + 1 * 2 + 4 * c * 2 / (c + 2)) / (c + 2)
    assert out1 == pytest.approx(np.array([1.0, 3.0]) / math.sqrt(var1), rel=1e-6)
    out2 = norm(np.array([0.0, 1.0]), envs)
    # returns now [0.5, 2.5]: batch mean 1.5, var 1
    total = c + 4
    delta = 1.5 - mean1
    var2 = (var1 * (c + 2) + 1 * 2 + delta**2 * (c + 2) * 2 / total) / total
    assert out2 == pytest.approx(np.array([0.0, 1.0]) / math.sqrt(var2), rel=1e-6)
    # evaluation does not move the statistics
    assert norm(np.array([1.0, 1.0]), envs, update=False) == pytest.approx(np.array([1.0, 1.0]) / math.sqrt(var2), rel=1e-6)


def test_module_reward_path_by_hand():
    """The module's whole step (goal halves, folding, cache) against the tiny predictor by hand."""
    space = spaces.Box(-10, 10, (1,), np.float32)
    # revisit_decay="none": eq 13 on every visit, so the memoised value is paid again
    mod = GoalCuriosityModule(space, n_goals=2, goal_buffer_size=2, embed_dim=1, predictor_hidden=(1,), seed=0, goal_novelty=0.0,
                              revisit_decay="none")
    mod.vae.embed = lambda x: x  # phi(s) = s, so the numbers stay hand-made
    mod.predictor.load_state_dict(tiny_predictor().state_dict())
    mod.predictor.hidden[1].eps = 0.0  # as tiny_predictor's (not in a state dict)
    mod.refresh()  # inference embeds with a frozen copy of the VAE, and scores with the folded predictor
    goals = np.array([[2.0], [-4.0]], dtype=np.float32)
    assert mod.goal_buffer.add(goals, th.from_numpy(goals), mod.rng) == 2
    mod.ensure_envs(2)
    mod.begin_episodes(np.arange(2))
    raw, normalized = mod.step(np.array([[1.0], [-2.0]], dtype=np.float32), np.zeros(2, bool))
    # env 0, s = 1: hidden relu(0.5 + 0.5) = 1 -> m = sig(1); relu(0.5 - 1) = 0 -> m = sig(-1); h = max = sig(1)
    # env 1, s = -2: relu(-1 + 0.5) = 0, relu(-1 - 1) = 0 -> both sig(-1)
    assert raw.tolist() == pytest.approx([(1 - sigmoid(1)) / 10, (1 - sigmoid(-1)) / 10], abs=1e-6)
    assert normalized.tolist() == pytest.approx((raw / mod.normalizer.std).tolist(), abs=1e-6)
    # the same state again in the same episode comes from the cache, with the same value
    raw2, _ = mod.step(np.array([[1.0], [-2.0]], dtype=np.float32), np.zeros(2, bool))
    assert raw2.tolist() == raw.tolist()
    assert mod.pop_reward_stats()["cache_hit_rate"] == pytest.approx(0.5)


def test_revisit_factor_by_hand():
    visits = np.array([1, 2, 4, 9])
    assert revisit_factor(visits, "none").tolist() == [1.0, 1.0, 1.0, 1.0]
    assert revisit_factor(visits, "inverse_sqrt").tolist() == pytest.approx([1.0, 1 / math.sqrt(2), 0.5, 1 / 3])
    assert revisit_factor(visits, "first_visit").tolist() == [1.0, 0.0, 0.0, 0.0]
    with pytest.raises(ValueError, match=r"revisit_decay must be one of \('none', 'inverse_sqrt', 'first_visit'\), got 'half'"):
        revisit_factor(visits, "half")
    with pytest.raises(ValueError, match="visits must be >= 1"):
        revisit_factor(np.array([0]), "none")


@pytest.mark.parametrize("decay", ["inverse_sqrt", "first_visit"])
def test_module_pays_revisits_within_an_episode_by_the_decay(decay):
    """The n-th visit of a state in an episode pays eq 13 x the revisit factor; a new episode counts from 1 again,
    and the counts are per env."""
    space = spaces.Box(-10, 10, (1,), np.float32)
    mod = GoalCuriosityModule(space, n_goals=1, goal_buffer_size=1, embed_dim=1, predictor_hidden=(1,), seed=0, revisit_decay=decay)
    mod.vae.embed = lambda x: x
    mod.predictor.load_state_dict(tiny_predictor().state_dict())
    mod.predictor.hidden[1].eps = 0.0  # as tiny_predictor's (not in a state dict)
    mod.refresh()
    goal = np.array([[2.0]], dtype=np.float32)
    mod.goal_buffer.add(goal, th.from_numpy(goal), mod.rng)
    mod.ensure_envs(2)
    mod.begin_episodes(np.arange(2))
    r = (1 - sigmoid(1)) / 10  # s = 1 against g = 2: m = sig(1)
    a, b = np.array([[1.0], [1.0]], dtype=np.float32), np.array([[-2.0], [1.0]], dtype=np.float32)
    paid = [mod.step(x, np.array([False, False]))[0] for x in (a, a, b, a)]
    factor = {"inverse_sqrt": lambda n: 1 / math.sqrt(n), "first_visit": lambda n: float(n == 1)}[decay]
    # env 0 sees s = 1 at visits 1, 2, then s = -2, then s = 1 a third time; env 1 sees s = 1 four times
    assert [p[0] for p in paid[:2]] + [paid[3][0]] == pytest.approx([r * factor(1), r * factor(2), r * factor(3)], abs=1e-7)
    assert [p[1] for p in paid] == pytest.approx([r * factor(n) for n in (1, 2, 3, 4)], abs=1e-7)
    # the episode of env 0 ends on this step (visit 4 of s = 1); the next one counts from 1 again
    last, _ = mod.step(a, np.array([True, False]))
    assert last[0] == pytest.approx(r * factor(4), abs=1e-7)
    again, _ = mod.step(a, np.array([False, False]))
    assert again[0] == pytest.approx(r, abs=1e-7) and again[1] == pytest.approx(r * factor(6), abs=1e-7)


@pytest.mark.parametrize("shape", [(32, 32, 3), (3, 32, 32), (21, 21)])
def test_numpy_to_tensor_equals_the_torch_path_to_the_bit(shape):
    """ObservationAdapter.to_tensor converts numpy batches in numpy (no GIL round trips in the scoring worker):
    the same float tensor, layout and contiguity as the torch path it replaces."""
    from sb3_gocu.curiosity.observations import ObservationAdapter

    adapter = ObservationAdapter(spaces.Box(0, 255, shape, np.uint8))
    raw = np.random.default_rng(0).integers(0, 256, (4, *shape), dtype=np.uint8)
    got, ref = adapter.to_tensor(raw), adapter.to_tensor(th.from_numpy(raw))
    assert got.dtype == th.float32 and got.is_contiguous() and got.shape == ref.shape == (4, *((1, *shape) if len(shape) == 2 else (3, 32, 32)))
    assert th.equal(got, ref)
    assert float(got.max()) <= 1.0 and float(got.max()) > 0.9


@pytest.mark.parametrize("layout", ["chw", "hwc", "hw"])
def test_large_images_are_kept_as_block_means(layout):
    """Images longer than MAX_IMAGE_SIDE (64) a side: GoCu keeps and embeds them averaged over f x f blocks (uint8
    means rounded; Atari's 84x84: f = 2, 42x42), newest channel only where image_channels says so; the module's VAE
    and buffers take the smaller frames. 32x32 and 64x64 images are kept whole."""
    from sb3_gocu.curiosity.observations import ObservationAdapter

    shape = {"chw": (4, 84, 84), "hwc": (84, 84, 4), "hw": (84, 84)}[layout]
    channels = None if layout == "hw" else 1
    adapter = ObservationAdapter(spaces.Box(0, 255, shape, np.uint8), image_channels=channels)
    assert adapter.image_downsample == 2 and adapter.input_shape == (1, 42, 42)
    obs = np.random.default_rng(0).integers(0, 256, (3, *shape), dtype=np.uint8)
    newest = obs[:, -1] if layout == "chw" else obs[..., -1] if layout == "hwc" else obs
    block = newest[:, 4:6, 10:12].astype(np.float64).mean(axis=(1, 2))  # the block at (2, 5) of the 42x42 frame
    kept = adapter.extract(obs)
    assert kept.dtype == np.uint8 and kept.shape == (3, *adapter.raw_shape)
    kept_2d = kept[:, 0] if layout == "chw" else kept[..., 0] if layout == "hwc" else kept
    assert np.array_equal(kept_2d[:, 2, 5], np.rint(block).astype(np.uint8))
    mod = GoalCuriosityModule(spaces.Box(0, 255, shape, np.uint8), image_channels=channels, n_goals=2, goal_buffer_size=8,
                              predictor_hidden=[16], pretrain_steps=0, memory_size=64)
    assert mod.vae.input_shape == (1, 42, 42)
    mod.recording = True
    raw, _ = mod.step(obs[:2], np.array([False, False]))
    assert raw.shape == (2,) and mod.memory.size == 2 and mod.memory.observations.shape[1:] == adapter.raw_shape
    for side, f in ((32, 1), (64, 1), (65, 2), (210, 4)):
        assert ObservationAdapter(spaces.Box(0, 255, (side, side, 3), np.uint8)).image_downsample == f
    with pytest.raises(ValueError, match="a 300x2 image would keep no pixel"):
        ObservationAdapter(spaces.Box(0, 255, (300, 2), np.uint8))


def test_running_mean_is_the_plain_mean_then_an_average_over_its_horizon():
    rm = RunningMean(horizon=4)
    rm.update(np.array([1.0, 3.0]))
    assert rm.mean == 2.0 and rm.count == 2
    rm.update(np.array([5.0]))
    assert rm.mean == 3.0  # (1 + 3 + 5) / 3
    rm.update(np.array([7.0, 9.0]))  # full: 2 of 4 weight on the batch's mean 8
    assert rm.mean == pytest.approx(3.0 + 0.5 * (8.0 - 3.0))
    rm.update(np.array([], dtype=np.float32))
    assert rm.count == 5
    with pytest.raises(ValueError, match="horizon"):
        RunningMean(0)
