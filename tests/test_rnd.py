"""The RND peer (benchmarks/peers/rnd.py): its reward on hand-made inputs, its normalisation, its training, and a
short PPO_RND run that reads the reward where PPO_GoCu reads r_gc."""

import numpy as np
import pytest
import torch as th
from conftest import load_script
from gymnasium import spaces

SPACE = spaces.Box(0, 255, (3, 8, 8), np.uint8)


@pytest.fixture(scope="module")
def rnd_mod():
    return load_script("rnd", "benchmarks/peers/rnd.py")


def frames(values):
    """One 3x8x8 frame per value, every pixel that value."""
    return np.stack([np.full(SPACE.shape, v, dtype=np.uint8) for v in values])


def test_reward_is_half_the_squared_error_on_clipped_normalised_observations(rnd_mod):
    rnd = rnd_mod.RND(SPACE, n_envs=2, feature_dim=16, seed=0)
    first = frames([0, 100])  # per pixel mean 50, std 50: normalised to -1 and +1
    raw, _ = rnd.step(first)
    x = th.tensor(np.stack([np.full(SPACE.shape, -1.0), np.full(SPACE.shape, 1.0)]), dtype=th.float32)
    with th.no_grad():
        expected = 0.5 * ((rnd.predictor(x) - rnd.target(x)) ** 2).sum(1).numpy()
    np.testing.assert_allclose(raw, expected, rtol=1e-5)
    assert np.all(raw > 0)
    # a frame far outside the statistics is clipped at 5 std
    rnd.obs_stats.mean.fill_(0.0), rnd.obs_stats.var.fill_(1.0)
    assert rnd.normalize(frames([255, 3])).max().item() == pytest.approx(5.0)
    assert rnd.normalize(frames([255, 3]))[1].min().item() == pytest.approx(3.0)


def test_a_predictor_equal_to_the_target_pays_nothing(rnd_mod):
    rnd = rnd_mod.RND(SPACE, n_envs=2, feature_dim=16, seed=0)
    rnd.predictor = rnd_mod._conv_net(3, 8, 16, extra_layers=0)
    rnd.predictor.load_state_dict(rnd.target.state_dict())
    raw, normalized = rnd.step(frames([10, 200]))
    np.testing.assert_array_equal(raw, [0.0, 0.0])
    np.testing.assert_array_equal(normalized, [0.0, 0.0])


def test_reward_is_divided_by_the_std_of_discounted_intrinsic_returns(rnd_mod):
    rnd = rnd_mod.RND(SPACE, n_envs=2, feature_dim=16, intrinsic_gamma=0.5, seed=0)
    returns, seen = np.zeros(2), []
    for values in ([0, 100], [30, 60], [90, 10]):
        raw, normalized = rnd.step(frames(values))
        returns = 0.5 * returns + raw.astype(np.float64)  # the forward filter, per env
        seen.extend(returns)
        np.testing.assert_allclose(normalized, raw / np.sqrt(np.var(seen) + 1e-8), rtol=1e-4)


def test_training_lowers_the_error_on_what_was_seen(rnd_mod):
    rnd = rnd_mod.RND(SPACE, n_envs=4, feature_dim=16, learning_rate=1e-3, epochs=20, batch_size=4, seed=0)
    obs = frames([0, 80, 160, 240])
    before, _ = rnd.step(obs)
    loss = rnd.train_predictor()
    assert rnd.rollout == []
    with th.no_grad():
        after = rnd.prediction_error(rnd.normalize(obs)).numpy()
    assert np.isfinite(loss) and after.sum() < 0.5 * before.sum()


def test_bad_settings_raise_with_the_name(rnd_mod):
    with pytest.raises(ValueError, match="batch_size must be an integer >= 1"):
        rnd_mod.RND(SPACE, n_envs=2, batch_size=0)
    with pytest.raises(ValueError, match="intrinsic_gamma must be in"):
        rnd_mod.RND(SPACE, n_envs=2, intrinsic_gamma=1.5)
    with pytest.raises(ValueError, match="channel-first image"):
        rnd_mod.RND(spaces.Box(0, 1, (4,)), n_envs=2)
    with pytest.raises(ValueError, match="one observation per env"):
        rnd_mod.RND(SPACE, n_envs=2).step(frames([1]))


def test_ppo_rnd_learns_from_the_rnd_stream_and_resumes(rnd_mod, tmp_path):
    from stable_baselines3.common.env_util import make_vec_env

    model = rnd_mod.PPO_RND("CnnPolicy", make_vec_env("GoCu/DoorKey-5x5-v0", n_envs=2, seed=0), n_steps=64, batch_size=64, seed=0)
    assert model.curiosity is None and isinstance(model.env, rnd_mod.RNDVecEnvWrapper)
    weights = [p.detach().clone() for p in model.rnd.predictor.parameters()]
    model.learn(256)
    buffer = model.rollout_buffer
    assert np.all(buffer.intrinsic_rewards > 0)  # the RND stream reached the second value head
    assert any(not th.equal(a, b) for a, b in zip(weights, model.rnd.predictor.parameters()))  # the predictor trained
    model.save(tmp_path / "m.zip")
    loaded = rnd_mod.PPO_RND.load(tmp_path / "m.zip", env=make_vec_env("GoCu/DoorKey-5x5-v0", n_envs=2, seed=1))
    for a, b in zip(model.rnd.state_dict().values(), loaded.rnd.state_dict().values()):
        assert th.equal(a.cpu(), b.cpu())
    assert loaded.rnd.obs_stats.count.item() == model.rnd.obs_stats.count.item() > 0
