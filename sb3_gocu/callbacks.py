"""GoCuCallback: the learning side of goal-based curiosity as a Stable-Baselines3 callback (Alg. 1, lines
1-2 and 20-21, section 4.2.3)."""

from __future__ import annotations

import contextlib
import math
import time
import warnings
from typing import Any, Iterator

import gymnasium as gym
import numpy as np
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import DummyVecEnv, VecEnv, VecEnvWrapper

from sb3_gocu.curiosity import GoalCuriosityModule
from sb3_gocu.wrappers import GoCuVecEnvWrapper, GoCuWrapper, find_gocu_module


@contextlib.contextmanager
def monitors_paused(env: VecEnv) -> Iterator[None]:
    """Within the block, the ``Monitor`` wrappers of an in-process env (``DummyVecEnv``) write no episode and keep no
    count of the steps and episodes taken; afterwards they go on as before. Monitors in other processes cannot be
    reached: a warning says that their files will hold the block's episodes."""
    base: Any = env
    while isinstance(base, VecEnvWrapper):
        base = base.venv
    if not isinstance(base, DummyVecEnv):
        warnings.warn(f"GoCuCallback: the pretraining's random-policy episodes go into the Monitor files of this {type(base).__name__}")
        yield
        return
    found = []
    for e in base.envs:
        while isinstance(e, gym.Wrapper):
            if isinstance(e, Monitor):
                found.append(e)
            e = e.env
    saved = [(m.results_writer, list(m.episode_returns), list(m.episode_lengths), list(m.episode_times), m.total_steps) for m in found]
    for m in found:
        m.results_writer = None
    try:
        yield
    finally:
        for m, (writer, returns, lengths, times, steps) in zip(found, saved):
            m.results_writer, m.episode_returns, m.episode_lengths, m.episode_times, m.total_steps = writer, returns, lengths, times, steps


#: the module's running counts of its guards (``module.stats``), logged when they change
GUARD_COUNTERS = ("nonfinite_rewards", "vae_collapsed_updates", *(f"{net}_{name}" for net in ("vae", "predictor")
                                         for name in ("skipped_updates_total", "nonfinite_parameters", "restored_updates")))
#: logged names of the module's figures that differ from their keys
LOG_NAMES = {
    "reward_mean": "intrinsic_reward_mean",
    "reward_std": "intrinsic_reward_std",
    "time_inference": "time_inference_s",
    "vae_time": "vae_time_s",
    "predictor_time": "predictor_time_s",
    "pretrain_time": "pretrain_time_s",
}


class GoCuCallback(BaseCallback):
    """Trains the curiosity module of a GoCu-wrapped training env.

    * before the first rollout: steps the training env with a random policy for ``pretrain_steps``
      observations (the module's setting, default 10,000; not counted as training steps), pretrains the VAE
      on them, seeds the goal buffer from those episodes, then resets the env;
    * while training: the module records every observation (memory bank, trajectory store, episodes);
    * at each rollout end: adds l new goals from each finished episode, retrains the VAE every P_vae and
      the predictor every P_m recorded steps, and logs to the SB3 logger (``gocu/...``).

    :param gocu: the GoCu wrapper or module to train; default: found in the training env's wrapper stack
    :param verbose: 1 prints the curiosity updates
    """

    def __init__(self, gocu: GoCuVecEnvWrapper | GoCuWrapper | GoalCuriosityModule | None = None, verbose: int = 0) -> None:
        super().__init__(verbose)
        if gocu is not None and not isinstance(gocu, (GoCuVecEnvWrapper, GoCuWrapper, GoalCuriosityModule)):
            raise TypeError(f"gocu must be a GoCuVecEnvWrapper, a GoCuWrapper, a GoalCuriosityModule or None, got {type(gocu).__name__}")
        self.module: GoalCuriosityModule | None = gocu if isinstance(gocu, GoalCuriosityModule) or gocu is None else gocu.module
        self.pretrain_time = 0.0
        self._pretrain_logged = False
        self._counters: dict[str, float] = {}  # the module's guard counters as last logged

    def _init_callback(self) -> None:
        found = find_gocu_module(self.training_env)
        if self.module is None:
            if found is None:
                raise ValueError(
                    "GoCuCallback found no GoCuVecEnvWrapper or GoCuWrapper in the training env: wrap the env, "
                    "or pass the wrapper or module to GoCuCallback"
                )
            self.module = found[0]
        elif found is not None and found[0] is not self.module:
            raise ValueError("the module given to GoCuCallback is not the one of the training env's GoCu wrapper")

    def _on_training_start(self) -> None:
        assert self.module is not None
        self.module.recording = True
        if not self.module.pretrained:
            self._pretrain()

    def _pretrain(self) -> None:
        """Random-policy observations -> VAE pretraining and first goals (Alg. 1, lines 1-2). These steps are not
        training steps: they are not counted in ``num_timesteps`` nor in ``time/fps``, and the Monitor wrappers of an
        in-process env neither write nor count their episodes."""
        assert self.module is not None
        t0 = time.perf_counter()
        env = self.training_env
        n_steps = -(-self.module.config.pretrain_steps // env.num_envs)
        with monitors_paused(env):
            if n_steps > 0:
                env.reset()
                for _ in range(n_steps):
                    env.step(np.array([self.model.action_space.sample() for _ in range(env.num_envs)]))
                    self.module.add_finished_episode_goals()
            stats = self.module.pretrain()
            bank_size = self.module.memory.size  # what the VAE was pretrained on (the reset below records more)
            # the reset closes the random episodes still running (on large grids none has ended yet): their states
            # become goals too, embedded by the pretrained VAE, and every env then draws its first K goals
            self.model._last_obs = env.reset()  # type: ignore[assignment]
        self.model._last_episode_starts = np.ones((env.num_envs,), dtype=bool)
        self.module.add_finished_episode_goals()
        self.module.sample_goals(np.arange(self.module.n_envs))
        self.pretrain_time = time.perf_counter() - t0
        self.model.start_time += int(self.pretrain_time * 1e9)  # time/fps counts the training steps' time alone
        if self.verbose:
            print(
                f"GoCu: pretrained the VAE on {bank_size} random-policy observations "
                f"({stats.get('vae_observations', 0):.0f} {'distinct' if self.module.config.vae_dedupe else 'trained on'}) "
                f"in {self.pretrain_time:.1f} s; "
                f"{self.module.goal_buffer.size} goals; revisit cell {self.module.revisit_key.describe()} (first-visit share "
                f"{stats.get('revisit_share', float('nan')):.3f} on those episodes)"
            )

    def _on_step(self) -> bool:
        return True

    def _on_rollout_end(self) -> None:
        assert self.module is not None
        stats: dict[str, Any] = self.module.maybe_train()  # the figures of the updates run now, if any
        if self.verbose and ("vae_loss" in stats or "predictor_loss" in stats):
            shown = {k: round(v, 4) for k, v in stats.items() if k in ("vae_loss", "predictor_loss", "predictor_accuracy", "mastered_fraction")}
            print(f"GoCu update at {self.num_timesteps} steps: {shown}")
        stats.update(self.module.pop_reward_stats())
        counters = {k: v for k, v in self.module.stats.items() if k in GUARD_COUNTERS and self._counters.get(k) != v}
        self._counters.update(counters)
        stats.update(counters)  # the guards' running counts, when they changed
        if self.pretrain_time and not self._pretrain_logged:
            stats["pretrain_time"] = self.pretrain_time
            self._pretrain_logged = True
        for key, value in stats.items():
            if math.isfinite(value):  # a figure that was not measured (e.g. no held-out loss) is not logged
                self.logger.record(f"gocu/{LOG_NAMES.get(key, key)}", value)
        episodes = [ep["gocu_r"] for ep in self.model.ep_info_buffer if "gocu_r" in ep]
        if episodes:
            self.logger.record("rollout/ep_intrinsic_rew_mean", float(np.mean(episodes)))

    def _on_training_end(self) -> None:
        assert self.module is not None
        self.module.recording = False
