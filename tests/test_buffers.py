"""GAE of both streams and the combined advantage against a plain reference loop, and the rollout's
time-limit bootstrap of both value heads."""

import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.env_util import make_vec_env

from sb3_gocu import PPO_GoCu
from sb3_gocu.buffers import GoCuRolloutBuffer

from conftest import SMALL_CURIOSITY, ChainEnv


def reference_returns(rewards, values, dones_after, last_values, gamma, lam):
    """Per env, walking back in time: done_after[t] says the episode ended after step t."""
    n_steps, n_envs = rewards.shape
    adv = np.zeros_like(rewards)
    for e in range(n_envs):
        gae = 0.0
        for t in reversed(range(n_steps)):
            next_value = last_values[e] if t == n_steps - 1 else values[t + 1, e]
            alive = 0.0 if dones_after[t, e] else 1.0
            delta = rewards[t, e] + gamma * next_value * alive - values[t, e]
            gae = delta + gamma * lam * alive * gae
            adv[t, e] = gae
    return adv


def test_gae_both_streams_and_combined_advantage():
    rng = np.random.default_rng(0)
    n_steps, n_envs = 7, 3
    obs_space, act_space = spaces.Box(-1, 1, (2,), np.float32), spaces.Discrete(2)
    buf = GoCuRolloutBuffer(n_steps, obs_space, act_space, gae_lambda=0.9, gamma=0.97, n_envs=n_envs,
                            intrinsic_gamma=0.8, intrinsic_coef=0.25, intrinsic_episodic=True)
    # env 0: terminal after step 2; env 1: time-limit truncation after step 4 (its bootstrap is already in
    # the reward, as collect_rollouts adds it); env 2: no episode end; env 0 also ends at the last step
    dones_after = np.zeros((n_steps, n_envs), bool)
    dones_after[2, 0] = dones_after[4, 1] = dones_after[6, 0] = True
    r_e = rng.normal(size=(n_steps, n_envs)).astype(np.float32)
    r_i = rng.normal(size=(n_steps, n_envs)).astype(np.float32)
    v = rng.normal(size=(n_steps, n_envs, 2)).astype(np.float32)
    starts = np.zeros(n_envs, bool)
    for t in range(n_steps):
        buf.add(np.zeros((n_envs, 2), np.float32), np.zeros((n_envs, 1)), r_e[t], starts, th.from_numpy(v[t]),
                th.zeros(n_envs), intrinsic_reward=r_i[t])
        starts = dones_after[t]
    last_v = rng.normal(size=(n_envs, 2)).astype(np.float32)
    buf.compute_returns_and_advantage(th.from_numpy(last_v), dones=dones_after[-1])

    adv_e = reference_returns(r_e, v[..., 0], dones_after, last_v[:, 0], 0.97, 0.9)
    adv_i = reference_returns(r_i, v[..., 1], dones_after, last_v[:, 1], 0.8, 0.9)
    assert np.allclose(buf.extrinsic_advantages, adv_e, atol=1e-5)
    assert np.allclose(buf.intrinsic_advantages, adv_i, atol=1e-5)
    assert np.allclose(buf.advantages, adv_e + 0.25 * adv_i, atol=1e-5)
    assert np.allclose(buf.returns, adv_e + v[..., 0], atol=1e-5)
    assert np.allclose(buf.intrinsic_returns, adv_i + v[..., 1], atol=1e-5)

    # samples carry both value targets, interleaved [e, gc] per row like the critic's flattened output
    sample = next(buf.get(batch_size=None))
    flat_ret = np.stack([buf.returns, buf.intrinsic_returns], -1)  # already flattened by get()
    assert sample.returns.shape == (2 * n_steps * n_envs,)
    assert sample.advantages.shape == (n_steps * n_envs,)
    assert set(np.round(sample.returns.numpy(), 4)) == set(np.round(flat_ret.reshape(-1), 4))


def test_non_episodic_curiosity_stream_ignores_episode_ends():
    n_steps = 4
    buf = GoCuRolloutBuffer(n_steps, spaces.Box(-1, 1, (1,)), spaces.Discrete(2), gae_lambda=1.0, gamma=0.5, n_envs=1,
                            intrinsic_gamma=0.5, intrinsic_coef=1.0, intrinsic_episodic=False)
    starts = np.array([False])
    for t in range(n_steps):
        buf.add(np.zeros((1, 1)), np.zeros((1, 1)), np.zeros(1), starts, th.zeros(1, 2), th.zeros(1), intrinsic_reward=np.ones(1))
        starts = np.array([t == 1])  # an episode ends after step 1
    buf.compute_returns_and_advantage(th.zeros(1, 2), dones=np.array([False]))
    # intrinsic returns run through the episode end: 1 + .5 + .25 + .125, ...
    assert buf.intrinsic_returns[:, 0].tolist() == pytest.approx([1.875, 1.75, 1.5, 1.0])


@pytest.mark.parametrize("episodic", [True, False])
def test_rollout_bootstraps_both_heads_on_truncation(episodic):
    env = make_vec_env(lambda: ChainEnv(length=50, max_steps=3), n_envs=1, seed=0)
    # learning_rate=0 keeps the critic as it was during the rollout, so the bootstrap can be recomputed
    model = PPO_GoCu("MlpPolicy", env, n_steps=6, batch_size=6, n_epochs=1, seed=0, gamma=0.9, learning_rate=0.0, intrinsic_episodic=episodic,
                     curiosity_kwargs={**SMALL_CURIOSITY, "intrinsic_gamma": 0.7, "pretrain_steps": 0})
    infos_log = []
    original_step = model.env.step_wait

    def step_spy():
        out = original_step()
        infos_log.append(out[3])  # the dicts themselves: gocu_* entries arrive a step later
        return out

    model.env.step_wait = step_spy
    model.learn(6)
    buf = model.rollout_buffer
    seen = [(buf.rewards[t], buf.intrinsic_rewards[t]) for t in range(6)]
    # steps 3 and 6 end in a truncation (max_steps=3, the chain is too long to finish)
    for t in (2, 5):
        info = infos_log[t][0]
        assert info["TimeLimit.truncated"]
        with th.no_grad():
            v = model.policy.predict_values(model.policy.obs_to_tensor(info["terminal_observation"])[0])[0]
        r_e, r_i = seen[t]
        assert r_e[0] == pytest.approx(info["extrinsic_reward"] + 0.9 * v[0].item(), abs=1e-6)
        # an episodic curiosity stream bootstraps its own head with its own discount; a non-episodic one
        # runs on into the next episode and needs no bootstrap
        bootstrap = 0.7 * v[1].item() if episodic else 0.0
        assert r_i[0] == pytest.approx(info["gocu_reward"] + bootstrap, abs=1e-6)
        assert abs(v[1].item()) > 1e-4  # the curiosity head's bootstrap is a real term
    for t in (0, 1, 3, 4):
        r_e, r_i = seen[t]
        assert r_e[0] == infos_log[t][0]["extrinsic_reward"]
        assert r_i[0] == pytest.approx(infos_log[t][0]["gocu_reward"])
