"""Memoised scoring (:class:`~sb3_gocu.curiosity.scoring.Scorer`): the memos change the cost of a reward, never its value."""

import numpy as np
from gymnasium import spaces

from sb3_gocu import GoalCuriosityModule

from conftest import SMALL_CURIOSITY

SPACE = spaces.Box(0, 255, (16, 16, 3), np.uint8)


def test_memoised_rewards_equal_fresh_scoring_across_updates():
    """Frames from a pool of 12, so that states recur within episodes (reward memo) and across envs and episodes (phi
    memo), and two envs often meet the same new frame in one step: each step's raw r_gc equals the fresh score of its
    batch (no memo), before and after a predictor and a VAE update."""
    module = GoalCuriosityModule(SPACE, **SMALL_CURIOSITY, revisit_decay="none", seed=3)
    module.recording = True
    module.pretrain()
    rng = np.random.default_rng(0)
    pool = rng.integers(0, 256, (12, 16, 16, 3), dtype=np.uint8)
    frames = pool[rng.integers(0, len(pool), (120, 3))]
    dones = rng.random((120, 3)) < 0.08
    rewards = []
    for t, (f, d) in enumerate(zip(frames, dones)):
        if t == 30:
            module.add_finished_episode_goals()
            module.begin_episodes(np.arange(3))
        if t == 60:
            module.train_predictor()
            module.train_vae()
        fresh = module.score_states(f)
        raw, _ = module.step(f, d)
        np.testing.assert_allclose(raw, fresh, rtol=1e-5, atol=1e-7)
        rewards.append(raw)
    assert module.scorer.cache_hits > 100 and len(module.scorer.phi_memo) <= len(pool)
    assert len(np.unique(np.concatenate(rewards[30:]))) > 5  # the rewards vary: a constant would match trivially
