"""GoCuCallback: the learning side of goal-based curiosity as a Stable-Baselines3 callback (Alg. 1, lines
1-2 and 20-21, section 4.2.3)."""

from __future__ import annotations

import time
from typing import Any

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback

from sb3_gocu.curiosity import GoalCuriosityModule
from sb3_gocu.wrappers import GoCuVecEnvWrapper, GoCuWrapper, find_gocu_module


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
        """Random-policy observations -> VAE pretraining and first goals (Alg. 1, lines 1-2)."""
        assert self.module is not None
        t0 = time.perf_counter()
        env = self.training_env
        n_steps = -(-self.module.config.pretrain_steps // env.num_envs)
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
        self.module.collect_all()
        self.module.sample_goals(np.arange(self.module.n_envs))
        self.pretrain_time = time.perf_counter() - t0
        if self.verbose:
            print(
                f"GoCu: pretrained the VAE on {bank_size} random-policy observations "
                f"({stats.get('vae_distinct_observations', 0):.0f} distinct) in {self.pretrain_time:.1f} s; "
                f"{self.module.goal_buffer.size} goals"
            )

    def _on_step(self) -> bool:
        return True

    def _on_rollout_end(self) -> None:
        assert self.module is not None
        stats: dict[str, Any] = self.module.maybe_train()
        if self.verbose and ("vae_loss" in stats or "predictor_loss" in stats):
            shown = {k: round(v, 4) for k, v in stats.items() if k in ("vae_loss", "predictor_loss", "predictor_accuracy", "mastered_fraction")}
            print(f"GoCu update at {self.num_timesteps} steps: {shown}")
        stats.update(self.module.pop_reward_stats())
        stats.update({k: v for k, v in self.module.stats.items() if k not in stats})
        names = {
            "reward_mean": "intrinsic_reward_mean",
            "reward_std": "intrinsic_reward_std",
            "time_inference": "time_inference_s",
            "time_training": "time_training_s",
            "vae_time": "vae_time_s",
            "predictor_time": "predictor_time_s",
        }
        for key, value in stats.items():
            self.logger.record(f"gocu/{names.get(key, key)}", value)
        self.logger.record("gocu/pretrain_time_s", self.pretrain_time)

    def _on_training_end(self) -> None:
        assert self.module is not None
        self.module.recording = False
