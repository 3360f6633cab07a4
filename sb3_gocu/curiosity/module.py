"""GoalCuriosityModule: the goal-based curiosity module (GCM) of the paper, Fig. 3, on tensors alone.

One object holds everything GoCu learns and remembers: the VAE and the mastery predictor with their optimisers
(:class:`~sb3_gocu.curiosity.training.Trainer`), the goal buffer, the memory bank, the trajectory store of
training pairs, the intrinsic-return normaliser, each env's episode (:class:`~sb3_gocu.curiosity.episodes.Episodes`)
and the random generators. Wrappers feed it batches of observations (:meth:`GoalCuriosityModule.step`); a callback
tells it when to learn (:meth:`~GoalCuriosityModule.pretrain` and :meth:`~GoalCuriosityModule.maybe_train`).

The reward of a state s in an episode with goals g_1..g_K (eq 13, 14)::

    m_k  = m(phi(s), phi(g_k))                  mastery predictor, eval mode
    r_gc = (alpha - h(m_1, ..., m_K)) / delta   h = max (paper) or mean
    r    = r_gc / std(intrinsic returns)

No Stable-Baselines3 import.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import math
import time
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces

from sb3_gocu.curiosity.checks import check, check_memory
from sb3_gocu.curiosity.config import DEFAULT_PIXEL_WEIGHTING, NEAR_DISTANCE, CuriosityConfig
from sb3_gocu.curiosity import persistence
from sb3_gocu.curiosity.episodes import Episodes
from sb3_gocu.curiosity.goals import GoalBuffer, select_goal_steps
from sb3_gocu.curiosity.networks import ConvVAE, MasteryPredictor, MlpVAE
from sb3_gocu.curiosity.observations import ObservationAdapter
from sb3_gocu.curiosity.reachability import PREDICTOR_HOLDOUT, QUALITY_KEYS, QualityPairs, reachability_pairs
from sb3_gocu.curiosity.revisits import Calibration, default_cell, first_cell
from sb3_gocu.curiosity.reward import IntrinsicReturnNormalizer, RunningMean, revisit_factor
from sb3_gocu.curiosity.scoring import Scorer, eq13_rows
from sb3_gocu.curiosity.stores import MemoryBank, TrajectoryStore, observation_key
from sb3_gocu.curiosity.training import (
    PredictorFit, PredictorJob, Trainer, VaeFit, VaeJob, guard_update,
)

#: keywords of earlier versions: experiments removed, or speed-ups now fixed (docs/results.md, "What was retired")
RETIRED = ("train_in_background", "predictor_lead", "update_threads", "vae_shards", "refit_predictor_after_vae", "train_dtype",
           "record_start_states", "split_updates", "queue_during_update", "overlap_ppo_update", "scoring_process", "scoring_dtype",
           "vae_holdout", "episode_memory", "vae_pretrain_patience", "soft_labels", "predictor_dedupe")
#: recorded steps the running mean of the normalised r_gc spans (``GoalCuriosityModule.reward_centre``): eight PPO rollouts
#: of 16 envs x 128 steps
CENTRE_HORIZON = 16_384


class GoalCuriosityModule:
    """Goal-based curiosity (GoCu) on batches of observations.

    :param observation_space: observation space of the (vectorised) environment
    :param device: torch device of the networks
    :param seed: seed of the module's random generators (the networks' initial weights depend on it alone)
    :param settings: the settings of :class:`~sb3_gocu.curiosity.config.CuriosityConfig`, by name (``n_goals``,
        ``goal_strategy``, ``reward_scale``, ...), each checked
    """

    def __init__(self, observation_space: spaces.Space, device: th.device | str = "cpu", seed: int | None = None, **settings: Any) -> None:
        retired = sorted(set(settings) & set(RETIRED))
        if retired:
            raise TypeError(f"GoalCuriosityModule: {retired} retired: removed or fixed behaviour (docs/results.md, 'What was retired, and why')")
        unknown = sorted(set(settings) - {f.name for f in dataclasses.fields(CuriosityConfig)})
        if unknown:
            raise TypeError(f"GoalCuriosityModule got unknown settings {unknown}; the settings are those of CuriosityConfig")
        self.config = cfg = CuriosityConfig(**settings)
        self.observation_space = observation_space
        self.adapter = ObservationAdapter(observation_space, obs_key=cfg.obs_key, image_channels=cfg.image_channels)
        self.device = th.device(device)
        check(not cfg.vae_pixel_weighting or self.adapter.is_image,
              f"vae_pixel_weighting applies to image observations, got {cfg.vae_pixel_weighting} with observations of shape {self.adapter.input_shape}")
        self._pixel_weighting_given = cfg.vae_pixel_weighting is not None
        default_weighting = DEFAULT_PIXEL_WEIGHTING if self.adapter.is_image else 0.0
        self.vae_pixel_weighting = float(default_weighting if cfg.vae_pixel_weighting is None else cfg.vae_pixel_weighting)

        self.rng = np.random.default_rng(seed)
        generator = th.Generator().manual_seed(int(self.rng.integers(2**62)))
        init_seed = int(self.rng.integers(2**62))
        with th.random.fork_rng(devices=[], enabled=seed is not None):  # with a seed, the weights depend on it alone
            if seed is not None:
                th.manual_seed(init_seed)
            vae_cls = ConvVAE if self.adapter.is_image else MlpVAE
            self.vae = vae_cls(self.adapter.input_shape, embed_dim=cfg.embed_dim, latent_dim=cfg.latent_dim).to(self.device)
            self.predictor = MasteryPredictor(cfg.embed_dim, cfg.predictor_hidden).to(self.device)
        self.trainer = Trainer(self.vae, self.predictor, cfg, self.adapter, self.device, generator)
        self.vae.eval()
        self.predictor.eval()

        raw_shape, raw_dtype = self.adapter.raw_shape, self.adapter.raw_dtype
        self._raw_bytes = int(np.prod(raw_shape)) * np.dtype(raw_dtype).itemsize
        check_memory({
            "memory bank": (f"memory_size={cfg.memory_size}", cfg.memory_size * self._raw_bytes),
            "goal buffer": (f"goal_buffer_size={cfg.goal_buffer_size}", cfg.goal_buffer_size * (self._raw_bytes + 4 * cfg.embed_dim + 16)),
            "trajectory store": (f"predictor_train_freq={cfg.predictor_train_freq}", cfg.predictor_train_freq * (4 * cfg.embed_dim + 8)),
            "pretraining's episodes": (f"pretrain_steps={cfg.pretrain_steps}", cfg.pretrain_steps * (self._raw_bytes + 8)),
        })
        self.goal_buffer = GoalBuffer(cfg.goal_buffer_size, raw_shape, raw_dtype, cfg.embed_dim, cfg.goal_novelty)
        self.memory = MemoryBank(cfg.memory_size, raw_shape, raw_dtype)
        self.normalizer = IntrinsicReturnNormalizer(cfg.intrinsic_gamma)
        #: running mean of the normalised r_gc over the recorded steps (about the last CENTRE_HORIZON): what the drop-in
        #: wrapper's sum subtracts, so that an episode is worth no more for being longer
        self.reward_centre = RunningMean(CENTRE_HORIZON)
        self.episodes, self.trajectories = self._new_env_stores()
        #: what counts as a revisit (``revisit_decay``): the cell of a state (:mod:`~sb3_gocu.curiosity.revisits`),
        #: chosen by :meth:`pretrain` from the random-policy episodes; until then the finest (revisits.first_cell)
        box = self.adapter.box
        self.revisit_key = first_cell(self.adapter.layout, self.adapter.scale, self.adapter.raw_shape, box.low, box.high)
        self._calibration = Calibration(cfg.pretrain_steps)
        to_tensor = functools.partial(self.adapter.to_tensor, device=self.device)
        self.scorer = Scorer(self.episodes, cfg.embed_dim, to_tensor, (cfg.alpha, cfg.aggregation, cfg.reward_scale))

        #: when True, :meth:`step` records observations (memory bank, trajectory store, episodes) and updates the
        #: normaliser; a training callback switches it on
        self.recording = False
        self.pretrained = False
        self.n_recorded_steps = 0
        self.last_vae_update = 0
        self.last_predictor_update = 0
        self.stats: dict[str, float] = {}
        self._reward_sums = [0.0, 0.0, 0]  # sum, sum of squares, count of the raw r_gc recorded since pop_reward_stats
        self._first_visits = [0, 0]  # recorded steps in a cell new to their episode, and recorded steps, since pop_reward_stats
        self._hits_at_pop = (0, 0)  # the scorer's (hits, lookups) at the last pop_reward_stats
        self.time_inference = 0.0  # cumulative seconds in the module's scoring calls
        self._inference_at_pop = 0.0  # time_inference at the last pop_reward_stats
        self.time_vae = 0.0
        self.time_predictor = 0.0
        self._folded = self.predictor.fold()
        self._encoder = self._frozen_encoder()

    def _default_cell(self) -> Any:
        box = self.adapter.box
        return default_cell(self.adapter.layout, self.adapter.scale, self.adapter.raw_shape, box.low, box.high)

    def _new_env_stores(self) -> tuple[Episodes, TrajectoryStore]:
        """Empty per-env stores, grown by :meth:`ensure_envs`: the episodes in progress and the training-pair store."""
        cfg = self.config
        episodes = Episodes(cfg.n_goals, self.adapter.raw_shape, self.adapter.raw_dtype, self.predictor.hidden[0].out_features)
        return episodes, TrajectoryStore(cfg.predictor_train_freq, cfg.embed_dim, min_per_env=2 * cfg.max_distance)

    def __getattr__(self, name: str) -> Any:
        """The settings read as attributes (``module.n_goals``)."""
        config = self.__dict__.get("config")
        if config is not None and name in CuriosityConfig.__dataclass_fields__:
            return getattr(config, name)
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    def __setattr__(self, name: str, value: Any) -> None:
        if name in CuriosityConfig.__dataclass_fields__ and name != "vae_pixel_weighting":  # that one: the exponent in use
            raise AttributeError(f"{name} is a setting, fixed at construction: build a new GoalCuriosityModule(..., {name}=...)")
        super().__setattr__(name, value)

    n_envs = property(lambda self: self.episodes.n_envs, doc="Envs the module keeps an episode for.")

    @property
    def encoder(self) -> th.nn.Module:
        """The frozen copy of the VAE that embeds observations for scoring (taken at every VAE update)."""
        return self._encoder

    # ------------------------------------------------------------------ embedding and scoring
    @th.inference_mode()
    def embed(self, raw: np.ndarray, batch_size: int = 1024, encoder: th.nn.Module | None = None) -> th.Tensor:
        """phi of a batch of raw observations (as kept in the buffers), (n, embed_dim).

        :param batch_size: observations per forward pass
        :param encoder: the VAE to embed with; None: the frozen copy inference uses"""
        if len(raw) == 0:
            return th.zeros(0, self.config.embed_dim)
        encoder = self._encoder if encoder is None else encoder
        out = [encoder.embed(self.adapter.to_tensor(raw[i : i + batch_size], self.device)).cpu() for i in range(0, len(raw), batch_size)]
        return th.cat(out)

    @th.inference_mode()
    def mastery(self, raw_states: np.ndarray, raw_goals: np.ndarray) -> th.Tensor:
        """m(phi(s), phi(g)) for a batch of states against a batch of goals, (n_states, n_goals)."""
        parts = self._folded.goal_part(self.embed(raw_goals))
        phi = self.embed(raw_states)
        return self._folded.mastery_from_parts(self._folded.state_part(phi), parts.expand(len(phi), *parts.shape))

    @th.inference_mode()
    def score_states(self, observations: Any, env_indices: np.ndarray | None = None) -> np.ndarray:
        """Raw r_gc (eq 13) of a batch of states against the current goals of their envs, computed afresh: nothing
        is recorded, memoised or counted (for probes and maps).

        :param observations: a batch of observations
        :param env_indices: the envs whose goals each row meets (default: 0..n-1)"""
        raw = self.adapter.extract(observations)
        env_indices = np.arange(len(raw)) if env_indices is None else np.asarray(env_indices, dtype=np.int64)
        self.ensure_envs(int(env_indices.max()) + 1)
        ep, cfg = self.episodes, self.config
        return eq13_rows(self.embed(raw), ep.goal_parts[th.from_numpy(env_indices)], ep.has_goals[env_indices], self._folded,
                         cfg.alpha, cfg.aggregation, cfg.reward_scale).numpy()

    def ensure_envs(self, n_envs: int) -> None:
        """Grow the per-env state to ``n_envs`` environments (new envs get goals at once)."""
        if n_envs <= self.n_envs:
            return
        cfg = self.config
        per_env = max(-(-cfg.predictor_train_freq // n_envs), 2 * cfg.max_distance)
        check_memory({
            "goals of the episodes": (f"n_goals={cfg.n_goals} with {n_envs} envs", n_envs * cfg.n_goals * self._raw_bytes),
            "trajectory store": (f"predictor_train_freq={cfg.predictor_train_freq} with {n_envs} envs", n_envs * per_env * (4 * cfg.embed_dim + 8)),
        })
        new = self.episodes.grow(n_envs)
        self.trajectories.ensure_envs(n_envs)
        self.normalizer.ensure_envs(n_envs)
        self.sample_goals(new)

    def register_env(self) -> int:
        """Add one env (for per-env wrappers sharing this module) and return its index."""
        self.ensure_envs(self.n_envs + 1)
        return self.n_envs - 1

    def begin_episodes(self, env_indices: np.ndarray) -> None:
        """Start new episodes in ``env_indices``: a finished episode (while recording) is queued for goal selection,
        and the new episode gets a fresh id and K fresh goals."""
        env_indices = np.asarray(env_indices, dtype=np.int64)
        if len(env_indices) == 0:
            return
        self.ensure_envs(int(env_indices.max()) + 1)
        for e in env_indices:
            self.episodes.restart(e, self.recording)
        self.sample_goals(env_indices)

    @th.inference_mode()
    def sample_goals(self, env_indices: np.ndarray) -> None:
        """Draw K goals from the goal buffer for a new episode of each env in ``env_indices`` (eq 11)."""
        env_indices = np.asarray(env_indices, dtype=np.int64)
        if len(env_indices) == 0:
            return
        idx = self.goal_buffer.sample(len(env_indices), self.config.n_goals, self.rng)
        ep = self.episodes
        ep.touch_goals(env_indices)
        if idx.shape[1] == 0:
            ep.has_goals[env_indices] = False
            return
        ep.goal_obs[env_indices] = self.goal_buffer.observations[idx]
        ep.goal_parts[th.from_numpy(env_indices)] = self._folded.goal_part(self.goal_buffer.embeddings[th.from_numpy(idx)])
        ep.has_goals[env_indices] = True

    @th.inference_mode()
    def _refresh_active_goals(self) -> None:
        """Recompute the goal halves of the active goals after the predictor or the VAE changed."""
        ep = self.episodes
        ep.touch_goals(np.arange(self.n_envs))
        for e in range(self.n_envs):
            if ep.has_goals[e]:
                ep.goal_parts[e] = self._folded.goal_part(self.embed(ep.goal_obs[e]))

    def refresh(self) -> None:
        """Take the VAE's and the predictor's current weights into use for scoring (after changing them by hand):
        a new frozen encoder and folded predictor, the goals re-embedded, the memos and the stored training pairs
        (embedded by the old encoder) dropped."""
        self._use_encoder()
        self._folded = self.predictor.fold()
        self._refresh_active_goals()

    def _use_encoder(self) -> None:
        """Embed with the VAE's current weights: a new frozen encoder, the goals re-embedded, and what the old encoder
        embedded dropped (the phi memo, the training-pair store)."""
        self._encoder = self._frozen_encoder()
        self.scorer.phi_memo.clear()
        self.goal_buffer.refresh(self.embed)
        self.trajectories.clear()

    # ------------------------------------------------------------------ the step
    def step(self, observations: Any, dones: np.ndarray, env_indices: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Curiosity reward of the states just reached, one per env.

        :param observations: batch of observations s_{t+1} (for an env whose episode just ended: its terminal
            observation, not the reset one)
        :param dones: whether each env's episode ended with this observation; such envs get new goals
        :param env_indices: which envs the rows belong to (default: 0..n-1)
        :return: raw r_gc (eq 13, times the revisit factor of ``revisit_decay``) and normalised r_gc (eq 14),
            float32 arrays of shape (n,)
        """
        t0 = time.perf_counter()
        raw = self.adapter.extract(observations)
        env_indices = np.arange(len(raw)) if env_indices is None else np.asarray(env_indices, dtype=np.int64)
        dones = np.asarray(dones, dtype=bool)
        self.ensure_envs(int(env_indices.max()) + 1)
        keys = [observation_key(x) for x in raw]
        rewards, phi = self.scorer.score(raw, env_indices, keys, self._encoder, self._folded)
        if self.recording:
            self.trajectories.add(th.from_numpy(phi), self.episodes.ids[env_indices], env_indices)
            self.memory.add(raw, self.rng)
            if not self.pretrained:
                self._calibration.add(raw, self.episodes.ids[env_indices])
            for j, e in enumerate(env_indices):
                self.episodes.states[e].append(raw[j].copy())
            self.n_recorded_steps += len(raw)
        if not np.all(np.isfinite(rewards)):
            # a broken network must not poison the policy's buffer: no bonus for these states
            self.stats["nonfinite_rewards"] = self.stats.get("nonfinite_rewards", 0) + int((~np.isfinite(rewards)).sum())
            rewards = np.where(np.isfinite(rewards), rewards, 0.0).astype(np.float32)
        if self.config.revisit_decay != "none":
            visits = self.episodes.count_visits(self.revisit_key(raw), env_indices)
            rewards = rewards * revisit_factor(visits, self.config.revisit_decay)
            if self.recording:
                self._first_visits[0] += int((visits == 1).sum())
                self._first_visits[1] += len(visits)
        normalized = self.normalizer(rewards, env_indices, update=self.recording)
        if self.recording:
            self.reward_centre.update(normalized)
            self._reward_sums[0] += float(rewards.sum())
            self._reward_sums[1] += float((rewards.astype(np.float64) ** 2).sum())
            self._reward_sums[2] += len(rewards)
        self.time_inference += time.perf_counter() - t0
        self.begin_episodes(env_indices[dones])
        return rewards, normalized

    # ------------------------------------------------------------------ learning
    def add_finished_episode_goals(self) -> int:
        """Add goals from every episode finished since the last call (final state + l by the strategy).

        :return: number of goals added (after the novelty filter)
        """
        added = 0
        finished = self.episodes.finished
        while finished:
            episode = finished.popleft()
            steps = select_goal_steps(len(episode), self.config.new_goals_per_episode, self.config.goal_strategy, self.rng)
            candidates = episode[steps]
            added += self.goal_buffer.add(candidates, self.embed(candidates), self.rng)
        return added

    def _frozen_encoder(self) -> th.nn.Module:
        """Inference embeds with a frozen copy of the VAE, so the VAE itself can train while steps go on."""
        return copy.deepcopy(self.vae).eval().requires_grad_(False)

    def vae_job(self, epochs: int | None = None, patience: int | None = None) -> VaeJob | None:
        """The job of a VAE update on the memory bank now (:meth:`Trainer.vae_job`); marks the update done.

        :param epochs: default ``vae_update_epochs``
        :param patience: default ``vae_patience``"""
        job = self.trainer.vae_job(self.memory.observations[: self.memory.size], self.rng, self.vae_pixel_weighting, epochs, patience)
        if job is not None:
            self.last_vae_update = self.n_recorded_steps
        return job

    def predictor_holdout(self) -> int:
        """The newest states of each env that a predictor update holds out to score itself: ``PREDICTOR_HOLDOUT`` of
        the states an env holds, at least 2 d_max (so that far pairs occur among them), at most half."""
        filled = np.minimum(self.trajectories.count, self.trajectories.capacity)
        if len(filled) == 0:
            return 0
        return min(max(int(round(PREDICTOR_HOLDOUT * filled.max())), 2 * self.config.max_distance), int(filled.min()) // 2)

    def predictor_job(self) -> PredictorJob | None:
        """The job of a predictor update on pairs drawn from the trajectory store now (``pair_labels``), with held-out
        pairs of the newest states to score it; marks the update done."""
        cfg, store = self.config, self.trajectories
        holdout = self.predictor_holdout()
        n_pairs = cfg.predictor_pairs if cfg.predictor_epochs > 0 else 0  # an untrained predictor is only scored
        if cfg.pair_labels == "eq16":
            pairs = (*store.sample_pairs(n_pairs, cfg.max_distance, self.rng, first_visit=cfg.first_visit_distance, holdout=holdout), None)
        else:
            pairs = reachability_pairs(store, self.goal_buffer, n_pairs, NEAR_DISTANCE, cfg.max_distance, self.rng, holdout)
        quality = QualityPairs.draw(store, self.goal_buffer, cfg.max_distance, self.rng, holdout)
        self.last_predictor_update = self.n_recorded_steps
        return self.trainer.predictor_job(*pairs, quality=quality)

    def _take_vae(self, fit: VaeFit) -> dict[str, float]:
        """Take a VAE fit into use: re-embed the goals, drop the embeddings of the old encoder."""
        t0 = time.perf_counter()
        guard_update("vae", self.vae, self.trainer.vae_optimizer, fit.snapshot, fit.skipped, self.stats)
        self.stats["vae_collapsed_updates"] = self.stats.get("vae_collapsed_updates", 0.0) + fit.collapsed
        if fit.best_epoch > 0:  # otherwise the VAE kept its weights: every embedding is still valid
            self._use_encoder()
            self._refresh_active_goals()
        dt = fit.time + time.perf_counter() - t0
        self.time_vae += dt
        out = fit.stats(dt)
        self.stats.update(out)
        return out

    def _take_predictor(self, fit: PredictorFit) -> dict[str, float]:
        """Take a predictor fit into use: fold it for inference, recompute the goal halves."""
        t0 = time.perf_counter()
        guard_update("predictor", self.predictor, self.trainer.predictor_optimizer, fit.snapshot, fit.skipped, self.stats)
        self._folded = self.predictor.fold()
        self._refresh_active_goals()
        dt = fit.time + time.perf_counter() - t0
        self.time_predictor += dt
        out = fit.stats(dt)
        self.stats.update(out)
        return out

    def use_fits(self, fits: list[VaeFit | PredictorFit]) -> dict[str, float]:
        """Take fits of :attr:`trainer` into use, in order (for fits made outside :meth:`maybe_train`); their statistics."""
        out: dict[str, float] = {}
        for fit in fits:
            out.update(self._take_vae(fit) if isinstance(fit, VaeFit) else self._take_predictor(fit))
        return out

    def train_vae(self, epochs: int | None = None, patience: int | None = None) -> dict[str, float]:
        """Train the VAE on the memory bank (eq 8) now, then re-embed goals and drop stale embeddings.

        :param epochs: the most passes over the memory bank (default ``vae_update_epochs``)
        :param patience: early stopping's patience (default ``vae_patience``; 0: all ``epochs``)
        :return: statistics of the update
        """
        job = self.vae_job(epochs, patience)
        return {} if job is None else self._take_vae(self.trainer.fit_vae(job))

    def train_predictor(self) -> dict[str, float]:
        """Draw pairs (s_t, s_{t+y}), label them with eq 15-16 and train the predictor now.

        :return: statistics of the update (loss, accuracy against the labels, fraction labelled mastered)
        """
        job = self.predictor_job()
        return {} if job is None else self._take_predictor(self.trainer.fit_predictor(job))

    def pretrain(self) -> dict[str, float]:
        """Train the VAE on what the memory bank holds (the random-policy observations) for all ``vae_epochs``
        epochs, choose the revisit cell from the random-policy episodes recorded (:func:`~sb3_gocu.curiosity.revisits.choose_cell`),
        and mark the module pretrained."""
        out = self.train_vae(epochs=self.config.vae_epochs, patience=0)
        if not self.pretrained:  # a second pretraining keeps the cell
            self.revisit_key, chosen = self._calibration.choose(self.adapter.layout, self.adapter.scale, self.adapter.raw_shape)
            out.update(chosen)
            self.stats.update(chosen)
            for visits in self.episodes.visits:  # counted with the cell before
                visits.clear()
        self.pretrained = True
        self.last_predictor_update = self.n_recorded_steps  # P_m counts from the first rollout
        return out

    def maybe_train(self) -> dict[str, float]:
        """Add goals from finished episodes, and run the updates due: the predictor every ``predictor_train_freq`` and
        the VAE every ``vae_train_freq`` recorded steps. Call it at a rollout's end.

        :return: statistics of the updates run, and ``goals_added``
        """
        out = {"goals_added": float(self.add_finished_episode_goals())}
        # predictor first: a VAE update makes the stored embeddings (the predictor's pairs) stale
        if self.n_recorded_steps - self.last_predictor_update >= self.config.predictor_train_freq:
            out.update(self.train_predictor())
        if self.n_recorded_steps - self.last_vae_update >= self.config.vae_train_freq:
            out.update(self.train_vae())
        return out

    def pop_reward_stats(self) -> dict[str, float]:
        """The figures of the steps since the last call: mean and std of the raw r_gc recorded (when any was), the
        scorer's memo hit rate, the seconds spent scoring; the sizes of the goal buffer and the memory bank and the
        normaliser's std now; and the held-out AUCs of the last predictor update (``predictor_auc_far``: near goals
        against far ones of the same episode; ``predictor_auc_goals``: near goals against goals of the buffer)."""
        hits, lookups = self.scorer.cache_hits - self._hits_at_pop[0], self.scorer.cache_lookups - self._hits_at_pop[1]
        self._hits_at_pop = (self.scorer.cache_hits, self.scorer.cache_lookups)
        out = {"goal_buffer_size": float(self.goal_buffer.size), "memory_size": float(self.memory.size), "return_std": self.normalizer.std,
               "time_inference": self.time_inference - self._inference_at_pop}
        self._inference_at_pop = self.time_inference
        out.update({k: self.stats[k] for k in QUALITY_KEYS if k in self.stats})  # the last predictor update's
        if lookups:
            out["cache_hit_rate"] = hits / lookups
        total, squares, count = self._reward_sums
        if count:
            mean = total / count
            out["reward_mean"] = mean
            out["reward_std"] = math.sqrt(max(0.0, squares / count - mean**2))
        self._reward_sums = [0.0, 0.0, 0]
        if self._first_visits[1]:
            out["first_visit_share"] = self._first_visits[0] / self._first_visits[1]
        self._first_visits = [0, 0]
        return out

    # ------------------------------------------------------------------ persistence
    def state_dict(self) -> dict[str, Any]:
        """Everything the module learned and remembers (:func:`~sb3_gocu.curiosity.persistence.module_state`): tensors
        and plain Python values, loadable with ``torch.load(..., weights_only=True)``, for a bit-exact resumption."""
        return persistence.module_state(self)

    def load_state_dict(self, state: dict[str, Any], strict: bool = True) -> None:
        """Restore a :meth:`state_dict`; a ``ValueError`` for a state that is not one or holds non-finite weights.

        :param state: what :meth:`state_dict` returned
        :param strict: as for ``torch.nn.Module.load_state_dict`` (accepted for SB3's ``set_parameters``)
        """
        persistence.load_module_state(self, state, strict)
