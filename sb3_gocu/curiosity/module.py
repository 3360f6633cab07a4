"""GoalCuriosityModule: the goal-based curiosity module (GCM) of the paper, Fig. 3, on tensors alone.

One object holds everything GoCu learns and remembers: the VAE and its optimiser, the mastery predictor
and its optimiser, the goal buffer, the memory bank, the trajectory store for training pairs, the
intrinsic-return normaliser and the random generator that samples goals. Wrappers feed it batches of
observations (:meth:`step`); a callback tells it when to learn (:meth:`add_finished_episode_goals`,
:meth:`train_vae`, :meth:`train_predictor`, or :meth:`maybe_train`).

The reward of a state s in an episode with goals g_1..g_K (eq 13, 14)::

    m_k  = m(phi(s), phi(g_k))                  mastery predictor, eval mode
    r_gc = (alpha - h(m_1, ..., m_K)) / delta   h = max (paper) or mean
    r    = r_gc / std(intrinsic returns)

Hot path. Between two predictor/VAE updates, the reward of a state against an episode's goals is a fixed
function, so it is computed with the folded predictor (batch norm folded, first layer split, goal half
cached per episode) and memoised per episode on the observation's bytes: an observation seen again in
the same episode costs a hash. The embedding and scoring of new states can run in a worker thread or a worker
process (:meth:`submit` / :meth:`collect`, ``scoring_process``; the maths in :mod:`sb3_gocu.curiosity.scoring`)
while the caller steps the envs. None of this changes the value computed.
"""

from __future__ import annotations

import contextlib
import copy
import functools
import threading
from concurrent.futures import ThreadPoolExecutor
import math
import os
import time
import warnings
from collections import deque
from typing import Any, Callable, Sequence

import numpy as np
import torch as th
from gymnasium import spaces

from sb3_gocu.curiosity.checks import check as _check, is_flag, is_integer, is_number
from sb3_gocu.curiosity.goals import GOAL_STRATEGIES, GoalBuffer, select_goal_steps
from sb3_gocu.curiosity.networks import (
    ConvVAE,
    FoldedPredictor,
    MasteryPredictor,
    MlpVAE,
    PixelWeights,
    mastery_loss,
    sharded_vae_gradients,
    vae_loss,
)
from sb3_gocu.curiosity.observations import ObservationAdapter
from sb3_gocu.curiosity.parallel import SplitWork, splitting
from sb3_gocu.curiosity.scoring import ProcessScorer, eq13_rows, score_rows
from sb3_gocu.curiosity.reward import (
    AGGREGATIONS,
    REVISIT_DECAYS,
    IntrinsicReturnNormalizer,
    complexity_score,
    mastered_probability,
    revisit_factor,
)
from sb3_gocu.curiosity.stores import MemoryBank, TrajectoryStore, distinct_rows, observation_key


#: the choices of ``scoring_dtype`` and ``train_dtype``
DTYPES = {"float32": th.float32, "bfloat16": th.bfloat16}
#: ``vae_pixel_weighting`` of image observations when it is None (the default); measured on DoorKey-8x8 (README, Results)
DEFAULT_PIXEL_WEIGHTING = 0.5


def _keys_to_tensor(table: dict[bytes, Any]) -> th.Tensor:
    """The (equal-length) byte keys of a memo as one uint8 tensor, a row per key."""
    return th.from_numpy(np.frombuffer(b"".join(table), dtype=np.uint8).reshape(len(table), -1 if table else 0).copy())


def _cache_to_state(cache: dict[bytes, Any]) -> dict[str, th.Tensor]:
    """A memo {key bytes: phi} or {key bytes: (reward, phi)} as tensors (loadable with weights_only=True)."""
    keys = _keys_to_tensor(cache)
    values = list(cache.values())
    if values and isinstance(values[0], tuple):
        return {"keys": keys, "rewards": th.tensor(np.array([r for r, _ in values], dtype=np.float32)),
                "phi": th.from_numpy(np.stack([np.asarray(p) for _, p in values]))}
    return {"keys": keys, "phi": th.stack([th.as_tensor(p) for p in values]) if values else th.zeros(0, 0)}


def _cache_from_state(state: dict[str, th.Tensor]) -> dict[bytes, Any]:
    """Inverse of :func:`_cache_to_state`."""
    keys = [bytes(k) for k in state["keys"].numpy()]
    if "rewards" in state:
        return dict(zip(keys, zip(state["rewards"].numpy(), state["phi"].numpy())))
    return dict(zip(keys, state["phi"].clone()))


def _counts_to_state(counts: dict[bytes, int]) -> dict[str, th.Tensor]:
    """Visit counts {key bytes: n} as tensors."""
    return {"keys": _keys_to_tensor(counts), "counts": th.tensor(list(counts.values()), dtype=th.int64)}


def _counts_from_state(state: dict[str, th.Tensor]) -> dict[bytes, int]:
    """Inverse of :func:`_counts_to_state`."""
    return {bytes(k): int(n) for k, n in zip(state["keys"].numpy(), state["counts"].tolist())}


@contextlib.contextmanager
def torch_threads(n: int | None):
    """Run the block with ``n`` torch threads in the calling thread (None: leave the count alone), then restore
    the count it had. Torch keeps the count per thread once the thread has read it (``torch.get_num_threads``
    or a parallel operation), so a worker thread can change its own count while the training thread keeps its
    own; a thread that first reads it meanwhile takes the worker's (torch's default for new threads)."""
    before = th.get_num_threads()
    if n is None or n == before:
        yield
        return
    th.set_num_threads(n)
    try:
        yield
    finally:
        th.set_num_threads(before)


class EarlyStopping:
    """The rule of ``vae_patience``: track the best held-out loss, starting from the loss before training (epoch
    0), and stop after ``patience`` epochs in a row without a new best. NaN never is a new best.

    :param start_loss: held-out loss before the first epoch
    :param patience: epochs without a new best that end training (>= 1)
    """

    def __init__(self, start_loss: float, patience: int) -> None:
        self.best_loss, self.best_epoch, self.patience, self._since_best = start_loss, 0, patience, 0

    def update(self, epoch: int, loss: float) -> bool:
        """Record the held-out ``loss`` after ``epoch`` (1-based); True when it is a new best."""
        if loss < self.best_loss:
            self.best_loss, self.best_epoch, self._since_best = loss, epoch, 0
            return True
        self._since_best += 1
        return False

    @property
    def stop(self) -> bool:
        return self._since_best >= self.patience


class ScoringTicket:
    """One batch of states handed to :meth:`GoalCuriosityModule.submit`, until its rewards are collected."""

    def __init__(self, n: int, embed_dim: int) -> None:
        self.rewards = np.zeros(n, dtype=np.float32)  # raw r_gc (eq 13), filled at collection
        self.phi = np.zeros((n, embed_dim), dtype=np.float32)
        self.miss = np.zeros(0, dtype=np.int64)  # rows scored by the predictor
        self.embed_rows = np.zeros(0, dtype=np.int64)  # rows of ``miss`` whose phi is not memoised: embedded with the scoring
        self.phi_from: list[tuple[int, ScoringTicket, int]] = []  # (row, earlier ticket, its row): phi being embedded there
        self.computed: np.ndarray | None = None  # eq 13 of the miss rows, when computed in the caller's thread
        self.raw: np.ndarray | None = None  # their raw observations (a copy: the env reuses its buffers)
        self.observations: np.ndarray | None = None  # every row's raw observation, for a trajectory store that keeps them
        self.encoder: Any = None  # the encoder of the submission (a VAE update swaps the module's)
        self.pending: list[tuple[int, ScoringTicket, int]] = []  # (row, earlier ticket, its row): same state, same episode
        self.env_indices = np.zeros(0, dtype=np.int64)
        self.keys: list[bytes] = []
        self.episode_ids = np.zeros(0, dtype=np.int64)
        self.has_goals = np.zeros(0, dtype=bool)  # whether each miss row's episode has its K goals
        self.goal_parts: th.Tensor | None = None  # the miss rows' goal halves, copied for a worker thread or the caller
        self.folded: FoldedPredictor | None = None
        self.factor: np.ndarray | None = None  # revisit factor
        self.recording = False
        self.start = False  # the first observations of new episodes (record_start_states): recorded, no reward
        self.future: Any = None  # a concurrent Future (worker thread) or the scoring process's
        self.compute_time = 0.0
        self.compute_cpu_time = 0.0  # CPU time of the computing thread (the rest of compute_time: waiting for the GIL or a core)
        self.result: tuple[np.ndarray, np.ndarray] | None = None
        #: (raw rows, dones, env indices, first observations of the new episodes or None) of a step queued behind a
        #: running update (``queue_during_update``), until it is submitted
        self.queued: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None] | None = None


class FitThread:
    """Curiosity fits run in a thread of their own: an update overlapped with PPO's (``overlap_ppo_update``,
    ``train_in_background``) or a predictor update started ahead of time (``predictor_lead``). The thread that
    takes them into use gets their results from :meth:`take`, which raises there what the fits raised.

    :param name: the thread's name
    :param work: runs the fits; returns ``(network name, fit)`` pairs for :meth:`GoalCuriosityModule._finish_fits`
    :param wake: called when the fits end (``split_updates``' helper stops waiting for halves to compute)
    """

    def __init__(self, name: str, work: Callable[[], list[tuple[str, dict[str, Any]]]], wake: Callable[[], None]) -> None:
        self._work, self._wake = work, wake
        self._fits: list[tuple[str, dict[str, Any]]] = []
        self._error: BaseException | None = None
        self.finished = threading.Event()  # set when the fits end
        self.thread = threading.Thread(target=self._body, name=name, daemon=True)
        self.thread.start()

    def _body(self) -> None:
        try:
            self._fits = self._work()
        except BaseException as error:  # raised again in the thread that takes the fits into use
            self._error = error
        finally:
            self.finished.set()
            self._wake()

    def outcome(self) -> list[tuple[str, dict[str, Any]]]:
        """Wait for the thread to end: the fits, or the error they raised, as raised."""
        self.thread.join()
        if self._error is not None:
            raise self._error
        return self._fits

    def take(self) -> list[tuple[str, dict[str, Any]]]:
        """Wait for the thread to end: the fits, or a ``RuntimeError`` from the error they raised."""
        try:
            return self.outcome()
        except BaseException as error:
            raise RuntimeError("a background curiosity update failed") from error


class GoalCuriosityModule:
    """Goal-based curiosity (GoCu) on batches of observations.

    Defaults are the paper's MiniGrid settings (section 5.1.2); the paper's symbol is given for each.

    :param observation_space: observation space of the (vectorised) environment
    :param n_goals: K, goals sampled from the goal buffer at each episode start (1 <= K <= goal_buffer_size)
    :param goal_buffer_size: capacity of the goal buffer R_g
    :param new_goals_per_episode: l, goals drawn from each finished episode besides its final state
    :param goal_strategy: how new goals are drawn: "random", "proportional" or "late" (section 5.1.4)
    :param goal_novelty: novelty filter of eq 12: a candidate goal is kept only if its distance to the nearest
        goal exceeds ``goal_novelty`` times the buffer's median nearest-neighbour distance (0: refuse only
        exact duplicates)
    :param alpha: alpha of eq 13
    :param aggregation: h of eq 13, "max" or "mean"
    :param reward_scale: delta of eq 13 (> 0)
    :param revisit_decay: how much a state seen again within the same episode is paid: ``"none"`` (every visit
        pays eq 13, the paper), ``"inverse_sqrt"`` (the n-th visit pays r_gc / sqrt(n)) or ``"first_visit"``
        (only the first visit pays; the default, measured on DoorKey-8x8, see the README). Visits are counted
        on the observation's bytes, per env, from the episode's first recorded state (its reset observation with
        ``record_start_states``, else the first state a step reaches; at most ``episode_memory`` distinct
        observations; the count restarts when that is exceeded).
        See :func:`~sb3_gocu.curiosity.reward.revisit_factor`
    :param intrinsic_gamma: discount of the intrinsic returns, for the normalisation of eq 14 and (in
        PPO_GoCu) the GAE of the intrinsic stream
    :param prior_weight: lambda of eq 15
    :param distance_weight: beta of eq 15
    :param label_threshold: a of eq 16 (> 0)
    :param label_slope: b of eq 16 (> 0)
    :param max_distance: d_max, the largest step gap y of a training pair (s_t, s_{t+y}) (>= 1)
    :param soft_labels: train the predictor on p_skill of eq 16 as a soft target (True) or on labels drawn
        from Bernoulli(p_skill) (False)
    :param first_visit_distance: dist(s, g) of eq 15 is the number of steps until the goal's observation is
        first seen after s (0 if s itself is g) rather than the step gap y of the pair: an agent that stays
        put or comes back would otherwise see (s, s) labelled both mastered (small y) and not mastered
        (large y). See ``TrajectoryStore.sample_pairs``.
    :param predictor_hidden: hidden layer sizes of the predictor
    :param predictor_lr: Adam learning rate of the predictor
    :param predictor_batch_size: minibatch size of predictor training
    :param predictor_epochs: epochs over the drawn pairs at each predictor update (the paper: 15 over all the new
        pairs; on a bounded draw, 15 epochs overfit it: measured with ``benchmarks/predictor_epochs.py``, the
        validation loss is lowest after 1-2 epochs, and 16,384 pairs x 1 epoch beat 8,192 x 15 at an eighth of
        the cost)
    :param predictor_pairs: training pairs drawn per predictor update (a bounded sample of all pairs)
    :param predictor_train_freq: P_m, env steps between predictor updates
    :param predictor_dedupe: train the predictor on the distinct drawn pairs (same phi(s), phi(g) and distance),
        each weighted by its multiplicity: the same objective as the whole draw, with fewer passes when states
        repeat (an agent that stays put yields the same pair many times). With ``soft_labels=False`` each distinct
        pair draws one Bernoulli label and carries its count as weight: the same expected loss as one label per
        drawn pair, not the same variance
    :param embed_dim: size of the embedding phi (the FC layer after the VAE encoder)
    :param latent_dim: size of the VAE latent (mu, sigma)
    :param vae_beta: beta of eq 8
    :param vae_pixel_weighting: exponent (in [0, 1]) of the rare-colour weighting of the reconstruction term of
        eq 8 (:class:`~sb3_gocu.curiosity.networks.PixelWeights`, fitted at each VAE update to the colours of the
        observations it trains on): a pixel of a colour with share f of the pixels weighs ``f ** -exponent``,
        scaled so the mean pixel weight is 1. 0 (the paper): every pixel weighs 1. None (default): 0.5
        (:data:`DEFAULT_PIXEL_WEIGHTING`) for image observations, 0 for vectors (a value > 0 with vector
        observations is refused). Not in the paper: with 0 the VAE drops DoorKey's key, door colour and goal square
        (a few pixels of a grey view), and phi hardly moves for the key. Measured on DoorKey-8x8, seeds 0-6, one
        run each on one machine (README, Results): with 0.5, 3 of 3 of seeds 0-2 and 6 of 7 in all reached a mean
        return of 0.9 within 0.8M steps, in 4.59M steps summed over seeds 0-6 (a miss counted at 800,768), against
        2 of 3, 5 of 7 and 5.04M with 0. Of 0.5 and 1, 0.5 moved phi more for the key (a fresh VAE fitted to a
        trained agent's memory bank, ``benchmarks/embedding_phases.py --refit``). Fitting the weights took 0.1 s
        per VAE update on a trained DoorKey-8x8 agent's bank, and a VAE step took as long with them as without
        (``benchmarks/pixel_weights_cost.py``)
    :param vae_lr: Adam learning rate of the VAE
    :param vae_batch_size: minibatch size of VAE training
    :param vae_epochs: epochs over the memory bank at each VAE update (the most, with ``vae_patience``)
    :param vae_train_freq: P_vae, env steps between VAE updates
    :param vae_dedupe: train the VAE on the distinct observations of the memory bank, each weighted by its
        multiplicity (same objective as the whole bank, fewer passes when observations repeat)
    :param vae_patience: early stopping of a VAE update: ``vae_holdout`` of the distinct observations are held
        out, the loss of eq 8 on them is measured before the update and after each epoch, the update stops after
        ``vae_patience`` epochs without a new best, and the VAE keeps the weights of its best epoch. When no epoch
        beats the weights the update started from, the VAE's weights are left as they were and nothing is
        re-embedded (the trajectories of the predictor are kept); its Adam moments and step count keep the
        tried epochs' steps. 0 (the paper): always ``vae_epochs`` epochs on the whole bank.
        Default 1, measured: with ``benchmarks/vae_epochs.py`` a cold VAE improves through 20 epochs, a warm one
        on DoorKey-8x8 does not improve at all at 600k steps (its 20 epochs only move phi at random); on the
        DoorKey-8x8 sample-efficiency benchmark (seeds 0-2) patience 1 reached a mean return of 0.9 in fewer
        steps and less wall time than 0 on every seed (README, Results)
    :param vae_pretrain_patience: ``vae_patience`` of the pretraining's VAE update (on the random-policy
        observations); None: ``vae_patience``. Default 0 (the paper): the pretraining trains all ``vae_epochs``
        epochs on the whole bank, while every later update stops early with ``vae_patience``. With patience 1 the
        pretraining stops after 5 to 7 of its 20 epochs on DoorKey-8x8, at a held-out loss of 1240 to 1507 against
        932 after all 20 (``benchmarks/pretrain_epochs.py``). Measured on DoorKey-8x8 (README, Results), one run per
        seed: with 0, seeds 0-6 but seed 4 reached a mean return of 0.9 within 0.8M steps (seed 4 at 917,504); with
        None (the default until a69ce69), seeds 0-6 but 4 and 6, in 346k more steps summed over seeds 0-6 (a seed
        not reached counted at 800,768)
    :param vae_holdout: fraction of the distinct observations held out for ``vae_patience`` (in (0, 0.5]); with
        ``vae_dedupe=False``, of the bank's rows, so copies of a held-out observation can stay in the training part
    :param vae_shards: each VAE minibatch is cut into this many parts (1 to ``vae_batch_size``) whose losses and
        gradients are computed independently, each with 1 torch thread, then added in a fixed order
        (:func:`~sb3_gocu.curiosity.networks.sharded_vae_gradients`); the held-out loss of ``vae_patience``
        likewise, by chunks. The parts run in parallel threads (``update_threads`` of them; default: one per
        part, at most the usable cores), and the values do not depend on how many: a seed gives the same VAE,
        and the same run, with any thread count. Same objective and gradient as the whole minibatch, summed in
        another order. 1 (default): the whole minibatch at once with the update's thread count
        (``update_threads``), whose low bits depend on that count. Opt-in because another summation order is
        another draw of each seed's run: with 2, DoorKey-8x8 seed 1 reached a mean return of 0.9 at 620,544
        steps (763,904 with 1) but seed 2 not within 800,768 (README, Results), which the 3-of-3 target of the
        defaults cannot afford. One VAE step on 128 32x32 images: 267 ms with the parts one after the other,
        158 ms in 2 threads (``benchmarks/update_threads.py``)
    :param refit_predictor_after_vae: at each VAE update, embed the trajectory store again with the new encoder
        (it keeps the raw observations for that) and retrain the predictor on it right after the VAE, before the new
        embeddings score a state; the predictor's schedule (``predictor_train_freq``) counts on from there. This
        includes pretraining's VAE update: the predictor's first fit is then on the random-policy trajectories. False:
        the store is emptied at a VAE update (its embeddings belong to the old encoder) and the predictor is retrained
        when its schedule says, so until then a predictor fitted to the old embeddings scores the new ones (in a
        DoorKey-8x8 run its mastery saturates at 1 and r_gc is 0 for that rollout), and its next fit sees only the
        steps since the VAE update. The store's observations cost ``predictor_train_freq`` raw observations of memory.
        Opt-in: on DoorKey-8x8 no rollout had r_gc = 0 with it, but seeds 0 and 2 reached a mean return of 0.9 at
        778,240 and 751,616 steps and seed 1 not within 800,768 (README, Results), against 3 of 3 with False
    :param record_start_states: record the first observation of each episode, s_0 (the reset one; the wrappers
        hand it to :meth:`begin_episodes`), as the states reached by a step are recorded: into the memory bank,
        the episode's goal candidates, the trajectory store (so training pairs start from s_0 too: "each visited
        state s_t is concatenated with the d_max next states", section on the predictor) and the visit counts (a
        return to s_0 is a revisit for ``revisit_decay``). It is scored for the episode's memo but pays no reward,
        updates no normaliser and counts as no env step (the paper's reading). False (default): only the states
        reached by a step are recorded. Opt-in, measured: on DoorKey-8x8 it reached a mean return of 0.9 within
        0.8M steps on 5 of 7 seeds (not on seeds 4 and 5), against 6 of 7 without it (README, Results)
    :param pretrain_steps: random-policy observations collected to pretrain the VAE before the first rollout
    :param memory_size: capacity of the memory bank
    :param episode_memory: most recent states of the current episode kept per env to draw goals from
    :param obs_key: for a Dict observation space, the entry to embed
    :param image_channels: keep only the newest ``image_channels`` channels of an image (frame stacks)
    :param train_in_background: run each VAE / predictor update in a background thread, started by
        :meth:`maybe_train` at one rollout end and taken into use at the next one, so that it overlaps with the
        rollout (env stepping leaves a core idle). The networks trained are the same as without it (same data,
        same generator); only the step at which they take over moves one rollout later. Measured on DoorKey-8x8
        (README, Results): PPO_GoCu's time per step 1.12x plain PPO's against 1.40x without it (same run, 1 torch
        thread), but in the 3-seed sample-efficiency benchmark with it not every seed reached a mean return of 0.9
        within 0.8M steps (all three did without it), so it is off by default. Saving the module (``state_dict``)
        while an update runs waits for it and takes it into use at once
    :param overlap_ppo_update: (without ``train_in_background``) run an update due at a rollout end in a
        background thread, so that it overlaps with PPO's update of the policy (which leaves a core idle), and
        take it into use before the module is next used (the next rollout's first step): the same networks,
        taken into use at the same step as when run in place, only sooner in wall time. Its statistics come
        out of the next :meth:`maybe_train` (logged one rollout later). Measured on DoorKey-8x8 (README,
        Results): the rollouts waited 23.9 s for the updates per 100k steps, against 34.9 s in place (same run,
        1 torch thread). False: run the update in place
    :param predictor_lead: (with ``overlap_ppo_update``, without ``train_in_background`` or
        ``refit_predictor_after_vae``) start each predictor update this many rollouts before it is due, on the pairs
        drawn then, and run it only beside PPO's updates (paused while a rollout runs, so it competes with neither
        the scoring nor the env stepping); it is taken into use when due, as without a lead. So the update's
        compute is spread over the second core's idle time beside ``predictor_lead`` + 1 PPO updates instead of
        one, at the cost of pairs ``predictor_lead`` rollouts older (another run for each seed). Not when a VAE
        update falls due first (the predictor then runs as without a lead). 0 (default): no lead. Saving the
        module (``state_dict``), :meth:`train_predictor`, :meth:`train_vae` and :meth:`finish_updates` take a lead
        update into use at once
    :param update_threads: torch threads of a VAE or predictor update (pretraining's included). ``None``
        (default): the caller's ``torch.get_num_threads()``. An update that training waits for (in place, or
        overlapped with PPO's update and then waited for) leaves the caller's share of the machine and the
        scoring worker's idle (but for the halves of its large products that ``split_updates`` gives the caller,
        same values), so 2 on a 2-core machine with 1 torch thread uses both: on DoorKey-8x8 over 400k
        steps PPO_GoCu's time per step was 1.27x plain PPO's with 2 against 1.38x with 1 (same run; README,
        Results, "Throughput"). It is opt-in: some matrix products split their sums by thread, so the count
        changes the updates' low bits and with them the run a seed gives, and the 3-seed DoorKey-8x8 figures
        of the defaults were measured with 1; with 2, seed 1 was not solved within 0.8M steps (README). With
        ``train_in_background`` the update runs beside the rollout, so more threads compete with it. With
        ``vae_shards`` > 1 it is instead the number of threads that run the VAE minibatch's parts (1 torch thread
        each), which does not change the values
    :param scoring_process: score in a worker process rather than a worker thread (``submit(..., background=True)``,
        PPO_GoCu's ``async_scoring``): the process has its own GIL, so the scoring no longer waits for the env
        stepping's, and the env stepping no longer waits for the scoring's. The values are the same to the bit
        (the process runs the same operations with as many torch threads as the caller had); it costs a
        process (about 0.35 GB resident, measured during a DoorKey-8x8 run) and its start (a few seconds, once, overlapping pretraining when
        PPO_GoCu starts it). Measured on DoorKey-8x8 over 100k steps (README, Results, "Throughput"): the
        rollouts waited 2.8 s for the scores against 14.2 s with the worker thread, and PPO_GoCu's time per
        step was 1.30x plain PPO's against 1.39x (same run, 1 torch thread). ``None`` (default): a process
        on a POSIX system with a CPU device, else a thread. See :class:`~sb3_gocu.curiosity.scoring.ProcessScorer`
    :param scoring_dtype: dtype of the predictor's hidden layers after the first when scoring states against
        their K goals (eq 13, every step), ``"float32"`` (default) or ``"bfloat16"``. Those layers are nearly all
        of the scoring's work; bfloat16 rounds their inputs and weights to 8 bits of mantissa, so r_gc differs
        from float32's by under 1e-3 of its range (at most 6.4e-5 on a trained DoorKey-8x8 agent, where r_gc
        lies in [0, 0.1]), and runs about 3x faster on a CPU with AVX512-BF16 (slower
        on one without). Only the scoring changes: the predictor trains, and scores its training pairs' prior
        (eq 15), in float32 (see ``train_dtype``). Opt-in; see ``benchmarks/bf16_scoring.py`` and the
        README's "Throughput"
    :param train_dtype: dtype of the forward passes of the VAE's and the predictor's updates (pretraining's
        included), ``"float32"`` (default) or ``"bfloat16"`` (mixed precision: ``torch.autocast``; the weights,
        gradients, batch-norm statistics, optimiser state, losses, labels and the VAE's held-out loss for early
        stopping stay float32). On a CPU with AVX512-BF16 and one torch thread a minibatch step took about half
        the time for the 5x512 predictor and 0.5-0.65x for the image VAE. Opt-in: it changes the trained
        networks, and with them the run a seed gives
    :param split_updates: compute the large products of the VAE's and the predictor's updates (forward,
        backward and the labels' prior) in two halves, and let a thread that waits for the update compute the
        second halves (``sb3_gocu.curiosity.parallel``): the training thread while it waits for an update
        overlapped with PPO's (``overlap_ppo_update``), or the caller of an update run in place (pretraining
        included), which then runs the update in a thread of its own. Linear layers whose widths are multiples of
        32 are cut by output columns; convolutions by halves of the minibatch (output, input gradient) and, for the
        weight gradient, by halves of the output channels. These cuts leave every sum as it was, so the trained
        networks are the same to the bit as with whole products (tested for the default networks); halves are
        always computed the same way, so the values do not depend on who computes them or when. Only with one
        torch thread for the update, ``train_dtype="float32"`` and (for the VAE) ``vae_shards=1``; otherwise
        the products stay whole. Measured on DoorKey-8x8 in README, Results, "Throughput"
    :param queue_during_update: (with ``overlap_ppo_update``) a step submitted for background scoring
        (:meth:`submit`, as PPO_GoCu's rollouts do) while an update overlapped with PPO's still runs is queued, and
        :meth:`submit` returns at once, so the envs step on beside the update instead of waiting for it. When the
        update is done (checked at each submission), it is taken into use and the queued steps are submitted in
        their order, before anything else the module does; collecting a queued step waits for the update. Every
        step meets the same networks, goals and memos as without the queue, so the rewards and the module's
        state are the same bit for bit (tested); only the wall time changes. False: the first submission waits
        for the update
    :param device: torch device of the networks
    :param seed: seed of the module's random generators
    """

    def __init__(
        self,
        observation_space: spaces.Space,
        n_goals: int = 50,
        goal_buffer_size: int = 1500,
        new_goals_per_episode: int = 7,
        goal_strategy: str = "proportional",
        goal_novelty: float = 0.0,
        alpha: float = 1.0,
        aggregation: str = "max",
        reward_scale: float = 10.0,
        revisit_decay: str = "first_visit",
        intrinsic_gamma: float = 0.99,
        prior_weight: float = 3.0,
        distance_weight: float = 1.0,
        label_threshold: float = 15.0,
        label_slope: float = 0.8,
        max_distance: int = 30,
        soft_labels: bool = True,
        first_visit_distance: bool = True,
        predictor_hidden: Sequence[int] = (512, 512, 512, 512, 512),
        predictor_lr: float = 5e-4,
        predictor_batch_size: int = 128,
        predictor_epochs: int = 1,
        predictor_pairs: int = 16384,
        predictor_train_freq: int = 20_000,
        predictor_dedupe: bool = True,
        embed_dim: int = 128,
        latent_dim: int = 10,
        vae_beta: float = 1.0,
        vae_pixel_weighting: float | None = None,
        vae_lr: float = 1e-3,
        vae_batch_size: int = 128,
        vae_epochs: int = 20,
        vae_train_freq: int = 100_000,
        vae_dedupe: bool = True,
        vae_patience: int = 1,
        vae_pretrain_patience: int | None = 0,
        vae_holdout: float = 0.1,
        pretrain_steps: int = 10_000,
        memory_size: int = 10_000,
        episode_memory: int = 4096,
        obs_key: str | None = None,
        image_channels: int | None = None,
        train_in_background: bool = False,
        overlap_ppo_update: bool = True,
        predictor_lead: int = 0,
        scoring_process: bool | None = None,
        update_threads: int | None = None,
        vae_shards: int = 1,
        refit_predictor_after_vae: bool = False,
        record_start_states: bool = False,
        scoring_dtype: str = "float32",
        train_dtype: str = "float32",
        split_updates: bool = True,
        queue_during_update: bool = True,
        device: th.device | str = "cpu",
        seed: int | None = None,
    ) -> None:
        for name, value in (
            ("n_goals", n_goals), ("goal_buffer_size", goal_buffer_size), ("new_goals_per_episode", new_goals_per_episode),
            ("max_distance", max_distance), ("predictor_batch_size", predictor_batch_size), ("predictor_epochs", predictor_epochs),
            ("predictor_pairs", predictor_pairs), ("predictor_train_freq", predictor_train_freq), ("embed_dim", embed_dim),
            ("latent_dim", latent_dim), ("vae_batch_size", vae_batch_size), ("vae_epochs", vae_epochs),
            ("vae_train_freq", vae_train_freq), ("pretrain_steps", pretrain_steps), ("memory_size", memory_size),
            ("episode_memory", episode_memory), ("vae_patience", vae_patience), ("vae_shards", vae_shards),
            ("predictor_lead", predictor_lead),
        ):
            _check(is_integer(value), f"{name} must be an integer, got {value!r}")
        for name, value in (
            ("goal_novelty", goal_novelty), ("alpha", alpha), ("reward_scale", reward_scale), ("intrinsic_gamma", intrinsic_gamma),
            ("prior_weight", prior_weight), ("distance_weight", distance_weight), ("label_threshold", label_threshold),
            ("label_slope", label_slope), ("predictor_lr", predictor_lr), ("vae_lr", vae_lr), ("vae_beta", vae_beta),
        ):
            _check(is_number(value), f"{name} must be a number, got {value!r}")
        for name, value in (
            ("soft_labels", soft_labels), ("first_visit_distance", first_visit_distance), ("predictor_dedupe", predictor_dedupe),
            ("vae_dedupe", vae_dedupe), ("train_in_background", train_in_background), ("overlap_ppo_update", overlap_ppo_update),
            ("refit_predictor_after_vae", refit_predictor_after_vae), ("record_start_states", record_start_states),
            ("split_updates", split_updates), ("queue_during_update", queue_during_update),
        ):
            _check(is_flag(value), f"{name} must be True or False, got {value!r}")
        _check(goal_buffer_size >= 1, f"goal_buffer_size must be >= 1, got {goal_buffer_size}")
        _check(1 <= n_goals <= goal_buffer_size, f"n_goals (K) must be in [1, goal_buffer_size={goal_buffer_size}], got {n_goals}")
        _check(new_goals_per_episode >= 0, f"new_goals_per_episode (l) must be >= 0, got {new_goals_per_episode}")
        _check(goal_strategy in GOAL_STRATEGIES, f"goal_strategy must be one of {GOAL_STRATEGIES}, got {goal_strategy!r}")
        _check(goal_novelty >= 0, f"goal_novelty must be >= 0, got {goal_novelty}")
        _check(math.isfinite(alpha), f"alpha must be a finite number, got {alpha}")
        _check(aggregation in AGGREGATIONS, f"aggregation (h) must be one of {AGGREGATIONS}, got {aggregation!r}")
        _check(revisit_decay in REVISIT_DECAYS, f"revisit_decay must be one of {REVISIT_DECAYS}, got {revisit_decay!r}")
        _check(reward_scale > 0, f"reward_scale (delta) must be > 0, got {reward_scale}")
        _check(0 <= intrinsic_gamma <= 1, f"intrinsic_gamma must be in [0, 1], got {intrinsic_gamma}")
        _check(prior_weight >= 0, f"prior_weight (lambda) must be >= 0, got {prior_weight}")
        _check(distance_weight >= 0, f"distance_weight (beta) must be >= 0, got {distance_weight}")
        _check(label_threshold > 0, f"label_threshold (a) must be > 0, got {label_threshold}")
        _check(label_slope > 0, f"label_slope (b) must be > 0, got {label_slope}")
        _check(max_distance >= 1, f"max_distance (d_max) must be >= 1, got {max_distance}")
        for name, value in (
            ("predictor_batch_size", predictor_batch_size),
            ("predictor_pairs", predictor_pairs),
            ("predictor_train_freq", predictor_train_freq),
            ("embed_dim", embed_dim),
            ("latent_dim", latent_dim),
            ("vae_batch_size", vae_batch_size),
            ("vae_train_freq", vae_train_freq),
            ("memory_size", memory_size),
            ("episode_memory", episode_memory),
        ):
            _check(value >= 1, f"{name} must be >= 1, got {value}")
        for name, value in (
            ("predictor_epochs", predictor_epochs), ("vae_epochs", vae_epochs), ("pretrain_steps", pretrain_steps), ("vae_patience", vae_patience),
            ("predictor_lead", predictor_lead),
        ):
            _check(value >= 0, f"{name} must be >= 0, got {value}")
        _check(
            vae_pretrain_patience is None
            or (is_integer(vae_pretrain_patience) and vae_pretrain_patience >= 0),
            f"vae_pretrain_patience must be None or an integer >= 0, got {vae_pretrain_patience!r}",
        )
        for name, value in (("predictor_lr", predictor_lr), ("vae_lr", vae_lr)):
            _check(value > 0, f"{name} must be > 0, got {value}")
        _check(vae_beta >= 0, f"vae_beta must be >= 0, got {vae_beta}")
        _check(
            vae_pixel_weighting is None or (is_number(vae_pixel_weighting) and 0 <= vae_pixel_weighting <= 1),
            f"vae_pixel_weighting must be None or in [0, 1], got {vae_pixel_weighting!r}",
        )
        _check(
            is_number(vae_holdout) and 0 < vae_holdout <= 0.5,
            f"vae_holdout must be in (0, 0.5], got {vae_holdout!r}",
        )

        _check(
            update_threads is None or (is_integer(update_threads) and update_threads >= 1),
            f"update_threads must be None or an int >= 1, got {update_threads!r}",
        )
        _check(1 <= vae_shards <= vae_batch_size, f"vae_shards must be in [1, vae_batch_size={vae_batch_size}], got {vae_shards}")
        _check(
            not predictor_lead or (overlap_ppo_update and not train_in_background and not refit_predictor_after_vae),
            f"predictor_lead={predictor_lead} needs overlap_ppo_update=True, train_in_background=False and "
            f"refit_predictor_after_vae=False, got {overlap_ppo_update}, {train_in_background} and {refit_predictor_after_vae}",
        )

        self.observation_space = observation_space
        self.adapter = ObservationAdapter(observation_space, obs_key=obs_key, image_channels=image_channels)
        self.n_goals = n_goals
        self.new_goals_per_episode = new_goals_per_episode
        self.goal_strategy = goal_strategy
        self.alpha = alpha
        self.aggregation = aggregation
        self.reward_scale = reward_scale
        self.revisit_decay = revisit_decay
        self.intrinsic_gamma = intrinsic_gamma
        self.prior_weight = prior_weight
        self.distance_weight = distance_weight
        self.label_threshold = label_threshold
        self.label_slope = label_slope
        self.max_distance = max_distance
        self.soft_labels = soft_labels
        self.first_visit_distance = first_visit_distance
        self.predictor_batch_size = predictor_batch_size
        self.predictor_epochs = predictor_epochs
        self.predictor_pairs = predictor_pairs
        self.predictor_train_freq = predictor_train_freq
        self.predictor_dedupe = predictor_dedupe
        self.vae_beta = vae_beta
        self.vae_batch_size = vae_batch_size
        self.vae_epochs = vae_epochs
        self.vae_train_freq = vae_train_freq
        self.vae_dedupe = vae_dedupe
        self.vae_patience = vae_patience
        self.vae_pretrain_patience = vae_patience if vae_pretrain_patience is None else int(vae_pretrain_patience)
        self.vae_holdout = float(vae_holdout)
        self.vae_shards = int(vae_shards)
        self.refit_predictor_after_vae = bool(refit_predictor_after_vae)
        self.record_start_states = bool(record_start_states)
        _check(scoring_dtype in DTYPES, f"scoring_dtype must be one of {tuple(DTYPES)}, got {scoring_dtype!r}")
        self.scoring_dtype = scoring_dtype
        _check(train_dtype in DTYPES, f"train_dtype must be one of {tuple(DTYPES)}, got {train_dtype!r}")
        self.train_dtype = train_dtype
        self.split_updates = bool(split_updates)
        self.queue_during_update = bool(queue_during_update)
        self._split = SplitWork()
        self._shard_pool: ThreadPoolExecutor | None = None
        self._shard_pool_workers = 0
        self.pretrain_steps = pretrain_steps
        self.episode_memory = episode_memory
        self.device = th.device(device)
        _check(scoring_process is None or is_flag(scoring_process), f"scoring_process must be True, False or None, got {scoring_process!r}")
        _check(not scoring_process or self.device.type == "cpu", f"scoring_process needs device='cpu', got {self.device}")
        _check(not scoring_process or os.name == "posix", f"scoring_process needs a POSIX system (it passes pipes to a child), got {os.name!r}")
        self.scoring_process = bool(self.device.type == "cpu" and os.name == "posix" if scoring_process is None else scoring_process)

        self.rng = np.random.default_rng(seed)
        self._torch_gen = th.Generator().manual_seed(int(self.rng.integers(2**62)))
        vae_cls = ConvVAE if self.adapter.is_image else MlpVAE
        _check(not vae_pixel_weighting or self.adapter.is_image,
               f"vae_pixel_weighting applies to image observations, got {vae_pixel_weighting} with observations of shape {self.adapter.input_shape}")
        self._pixel_weighting_given = vae_pixel_weighting is not None
        if vae_pixel_weighting is None:
            vae_pixel_weighting = DEFAULT_PIXEL_WEIGHTING if self.adapter.is_image else 0.0
        self.vae_pixel_weighting = float(vae_pixel_weighting)
        init_seed = int(self.rng.integers(2**62))
        # with a seed, the initial weights depend on it alone, not on the global torch RNG's state
        with th.random.fork_rng(devices=[], enabled=seed is not None):
            if seed is not None:
                th.manual_seed(init_seed)
            self.vae = vae_cls(self.adapter.input_shape, embed_dim=embed_dim, latent_dim=latent_dim).to(self.device)
            self.predictor = MasteryPredictor(embed_dim, predictor_hidden).to(self.device)
        # foreach: Adam's multi-tensor step, the same values as its per-parameter loop (tested) in fewer calls
        self.vae_optimizer = th.optim.Adam(self.vae.parameters(), lr=vae_lr, foreach=True)
        self.predictor_optimizer = th.optim.Adam(self.predictor.parameters(), lr=predictor_lr, foreach=True)
        self.vae.eval()
        self.predictor.eval()

        raw_shape, raw_dtype = self.adapter.raw_shape, self.adapter.raw_dtype
        self.goal_buffer = GoalBuffer(goal_buffer_size, raw_shape, raw_dtype, embed_dim, goal_novelty)
        self.memory = MemoryBank(memory_size, raw_shape, raw_dtype)
        self.trajectories = TrajectoryStore(
            predictor_train_freq, embed_dim, min_per_env=2 * max_distance,
            obs_shape=raw_shape if self.refit_predictor_after_vae else None, obs_dtype=raw_dtype,
        )
        self.normalizer = IntrinsicReturnNormalizer(intrinsic_gamma)

        # per-env state
        self.n_envs = 0
        self._goal_obs = np.zeros((0, n_goals, *raw_shape), dtype=raw_dtype)
        self._has_goals = np.zeros(0, dtype=bool)  # per env: its episode has K goals (none while the goal buffer is empty)
        self._goal_parts = th.zeros(0, n_goals, self.predictor.hidden[0].out_features)
        self._goal_version = np.zeros(0, dtype=np.int64)  # bumped at every change of an env's goal halves
        self._goal_stamp = 0
        self._episode_ids = np.zeros(0, dtype=np.int64)
        self._episodes: list[deque] = []
        self._reward_cache: list[dict] = []
        self._visit_counts: list[dict[bytes, int]] = []
        self._pending: list[dict[bytes, tuple[ScoringTicket, int]]] = []  # states of each episode being scored
        self._outstanding: deque[ScoringTicket] = deque()
        self._scorer: ThreadPoolExecutor | None = None
        self._process: ProcessScorer | None = None
        self._phi_cache: dict[bytes, th.Tensor] = {}
        self.train_in_background = train_in_background
        self.overlap_ppo_update = overlap_ppo_update
        self.update_threads = None if update_threads is None else int(update_threads)
        self._job: FitThread | None = None  # an update started by maybe_train, not yet taken into use
        self._job_until_next_use = False  # the running update is taken into use before the module is next used
        self._unreported: dict[str, float] = {}  # statistics of updates taken into use outside maybe_train
        self.predictor_lead = int(predictor_lead)
        self._lead: FitThread | None = None  # a predictor update started before it is due (predictor_lead)
        self._lead_gate = threading.Event()  # set while the lead update may run: between a rollout's end and the next
        self._recorded_at_last_train = 0  # n_recorded_steps at the last maybe_train (a rollout's recorded steps)
        self._queue: deque[ScoringTicket] = deque()  # steps submitted while an overlapped update runs (queue_during_update)
        self._holding_queue = False  # while an update is taken into use, or the queue is being submitted
        self.queued_steps = 0  # steps that waited in the queue (queue_during_update)
        self.embedding_cache_size = 100_000
        self._next_episode_id = 0
        self.finished_episodes: deque = deque(maxlen=1024)

        #: when True, :meth:`step` records observations (memory bank, trajectory store, episodes) and updates
        #: the normaliser; a training callback switches it on
        self.recording = False
        #: first observations of episodes begun while not recording (``record_start_states``), per env, recorded by
        #: :meth:`start_recording` if their episode has taken no step by then (e.g. the reset of SB3's
        #: ``_setup_learn``, which comes before a training callback switches recording on)
        self._unrecorded_starts: dict[int, np.ndarray] = {}
        self.pretrained = False
        self.n_recorded_steps = 0
        self.last_vae_update = 0
        self.last_predictor_update = 0
        self.stats: dict[str, float] = {}
        self._reward_sum = 0.0
        self._reward_sq_sum = 0.0
        self._reward_count = 0
        self._cache_hits = 0  # since the last pop_reward_stats
        self._cache_lookups = 0
        #: cumulative figures (seconds, counts) since construction
        self.cache_hits = 0
        self.cache_lookups = 0
        self.time_inference = 0.0
        self.time_inference_background = 0.0  # scoring in the worker thread (overlaps the caller's work)
        self.time_scoring_wait = 0.0  # part of time_inference: the caller waiting for the worker's scores
        #: scoring process only: a ticket submitted while this many or more of the process's tickets are unanswered
        #: (or while sending it would first wait for answers) is scored in the caller instead (None: never).
        #: PPO_GoCu sets it to ``scoring_lag - 1`` (at least 1) during rollouts (``spill_scoring``): the caller
        #: would otherwise soon wait for the process. Same values either way
        self.scoring_spill: int | None = None
        self.spilled_tickets = 0
        self.cpu_inference_background = 0.0  # CPU time of the worker's scoring (its wall time: time_inference_background)
        self.time_training = 0.0
        self.time_vae = 0.0
        self.time_predictor = 0.0
        self.time_update_wait = 0.0  # waiting for an update that overlapped PPO's (overlap_ppo_update) to finish
        self._folded = self._fold()
        self._sync_encoder()

    # ------------------------------------------------------------------ embedding and scoring
    @th.inference_mode()
    def embed(self, raw: np.ndarray, batch_size: int = 1024, encoder: th.nn.Module | None = None) -> th.Tensor:
        """phi of a batch of raw observations (as kept in the buffers), (n, embed_dim).

        :param encoder: the VAE to embed with; None: the frozen copy inference uses"""
        if len(raw) == 0:
            return th.zeros(0, self.goal_buffer.embeddings.shape[1])
        encoder = self._encoder if encoder is None else encoder
        out = [encoder.embed(self.adapter.to_tensor(raw[i : i + batch_size], self.device)).cpu() for i in range(0, len(raw), batch_size)]
        return th.cat(out)

    @th.inference_mode()
    def mastery(self, raw_states: np.ndarray, raw_goals: np.ndarray) -> th.Tensor:
        """m(phi(s), phi(g)) for a batch of states against a batch of goals, (n_states, n_goals)."""
        self._await_overlapped_update()
        parts = self._folded.goal_part(self.embed(raw_goals))
        phi = self.embed(raw_states)
        return self._folded.mastery_from_parts(self._folded.state_part(phi), parts.expand(len(phi), *parts.shape))

    @th.inference_mode()
    def score_states(self, observations: Any, env_indices: np.ndarray | None = None) -> np.ndarray:
        """Raw r_gc (eq 13) of a batch of states against the current goals of their envs, computed afresh:
        nothing is recorded, memoised or counted (for probes and maps)."""
        self._await_overlapped_update()
        raw = self.adapter.extract(observations)
        env_indices = np.arange(len(raw)) if env_indices is None else np.asarray(env_indices, dtype=np.int64)
        self.ensure_envs(int(env_indices.max()) + 1)
        envs = th.from_numpy(env_indices)
        return self._eq13(self.embed(raw), self._goal_parts[envs], self._has_goals[env_indices], self._folded).numpy()

    @property
    def _eq13_args(self) -> tuple[float, str, float]:
        """The settings of eq 13 after phi, goals and predictor: (alpha, aggregation h, reward_scale delta)."""
        return self.alpha, self.aggregation, self.reward_scale

    @property
    def _to_tensor(self) -> Callable[[np.ndarray], th.Tensor]:
        """Raw batch -> the encoder's input on the module's device (picklable, for the scoring process)."""
        return functools.partial(self.adapter.to_tensor, device=self.device)

    def _fold(self) -> FoldedPredictor:
        """The predictor's inference form for eq 13, in ``scoring_dtype``."""
        return self.predictor.fold(DTYPES[self.scoring_dtype])

    def _eq13(self, phi: th.Tensor, goal_parts: th.Tensor, has_goals: np.ndarray, folded: FoldedPredictor) -> th.Tensor:
        """Raw r_gc of states (phi) against their episodes' goals: :func:`~sb3_gocu.curiosity.scoring.eq13_rows`."""
        return eq13_rows(phi, goal_parts, has_goals, folded, *self._eq13_args)

    def ensure_envs(self, n_envs: int) -> None:
        """Grow the per-env state to ``n_envs`` environments (new envs get goals at once)."""
        old = self.n_envs
        if n_envs <= old:
            return
        extra = n_envs - old
        self._goal_obs = np.concatenate([self._goal_obs, np.zeros((extra, *self._goal_obs.shape[1:]), dtype=self._goal_obs.dtype)])
        self._has_goals = np.concatenate([self._has_goals, np.zeros(extra, dtype=bool)])
        self._goal_parts = th.cat([self._goal_parts, th.zeros(extra, *self._goal_parts.shape[1:])])
        self._goal_version = np.concatenate([self._goal_version, np.zeros(extra, dtype=np.int64)])
        self._episode_ids = np.concatenate([self._episode_ids, np.arange(self._next_episode_id, self._next_episode_id + extra)])
        self._next_episode_id += extra
        self._episodes += [deque(maxlen=self.episode_memory) for _ in range(extra)]
        self._reward_cache += [{} for _ in range(extra)]
        self._visit_counts += [{} for _ in range(extra)]
        self._pending += [{} for _ in range(extra)]
        self.trajectories.ensure_envs(n_envs)
        self.normalizer.ensure_envs(n_envs)
        self.n_envs = n_envs
        self.sample_goals(np.arange(old, n_envs))

    def begin_episodes(self, env_indices: np.ndarray, observations: Any = None, background: bool = False) -> None:
        """Start new episodes in ``env_indices``: a finished episode (while recording) is queued for goal
        selection, and the new episode gets a fresh id and K fresh goals.

        :param observations: the new episodes' first observations, one per env of ``env_indices`` (recorded with
            ``record_start_states``, ignored otherwise)
        :param background: score them in the worker, as :meth:`submit`
        """
        self._await_overlapped_update()  # steps queued behind an update come first
        env_indices = np.asarray(env_indices, dtype=np.int64)
        if len(env_indices):
            self.ensure_envs(int(env_indices.max()) + 1)
        record = observations is not None and self.record_start_states
        self._start_episodes(env_indices, self.adapter.extract(observations) if record else None, background)

    def _start_episodes(self, env_indices: np.ndarray, starts: np.ndarray | None, background: bool) -> None:
        """:meth:`begin_episodes` with the first observations already extracted (raw rows, or None)."""
        for e in env_indices:
            self._unrecorded_starts.pop(int(e), None)  # its episode is over
            if self.recording and len(self._episodes[e]):
                self.finished_episodes.append(np.stack(self._episodes[e]))
            self._episodes[e].clear()
            self._visit_counts[e].clear()
            self._pending[e].clear()
            self._episode_ids[e] = self._next_episode_id
            self._next_episode_id += 1
        if len(env_indices):
            self.sample_goals(env_indices)
        if starts is not None and self.record_start_states and len(env_indices):
            if self.recording:
                self._record_starts(starts, env_indices, background)
            else:
                for j, e in enumerate(env_indices):
                    self._unrecorded_starts[int(e)] = starts[j].copy()

    def start_recording(self) -> None:
        """Switch recording on (a training callback's start), and record the first observations of the episodes
        begun while it was off that have taken no step since (``record_start_states``): SB3's ``learn`` resets the
        env before its callbacks start, so without this each ``learn`` after the first would miss one s_0 per env."""
        self._await_overlapped_update()
        self.recording = True
        if self._unrecorded_starts:
            env_indices = np.array(sorted(self._unrecorded_starts), dtype=np.int64)
            starts = np.stack([self._unrecorded_starts.pop(int(e)) for e in env_indices])
            self._record_starts(starts, env_indices, background=False)

    def _record_starts(self, starts: np.ndarray, env_indices: np.ndarray, background: bool) -> None:
        """Record and score the first observations of new episodes (raw rows): no reward, no env step."""
        self._submit(starts, np.zeros(len(env_indices), dtype=bool), env_indices, background, start=True)

    def register_env(self) -> int:
        """Add one env (for per-env wrappers sharing this module) and return its index."""
        self.ensure_envs(self.n_envs + 1)
        return self.n_envs - 1

    @th.inference_mode()
    def sample_goals(self, env_indices: np.ndarray) -> None:
        """Draw K goals from the goal buffer for a new episode of each env in ``env_indices`` (eq 11)."""
        self._await_overlapped_update()
        env_indices = np.asarray(env_indices, dtype=np.int64)
        if len(env_indices) == 0:
            return
        idx = self.goal_buffer.sample(len(env_indices), self.n_goals, self.rng)
        self._touch_goals(env_indices)
        for e in env_indices:
            self._reward_cache[e].clear()
        if idx.shape[1] == 0:
            self._has_goals[env_indices] = False
            return
        t_env = th.from_numpy(env_indices)
        self._goal_obs[env_indices] = self.goal_buffer.observations[idx]
        self._goal_parts[t_env] = self._folded.goal_part(self.goal_buffer.embeddings[th.from_numpy(idx)])
        self._has_goals[env_indices] = True

    @th.inference_mode()
    def _refresh_active_goals(self) -> None:
        """Recompute the goal halves of the active goals after the predictor or the VAE changed."""
        self._touch_goals(np.arange(self.n_envs))
        for e in range(self.n_envs):
            self._reward_cache[e].clear()
            if self._has_goals[e]:
                self._goal_parts[e] = self._folded.goal_part(self.embed(self._goal_obs[e]))

    def _touch_goals(self, env_indices: np.ndarray) -> None:
        """Mark the goal halves of ``env_indices`` as changed (a scoring process re-reads them)."""
        self._goal_stamp += 1
        self._goal_version[env_indices] = self._goal_stamp

    _key = staticmethod(observation_key)  # the memo key of a raw observation

    def _lookup(self, raw: np.ndarray, env_indices: np.ndarray, keys: list[bytes], ticket: "ScoringTicket | None" = None) -> "ScoringTicket":
        """Memo lookups of one observation per env (main thread): rewards known from the episode's memo, rows
        equal to a row still being scored (``pending``), and the rows to score (``miss``), with their phi. Into
        ``ticket`` (a queued one, as new) if given."""
        n = len(raw)
        if ticket is None:
            ticket = ScoringTicket(n, self.goal_buffer.embeddings.shape[1])
        ticket.env_indices, ticket.keys = env_indices, keys
        ticket.episode_ids = self._episode_ids[env_indices].copy()
        miss = []
        for j, (e, key) in enumerate(zip(env_indices, keys)):
            hit = self._reward_cache[e].get(key)
            if hit is not None:
                ticket.rewards[j], ticket.phi[j] = hit
                continue
            earlier = self._pending[e].get(key)
            if earlier is not None:  # seen earlier in this episode, its score (and maybe phi) not taken yet
                ticket.pending.append((j, earlier[0], earlier[1]))
                continue
            miss.append(j)
        self._cache_lookups += n
        self._cache_hits += n - len(miss)
        self.cache_lookups += n
        self.cache_hits += n - len(miss)
        if miss:
            m_idx = np.asarray(miss)
            ticket.miss = m_idx
            # phi: memoised until the next VAE update; an entry is (ticket, row) while that ticket embeds it
            todo = []
            for j in miss:
                hit = self._phi_cache.get(keys[j])
                if hit is None:
                    todo.append(j)
                elif isinstance(hit, tuple):
                    ticket.phi_from.append((j, *hit))
                else:
                    ticket.phi[j] = hit
            if todo:
                ticket.embed_rows = np.asarray(todo, dtype=np.int64)
                ticket.raw = raw[ticket.embed_rows]
                ticket.encoder = self._encoder
                if len(self._phi_cache) + len(todo) > self.embedding_cache_size:
                    self._phi_cache.clear()
                for j in todo:
                    self._phi_cache[keys[j]] = (ticket, j)
            ticket.has_goals = self._has_goals[env_indices[m_idx]]
            ticket.folded = self._folded
            for j in miss:
                self._pending[env_indices[j]][keys[j]] = (ticket, j)
        return ticket

    @th.inference_mode()
    def _compute(self, ticket: "ScoringTicket") -> np.ndarray:
        """phi of the ticket's ``embed_rows`` and eq 13 for its ``miss`` rows (pure: reads only what the ticket
        captured, writes only the ticket's own phi rows; any thread)."""
        t0, c0 = time.perf_counter(), time.thread_time()
        for j, earlier, row in ticket.phi_from:  # computed before this one (one worker, in order; or the caller)
            ticket.phi[j] = earlier.phi[row]
        phi = ticket.phi[ticket.miss]
        embed_pos = np.searchsorted(ticket.miss, ticket.embed_rows)
        r = score_rows(phi, embed_pos, ticket.raw, ticket.encoder, self._to_tensor, ticket.goal_parts, ticket.has_goals, ticket.folded, self._eq13_args)
        ticket.phi[ticket.miss] = phi
        ticket.compute_time = time.perf_counter() - t0
        ticket.compute_cpu_time = time.thread_time() - c0
        return r

    def _commit(self, ticket: "ScoringTicket", computed: np.ndarray) -> None:
        """Fill a ticket's rewards (main thread, in submission order) and memoise the scored rows in their
        episode's memo, unless that episode has ended since."""
        env_indices, keys = ticket.env_indices, ticket.keys
        if len(ticket.miss):
            ticket.rewards[ticket.miss] = computed
        for j, earlier, row in ticket.pending:
            ticket.rewards[j] = earlier.rewards[row]
            ticket.phi[j] = earlier.phi[row]
        for j in ticket.embed_rows:
            entry = self._phi_cache.get(keys[j])
            if isinstance(entry, tuple) and entry[0] is ticket and entry[1] == j:
                self._phi_cache[keys[j]] = th.from_numpy(ticket.phi[j].copy())
        ticket.raw = ticket.encoder = None
        for j, rj in zip(ticket.miss, ticket.rewards[ticket.miss]):
            e = env_indices[j]
            if self._pending[e].get(keys[j], (None,))[0] is ticket:
                del self._pending[e][keys[j]]
            if self._episode_ids[e] != ticket.episode_ids[j]:
                continue  # that episode is over: its memo was dropped
            cache = self._reward_cache[e]
            if len(cache) >= self.episode_memory:
                cache.clear()
            cache[keys[j]] = (rj, ticket.phi[j])

    def _count_visits(self, keys: list[bytes], env_indices: np.ndarray) -> np.ndarray:
        """Count this visit of each observation in its env's episode; returns n >= 1 (this visit included)."""
        visits = np.empty(len(keys), dtype=np.int64)
        for j, (e, key) in enumerate(zip(env_indices, keys)):
            counts = self._visit_counts[e]
            if key not in counts and len(counts) >= self.episode_memory:
                counts.clear()
            visits[j] = counts[key] = counts.get(key, 0) + 1
        return visits

    # ------------------------------------------------------------------ the step
    def step(
        self, observations: Any, dones: np.ndarray, env_indices: np.ndarray | None = None, next_observations: Any = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Curiosity reward of the states just reached, one per env.

        :param observations: batch of observations s_{t+1} (for an env whose episode just ended: its terminal
            observation, not the reset one)
        :param dones: whether each env's episode ended with this observation; such envs get new goals
        :param env_indices: which envs the rows belong to (default: 0..n-1)
        :param next_observations: the batch the envs go on from (a VecEnv's: the reset observation where an episode
            ended), so that ``record_start_states`` records the new episodes' first observations; None: not recorded
        :return: raw r_gc (eq 13, times the revisit factor of ``revisit_decay``) and normalised r_gc (eq 14),
            float32 arrays of shape (n,)
        """
        return self.collect(self.submit(observations, dones, env_indices, background=False, next_observations=next_observations))

    def submit(
        self,
        observations: Any,
        dones: np.ndarray,
        env_indices: np.ndarray | None = None,
        background: bool = True,
        next_observations: Any = None,
    ) -> "ScoringTicket":
        """First half of :meth:`step`: everything but the VAE's embedding and the predictor's scoring of the states
        new to their episode (and to the embedding memo), which run in a worker thread (``background=True``) while the caller goes on (e.g. steps the envs again). Take the
        rewards with :meth:`collect`, in the order of submission; :meth:`step` is ``collect(submit(...))``.
        The values are the same either way: the states scored together are the same, and every update of the
        module's state (memo, normaliser, statistics) happens in the caller's thread in submission order.
        ``next_observations``: as for :meth:`step`.
        """
        raw = self.adapter.extract(observations)
        env_indices = np.arange(len(raw)) if env_indices is None else np.asarray(env_indices, dtype=np.int64)
        dones = np.asarray(dones, dtype=bool)
        record = next_observations is not None and self.record_start_states and dones.any()
        starts = self.adapter.extract(next_observations)[dones] if record else None
        if background and self._queueing():
            ticket = ScoringTicket(len(raw), self.goal_buffer.embeddings.shape[1])
            # copies: the env may reuse its buffers before the step is submitted
            ticket.queued = (np.array(raw, copy=True), dones.copy(), env_indices.copy(), None if starts is None else np.array(starts, copy=True))
            self._queue.append(ticket)
            self.queued_steps += 1
            return ticket
        return self._submit_step(raw, dones, env_indices, starts, background)

    def _submit_step(
        self, raw: np.ndarray, dones: np.ndarray, env_indices: np.ndarray, starts: np.ndarray | None, background: bool, ticket: "ScoringTicket | None" = None
    ) -> "ScoringTicket":
        """:meth:`submit` of extracted rows (``starts``: the first observations of the episodes that begin, or None);
        ``ticket``: a queued ticket to fill."""
        ticket = self._submit(raw, dones, env_indices, background, ticket=ticket)
        self._start_episodes(env_indices[dones], starts, background)
        return ticket

    def _queueing(self) -> bool:
        """Whether a background submission goes to the queue (``queue_during_update``): an update overlapped with
        PPO's still runs. Once it is done, it is taken into use and the queue submitted, and this is False."""
        if not self.queue_during_update:
            return False
        if self._job is not None and self._job_until_next_use and not self._job.finished.is_set():
            return True
        self._await_overlapped_update()
        return False

    def _submit(
        self, raw: np.ndarray, dones: np.ndarray, env_indices: np.ndarray, background: bool, start: bool = False, ticket: "ScoringTicket | None" = None
    ) -> "ScoringTicket":
        """:meth:`submit` of raw rows, without starting the episodes that end; ``start``: the rows are the first
        observations of new episodes (``record_start_states``): recorded and scored, but no env step; ``ticket``: a
        queued ticket to fill."""
        self._await_overlapped_update()
        t0 = time.perf_counter()
        n = len(raw)
        self.ensure_envs(int(env_indices.max()) + 1)
        if self._unrecorded_starts and not start:  # these episodes go on unrecorded: their s_0 stays so
            for e in env_indices:
                self._unrecorded_starts.pop(int(e), None)
        keys = [self._key(x) for x in raw]
        ticket = self._lookup(raw, env_indices, keys, ticket)
        ticket.recording = self.recording
        ticket.start = start
        if self.recording and self.trajectories.keeps_observations:
            ticket.observations = np.array(raw, copy=True)
        if self.revisit_decay != "none":
            ticket.factor = revisit_factor(self._count_visits(keys, env_indices), self.revisit_decay)
        if self.recording:
            self.memory.add(raw, self.rng)
            for j, e in enumerate(env_indices):
                self._episodes[e].append(raw[j].copy())
            if not start:
                self.n_recorded_steps += n
        if len(ticket.miss) and background and self.scoring_process and not self._spill(ticket):
            # the process keeps each env's goal halves: it is sent those changed since it last had them
            ticket.future = self.start_scoring_process().submit(ticket, self._eq13_args, self._goal_parts, self._goal_version)
        elif len(ticket.miss):
            background = background and not self.scoring_process  # a spilled ticket is scored here, now
            # a copy (indexing) of the episodes' goal halves: a new episode may start before scoring
            ticket.goal_parts = self._goal_parts[th.from_numpy(env_indices[ticket.miss])]
            if background:
                if self._scorer is None:
                    self._scorer = ThreadPoolExecutor(max_workers=1, thread_name_prefix="gocu-score")
                ticket.future = self._scorer.submit(self._compute, ticket)
            else:  # now, so that a later ticket may read this one's phi
                for _, earlier, _ in ticket.phi_from:
                    if earlier.future is not None:
                        earlier.future.result()
                ticket.computed = self._compute(ticket)
        self._outstanding.append(ticket)
        self.time_inference += time.perf_counter() - t0
        return ticket

    def _spill(self, ticket: "ScoringTicket") -> bool:
        """Whether to score this ticket in the caller rather than send it to the scoring process
        (``scoring_spill``): the process has that many tickets unanswered, or so many answers due that sending
        would first wait for one, and none of them holds a state this ticket takes its phi from."""
        if self.scoring_spill is None or self._process is None:
            return False
        if self._process.unanswered() < self.scoring_spill and not self._process.would_wait(ticket):
            return False
        if any(earlier.future is not None and not earlier.future.done() for _, earlier, _ in ticket.phi_from):
            return False
        self.spilled_tickets += 1
        return True

    def start_scoring_process(self) -> ProcessScorer:
        """Start the scoring process now, if ``scoring_process`` and not started yet (it takes a few seconds to
        start, beside whatever the caller does meanwhile; :meth:`submit` starts it otherwise)."""
        if not self.scoring_process:
            raise ValueError("start_scoring_process: this module scores in a thread (scoring_process=False)")
        if self._process is None:
            self._process = ProcessScorer(self._to_tensor)
        return self._process

    def collect(self, ticket: "ScoringTicket") -> tuple[np.ndarray, np.ndarray]:
        """Second half of :meth:`step`: the raw and normalised rewards of a ticket from :meth:`submit`. Tickets
        are taken in submission order (taking one takes the earlier ones first); taking one twice returns the
        same arrays."""
        if ticket.result is not None:
            return ticket.result
        if ticket.queued is not None:
            self._await_overlapped_update()  # waits for the update, then submits the queue
        while self._outstanding and self._outstanding[0] is not ticket:
            self.collect(self._outstanding[0])
        if not self._outstanding:
            raise ValueError("this scoring ticket does not belong to this module")
        t0 = time.perf_counter()
        self._outstanding.popleft()
        if not len(ticket.miss):
            computed = np.zeros(0, dtype=np.float32)
        elif ticket.future is not None:
            t_wait = time.perf_counter()
            computed = ticket.future.result()
            self.time_scoring_wait += time.perf_counter() - t_wait
            self.time_inference_background += ticket.compute_time
            self.cpu_inference_background += ticket.compute_cpu_time
        else:
            computed = ticket.computed
        self._commit(ticket, computed)
        if ticket.recording:  # phi of every row is known now
            self.trajectories.add(th.from_numpy(ticket.phi), ticket.episode_ids, ticket.env_indices, ticket.observations)
        rewards = ticket.rewards
        if ticket.start:  # first observations of episodes: no reward to pay, normalise or count
            ticket.result = (rewards, np.zeros_like(rewards))
            self.time_inference += time.perf_counter() - t0
            return ticket.result
        if not np.all(np.isfinite(rewards)):
            # a broken network must not poison the policy's buffer: no bonus for these states
            self.stats["nonfinite_rewards"] = self.stats.get("nonfinite_rewards", 0) + int((~np.isfinite(rewards)).sum())
            rewards = np.where(np.isfinite(rewards), rewards, 0.0).astype(np.float32)
        if ticket.factor is not None:
            rewards = rewards * ticket.factor
        normalized = self.normalizer(rewards, ticket.env_indices, update=ticket.recording)
        if ticket.recording:
            self._reward_sum += float(rewards.sum())
            self._reward_sq_sum += float((rewards.astype(np.float64) ** 2).sum())
            self._reward_count += len(rewards)
        ticket.result = (rewards, normalized)
        self.time_inference += time.perf_counter() - t0
        return ticket.result

    def collect_all(self) -> None:
        """Take every outstanding ticket (before the networks, the goals or the state change hands), the queued ones
        included (which waits for the update they are queued behind)."""
        if self._queue and not self._holding_queue:
            self._await_overlapped_update()
        while self._outstanding:
            self.collect(self._outstanding[0])

    # ------------------------------------------------------------------ learning
    def add_finished_episode_goals(self) -> int:
        """Add goals from every episode finished since the last call (final state + l by the strategy).

        :return: number of goals added (after the novelty filter)
        """
        self._await_overlapped_update()
        added = 0
        while self.finished_episodes:
            episode = self.finished_episodes.popleft()
            steps = select_goal_steps(len(episode), self.new_goals_per_episode, self.goal_strategy, self.rng)
            candidates = episode[steps]
            added += self.goal_buffer.add(candidates, self.embed(candidates), self.rng)
        return added

    def _sync_encoder(self) -> None:
        """Inference embeds with a frozen copy of the VAE, so the VAE itself can train while steps go on."""
        self._encoder = copy.deepcopy(self.vae).eval().requires_grad_(False)

    def _update_thread_count(self) -> int:
        """Torch threads of an update prepared now (call it in the caller's thread; see ``update_threads``)."""
        caller = th.get_num_threads()  # also fixes the caller's count before an update thread changes torch's default
        return caller if self.update_threads is None else self.update_threads

    def _shard_threads(self) -> int:
        """Threads that run the parts of a sharded VAE step (``vae_shards``)."""
        if self.update_threads is not None:
            return min(self.update_threads, self.vae_shards)
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
        return max(1, min(self.vae_shards, cores))

    def _train_autocast(self, enabled: bool | None = None) -> th.autocast:
        """The mixed-precision context of the updates' forward passes (``train_dtype``).

        :param enabled: None: enabled unless ``train_dtype`` is float32"""
        enabled = self.train_dtype != "float32" if enabled is None else enabled
        return th.autocast(self.device.type, dtype=DTYPES[self.train_dtype], enabled=enabled)

    def _run_parts(self, parts: list[Callable[[], Any]]) -> list[Any]:
        """Run callables with 1 torch thread each, the first in the calling thread and the others in the shard
        pool (``_shard_threads`` threads in all); their results in order. Grad mode and autocast are the
        caller's in every thread (they are thread-local in torch)."""
        grad = th.is_grad_enabled()
        autocast = th.is_autocast_enabled(self.device.type)

        def one(fn: Callable[[], Any]) -> Any:
            with torch_threads(1), th.set_grad_enabled(grad), self._train_autocast(autocast):
                return fn()

        workers = self._shard_threads() - 1
        if workers < 1 or len(parts) == 1:
            return [one(fn) for fn in parts]
        if self._shard_pool is None or self._shard_pool_workers != workers:  # update_threads may have been set since
            if self._shard_pool is not None:
                self._shard_pool.shutdown(wait=True)
            self._shard_pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="gocu-vae-part")
            self._shard_pool_workers = workers
        futures = [self._shard_pool.submit(one, fn) for fn in parts[1:]]
        try:
            first = one(parts[0])
        finally:
            rest = [f.result() for f in futures]  # every part ends before the weights move on
        return [first, *rest]

    def _splits(self, threads: int, vae: bool = False) -> bool:
        """Whether an update run with ``threads`` torch threads splits its products (``split_updates``): not with
        more than one thread, bfloat16 training, or a sharded VAE step."""
        return self.split_updates and threads == 1 and self.train_dtype == "float32" and not (vae and self.vae_shards > 1)

    def _split_work(self, vae: bool = False) -> SplitWork | None:
        """Where an update's split products post their second halves (call it in the fit's thread, with the fit's
        torch threads set), or None: the products stay whole (:meth:`_splits`)."""
        return self._split if self._splits(th.get_num_threads(), vae) else None

    def _helped(self, fit: Callable[[], Any]) -> Any:
        """``fit()`` for an update run in place (pretraining, ``train_vae``, ``train_predictor``, no
        ``overlap_ppo_update``): with ``split_updates`` it runs in a thread of its own while this thread
        computes halves of its products (the values are the same either way)."""
        if not self._splits(self._update_thread_count()):
            return fit()
        out: dict[str, Any] = {}
        finished = threading.Event()

        def body() -> None:
            try:
                out["fit"] = fit()
            except BaseException as error:
                out["error"] = error
            finally:
                finished.set()
                self._split.wake()

        thread = threading.Thread(target=body, name="gocu-update", daemon=True)
        thread.start()
        self._split.help(finished)
        thread.join()
        if "error" in out:
            raise out["error"]
        return out["fit"]

    # VAE update: prepare (caller's thread) -> fit (any thread) -> finish (caller's thread)
    def _prepare_vae(self, epochs: int | None, patience: int | None = None) -> dict[str, Any] | None:
        epochs = self.vae_epochs if epochs is None else epochs
        patience = self.vae_patience if patience is None else patience
        data = self.memory.observations[: self.memory.size].copy()
        if len(data) == 0 or epochs == 0:
            return None
        weights = np.ones(len(data), dtype=np.float32)
        if self.vae_dedupe:
            first, inverse = distinct_rows(data)
            data = data[first]
            c = np.bincount(inverse, minlength=len(first)).astype(np.float64)
            weights = (c * len(c) / c.sum()).astype(np.float32)
        self.last_vae_update = self.n_recorded_steps
        job: dict[str, Any] = {"data": data, "weights": weights, "epochs": epochs, "threads": self._update_thread_count(), "patience": patience}
        if self.vae_pixel_weighting > 0:  # fitted to all the update's observations, the held-out ones included
            job["pixel_weights"] = PixelWeights.fit_observations(data, weights, self.adapter.to_tensor, self.vae_pixel_weighting)
        n_val = int(round(self.vae_holdout * len(data)))
        if patience > 0 and n_val >= 1:
            order = self.rng.permutation(len(data))
            val, train = np.sort(order[:n_val]), np.sort(order[n_val:])
            job.update(data=data[train], weights=weights[train], val_data=data[val], val_weights=weights[val])
        return job

    def _prepare_vae_update(self, epochs: int | None, patience: int | None = None) -> dict[str, Any] | None:
        """A VAE update's job (:meth:`_prepare_vae`) and, with ``refit_predictor_after_vae``, the predictor's
        retraining after it (``"refit"``: pairs drawn now from a copy of the trajectory store). Run it with
        :meth:`_fit_vae_job`, take it into use with :meth:`_finish_vae`."""
        job = self._prepare_vae(epochs, patience)
        if job is not None and self.refit_predictor_after_vae:
            self.collect_all()  # the trajectory store takes a state's phi when its ticket is collected
            draw = self.trajectories.draw_pairs(self.predictor_pairs, self.max_distance, self.rng, first_visit=self.first_visit_distance)
            self.last_predictor_update = self.n_recorded_steps
            job["refit"] = {"store": self.trajectories.copy(), "draw": draw} if len(draw[0]) >= 2 else None
        return job

    def _fit_vae_job(self, job: dict[str, Any]) -> dict[str, Any]:
        """Fit the VAE (any thread); then, with a ``"refit"``, embed the copied trajectory store with the fitted VAE
        (when it changed) and fit the predictor to the drawn pairs' new embeddings (``fit["refit"]``)."""
        fit = self._fit_vae(**{k: v for k, v in job.items() if k != "refit"})
        refit = job.get("refit")
        if refit is not None:
            with torch_threads(job["threads"]):
                t0 = time.perf_counter()
                store: TrajectoryStore = refit["store"]
                embeddings = store.embedded(functools.partial(self.embed, encoder=self.vae)) if fit["best_epoch"] > 0 else None
                fit["time"] += time.perf_counter() - t0  # the VAE's cost
                pairs = self._predictor_job(*store.pairs(refit["draw"], embeddings), job["threads"])
                fit["refit"] = {"embeddings": embeddings, "count": store.count,
                                "fit": None if pairs is None else self._fit_predictor(**pairs)}
        return fit

    @th.no_grad()
    def _vae_val_loss(self, data: np.ndarray, weights: np.ndarray, pixel_weights: PixelWeights | None = None) -> float:
        """Loss of eq 8 (weighted mean, eval mode: z = mu) on held-out observations (by chunks of 1024; with
        ``vae_shards`` > 1 the chunks run as parts, see :meth:`_run_parts`)."""
        was_training = self.vae.training
        self.vae.eval()

        def chunk(start: int) -> float:
            x = self.adapter.to_tensor(data[start : start + 1024], self.device)
            w = th.from_numpy(weights[start : start + 1024]).to(self.device)
            return float(vae_loss(self.vae, x, self.vae_beta, w, pixel_weights=pixel_weights)[0]) * len(x)

        starts = range(0, len(data), 1024)
        if self.vae_shards > 1:
            sums = self._run_parts([functools.partial(chunk, start) for start in starts])
        else:
            sums = [chunk(start) for start in starts]
        self.vae.train(was_training)
        return sum(sums, 0.0) / len(data)

    def _vae_step(self, x: th.Tensor, w: th.Tensor, pixel_weights: PixelWeights | None = None) -> tuple[bool, float]:
        """One optimiser step of the VAE on a minibatch (``vae_shards``); whether it stepped, and the loss."""
        grads = None
        with self._train_autocast():  # _run_parts carries it into the parts' threads
            if self.vae_shards == 1:
                loss, _, _ = vae_loss(self.vae, x, self.vae_beta, w, generator=self._torch_gen, pixel_weights=pixel_weights)
            else:
                loss, grads = sharded_vae_gradients(
                    self.vae, x, self.vae_beta, w, self._torch_gen, self.vae_shards, self._run_parts, pixel_weights
                )
        return self._guarded_step(self.vae, self.vae_optimizer, loss, grads), float(loss.detach())

    def _fit_vae(
        self,
        data: np.ndarray,
        weights: np.ndarray,
        epochs: int,
        val_data: np.ndarray | None = None,
        val_weights: np.ndarray | None = None,
        on_epoch: Callable[[int], None] | None = None,
        threads: int | None = None,
        patience: int | None = None,
        pixel_weights: PixelWeights | None = None,
    ) -> dict[str, Any]:
        """Fit the VAE (eq 8) to ``data`` (weighted by multiplicity) for at most ``epochs`` epochs.

        :param val_data: held-out observations for early stopping (``vae_patience``); None: all ``epochs`` epochs
        :param val_weights: their multiplicities
        :param on_epoch: called with the epoch number after each epoch (the VAE is in train mode), for probes
        :param threads: torch threads of the fit (None: the calling thread's)
        :param patience: early stopping's patience (None: ``vae_patience``)
        :param pixel_weights: weights of the pixels in the reconstruction term, of training and held-out loss alike
            (``vae_pixel_weighting``; None: all 1)
        """
        patience = self.vae_patience if patience is None else patience
        with torch_threads(threads), splitting(self._split_work(vae=True)):
            t0 = time.perf_counter()
            snapshot = self._snapshot(self.vae, self.vae_optimizer)
            early = val_data is not None and val_weights is not None and patience > 0
            start_loss = self._vae_val_loss(val_data, val_weights, pixel_weights) if early else float("nan")
            stopping, best_state = EarlyStopping(start_loss, patience), None
            self.vae.train()
            losses, skipped = [], 0
            n = len(data)
            epoch = -1
            for epoch in range(epochs):
                order = th.randperm(n, generator=self._torch_gen).numpy()
                for start in range(0, n, self.vae_batch_size):
                    idx = order[start : start + self.vae_batch_size]
                    x = self.adapter.to_tensor(data[idx], self.device)
                    w = th.from_numpy(weights[idx]).to(self.device)
                    stepped, loss_value = self._vae_step(x, w, pixel_weights)
                    if not stepped:
                        skipped += 1
                        continue
                    losses.append(loss_value)
                if on_epoch is not None:
                    on_epoch(epoch)
                if early:
                    if stopping.update(epoch + 1, self._vae_val_loss(val_data, val_weights, pixel_weights)):
                        best_state = copy.deepcopy(self.vae.state_dict())
                    elif stopping.stop:
                        break
            epochs_run = epoch + 1
            if early and stopping.best_epoch < epochs_run:  # keep the best epoch's weights (the starting ones if none beat them)
                self.vae.load_state_dict(best_state if best_state is not None else snapshot[0])
            self.vae.eval()
            return {"snapshot": snapshot, "losses": losses, "skipped": skipped, "n": n + (0 if val_data is None else len(val_data)),
                    "time": time.perf_counter() - t0, "epochs_run": epochs_run,
                    "best_epoch": stopping.best_epoch if early else epochs_run, "val_loss_start": start_loss,
                    "val_loss": stopping.best_loss}

    def _finish_vae(self, fit: dict[str, Any]) -> dict[str, float]:
        self.collect_all()
        t0 = time.perf_counter()
        rolled_back = self._guard_update("vae", self.vae, self.vae_optimizer, fit["snapshot"], fit["skipped"])
        refit = fit.get("refit")
        if fit["best_epoch"] > 0:  # otherwise the VAE kept its weights: every embedding is still valid
            self._sync_encoder()
            self._phi_cache.clear()
            self.goal_buffer.refresh(self.embed)
            if not self.refit_predictor_after_vae:
                self.trajectories.clear()  # stored embeddings belong to the old encoder
            elif not rolled_back:  # the store's embeddings, renewed (rolled back: the old encoder's are still valid)
                renewed = refit is not None and refit["embeddings"] is not None and np.array_equal(refit["count"], self.trajectories.count)
                self.trajectories.embeddings = refit["embeddings"] if renewed else self.trajectories.embedded(self.embed)
            self._refresh_active_goals()
        dt = fit["time"] + time.perf_counter() - t0
        self.time_training += dt
        self.time_vae += dt
        out = {
            "vae_loss": float(np.mean(fit["losses"])) if fit["losses"] else float("nan"),
            "vae_distinct_observations": float(fit["n"]),
            "vae_skipped_updates": float(fit["skipped"]),
            "vae_epochs_run": float(fit["epochs_run"]),
            "vae_best_epoch": float(fit["best_epoch"]),
            "vae_val_loss": fit["val_loss"],
            "vae_time": dt,
        }
        self.stats.update(out)
        if refit is not None and refit["fit"] is not None:
            if rolled_back:  # fitted to the embeddings of a VAE that is not kept
                self._restore(self.predictor, self.predictor_optimizer, refit["fit"]["snapshot"])
            else:
                out.update(self._finish_predictor(refit["fit"]))
        return out

    def train_vae(self, epochs: int | None = None, patience: int | None = None) -> dict[str, float]:
        """Train the VAE on the memory bank (eq 8), then re-embed goals and drop stale embeddings.

        :param epochs: passes over the memory bank (default ``vae_epochs``)
        :param patience: early stopping's patience (default ``vae_patience``; 0: all ``epochs``)
        :return: statistics of the update
        """
        self.finish_updates()
        job = self._prepare_vae_update(epochs, patience)
        return {} if job is None else self._finish_vae(self._helped(functools.partial(self._fit_vae_job, job)))

    def pretrain(self) -> dict[str, float]:
        """Train the VAE on what the memory bank holds (the random-policy observations) and mark the module
        pretrained."""
        out = self.train_vae(patience=self.vae_pretrain_patience)
        self.pretrained = True
        self.last_predictor_update = self.n_recorded_steps  # P_m counts from the first rollout
        self._recorded_at_last_train = self.n_recorded_steps
        return out

    # predictor update: prepare (caller's thread) -> fit (any thread) -> finish (caller's thread)
    def _prepare_predictor(self) -> dict[str, Any] | None:
        self.collect_all()  # the trajectory store takes a state's phi when its ticket is collected
        phi_s, phi_g, dist = self.trajectories.sample_pairs(
            self.predictor_pairs, self.max_distance, self.rng, first_visit=self.first_visit_distance
        )
        self.last_predictor_update = self.n_recorded_steps
        return self._predictor_job(phi_s, phi_g, dist, self._update_thread_count())

    def _predictor_job(self, phi_s: th.Tensor, phi_g: th.Tensor, dist: th.Tensor, threads: int) -> dict[str, Any] | None:
        """The arguments of :meth:`_fit_predictor` for drawn pairs: non-finite embeddings dropped, duplicates merged
        (``predictor_dedupe``); None when fewer than two pairs are left."""
        keep = th.isfinite(phi_s).all(1) & th.isfinite(phi_g).all(1)  # a broken VAE's embeddings teach nothing
        phi_s, phi_g, dist = phi_s[keep], phi_g[keep], dist[keep]
        if len(phi_s) < 2:
            return None
        drawn = len(phi_s)
        weights = th.ones(drawn)
        if self.predictor_dedupe:
            rows = np.ascontiguousarray(th.cat([phi_s, phi_g, dist[:, None]], dim=1).numpy())
            _, first, counts = np.unique(rows.view(np.dtype((np.void, rows.itemsize * rows.shape[1]))).ravel(), return_index=True, return_counts=True)
            if len(first) < 2:
                first, counts = np.arange(drawn), np.ones(drawn, dtype=np.int64)
            first = th.from_numpy(first)
            phi_s, phi_g, dist = phi_s[first], phi_g[first], dist[first]
            weights = th.from_numpy(counts * (len(counts) / counts.sum())).float()  # mean 1 over the distinct pairs
        return {"phi_s": phi_s.to(self.device), "phi_g": phi_g.to(self.device), "dist": dist.to(self.device),
                "weights": weights.to(self.device), "drawn": drawn, "threads": threads}

    @th.no_grad()
    def label_pairs(self, phi_s: th.Tensor, phi_g: th.Tensor, dist: th.Tensor) -> th.Tensor:
        """p_skill of eq 15-16 for each pair, with the predictor's current belief as the prior (decision 1:
        ``prior = 1 - m(phi(s), phi(g))``, the belief that the skill is *not* mastered)."""
        prior = 1.0 - self.predictor.mastery(phi_s, phi_g)
        return mastered_probability(complexity_score(prior, dist, self.prior_weight, self.distance_weight), self.label_threshold, self.label_slope)

    def _fit_predictor(
        self,
        phi_s: th.Tensor,
        phi_g: th.Tensor,
        dist: th.Tensor,
        weights: th.Tensor | None = None,
        drawn: int | None = None,
        on_epoch: Callable[[int], None] | None = None,
        threads: int | None = None,
        before_step: Callable[[], Any] | None = None,
    ) -> dict[str, Any]:
        """Label the pairs (eq 15-16) and fit the predictor to them for ``predictor_epochs`` epochs.

        :param weights: multiplicity of each pair, mean 1 (the loss of a minibatch is the mean of weight x cross-entropy)
        :param drawn: pairs drawn before de-duplication (for the statistics)
        :param on_epoch: called with the epoch number after each epoch (the predictor is in train mode), for probes
        :param threads: torch threads of the fit (None: the calling thread's)
        :param before_step: called before each minibatch (a lead update waits there while a rollout runs)
        """
        with torch_threads(threads), splitting(self._split_work()):
            t0 = time.perf_counter()
            p_skill = self.label_pairs(phi_s, phi_g, dist)
            target = p_skill if self.soft_labels else th.bernoulli(p_skill.nan_to_num(0.5), generator=self._torch_gen)
            snapshot = self._snapshot(self.predictor, self.predictor_optimizer)
            self.predictor.train()
            n = len(phi_s)
            weights = th.ones(n, device=phi_s.device) if weights is None else weights
            losses, accs, skipped = [], [], 0
            for epoch in range(self.predictor_epochs):
                order = th.randperm(n, generator=self._torch_gen)
                for start in range(0, n, self.predictor_batch_size):
                    idx = order[start : start + self.predictor_batch_size]
                    if len(idx) < 2:  # batch norm needs two samples
                        continue
                    if before_step is not None:
                        before_step()
                    with self._train_autocast():
                        logits = self.predictor(phi_s[idx], phi_g[idx])
                    t, w = target[idx], weights[idx]
                    loss, logp = mastery_loss(logits, t, w)
                    if not self._guarded_step(self.predictor, self.predictor_optimizer, loss):
                        skipped += 1
                        continue
                    losses.append(loss.item())
                    accs.append(float((w * ((logp[:, 1] > logp[:, 0]) == (t > 0.5)).float()).sum() / w.sum()))
                if on_epoch is not None:
                    on_epoch(epoch)
            self.predictor.eval()
            return {"snapshot": snapshot, "losses": losses, "accs": accs, "skipped": skipped, "n": n,
                    "drawn": n if drawn is None else drawn,
                    "mastered": float((weights * (p_skill > 0.5).float()).sum() / weights.sum()), "time": time.perf_counter() - t0}

    def _finish_predictor(self, fit: dict[str, Any]) -> dict[str, float]:
        self.collect_all()  # scores in flight belong to the old predictor
        t0 = time.perf_counter()
        self._guard_update("predictor", self.predictor, self.predictor_optimizer, fit["snapshot"], fit["skipped"])
        self._folded = self._fold()
        self._refresh_active_goals()
        dt = fit["time"] + time.perf_counter() - t0
        self.time_training += dt
        self.time_predictor += dt
        out = {
            "predictor_loss": float(np.mean(fit["losses"])) if fit["losses"] else float("nan"),
            "predictor_accuracy": float(np.mean(fit["accs"])) if fit["accs"] else float("nan"),
            "mastered_fraction": fit["mastered"],
            "predictor_pairs": float(fit["drawn"]),
            "predictor_distinct_pairs": float(fit["n"]),
            "predictor_skipped_updates": float(fit["skipped"]),
            "predictor_time": dt,
        }
        self.stats.update(out)
        return out

    def train_predictor(self) -> dict[str, float]:
        """Draw pairs (s_t, s_{t+y}), label them with eq 15-16 and train the predictor.

        :return: statistics of the update (loss, accuracy against the labels, fraction labelled mastered)
        """
        self.finish_updates()
        job = self._prepare_predictor()
        return {} if job is None else self._finish_predictor(self._helped(functools.partial(self._fit_predictor, **job)))

    # scheduling
    def maybe_train(self) -> dict[str, float]:
        """Add goals from finished episodes, and retrain the predictor every ``predictor_train_freq`` and the
        VAE every ``vae_train_freq`` recorded steps. Call it between rollouts.

        With ``train_in_background``, an update due now starts in a background thread and is taken into use
        at the next call (which waits for it if it is not done). With ``overlap_ppo_update`` (and not
        ``train_in_background``), it starts in a background thread and is taken into use before the module is
        next used; its statistics come out of the next call."""
        out: dict[str, float] = self._unreported
        self._unreported = {}
        out.update(self.finish_background_update())
        out["goals_added"] = float(self.add_finished_episode_goals())
        rollout = self.n_recorded_steps - self._recorded_at_last_train  # recorded steps of the rollout just ended
        self._recorded_at_last_train = self.n_recorded_steps
        # predictor first: a VAE update makes the stored embeddings (the predictor's pairs) stale; with
        # refit_predictor_after_vae the VAE's job retrains the predictor after it instead
        jobs: list[tuple[str, dict[str, Any]]] = []
        vae_due = self.n_recorded_steps - self.last_vae_update >= self.vae_train_freq
        refit = vae_due and self.refit_predictor_after_vae
        predictor_due = not refit and self.n_recorded_steps - self.last_predictor_update >= self.predictor_train_freq
        if predictor_due and self._lead is not None:  # started predictor_lead rollouts ago: now it may run on
            jobs.append(("lead", self._lead))
            self._lead = None
            self._lead_gate.set()
            self.last_predictor_update = self.n_recorded_steps
        elif predictor_due:
            job = self._prepare_predictor()
            if job is not None:
                jobs.append(("predictor", job))
        if vae_due:
            job = self._prepare_vae_update(None)
            if job is not None:
                jobs.append(("vae", job))
        if self.predictor_lead and self._lead is None and not (predictor_due or vae_due) and rollout > 0:
            self._maybe_start_lead(self.n_recorded_steps + self.predictor_lead * rollout)
        if self._lead is not None:
            self._lead_gate.set()  # it runs beside PPO's update, until the next rollout uses the module
        if not jobs:
            return out
        if not (self.train_in_background or self.overlap_ppo_update):
            for name, job in jobs:
                out.update(self._run_job(name, job))
            return out
        self._job_until_next_use = not self.train_in_background
        self._job = FitThread("gocu-update", functools.partial(self._fit_jobs, jobs), self._split.wake)
        return out

    def _maybe_start_lead(self, ahead: int) -> None:
        """Start the predictor update due by ``ahead`` recorded steps (``predictor_lead``), unless a VAE update
        falls due by then (its pairs would be embedded by the VAE before it)."""
        if ahead - self.last_predictor_update < self.predictor_train_freq or ahead - self.last_vae_update >= self.vae_train_freq:
            return
        last = self.last_predictor_update
        job = self._prepare_predictor()
        self.last_predictor_update = last  # due when it would be without a lead
        if job is None:
            return
        fit = functools.partial(self._fit_predictor, **job, before_step=self._lead_gate.wait)
        self._lead = FitThread("gocu-lead", lambda: [("predictor", fit())], self._split.wake)

    def finish_updates(self) -> dict[str, float]:
        """Wait for every update started by :meth:`maybe_train` (:meth:`finish_background_update`, and a
        predictor update started ahead of time, ``predictor_lead``) and take them into use.

        :return: statistics of those updates
        """
        out = self.finish_background_update()
        lead, self._lead = self._lead, None
        if lead is None:
            return out
        self._lead_gate.set()
        if self.split_updates:
            self._split.help(lead.finished)
        fits = lead.take()
        self.last_predictor_update = self.n_recorded_steps
        out.update(self._finish_fits(fits))
        return out

    def _fit_job(self, name: str, job: dict[str, Any]) -> dict[str, Any]:
        """Run a ``"predictor"`` or ``"vae"`` job's fit (not yet taken into use)."""
        return self._fit_predictor(**job) if name == "predictor" else self._fit_vae_job(job)

    def _run_job(self, name: str, job: dict[str, Any]) -> dict[str, float]:
        """Fit a job in place and take it into use."""
        return self._finish_fits([(name, self._helped(functools.partial(self._fit_job, name, job)))])

    def _fit_jobs(self, jobs: list[tuple[str, Any]]) -> list[tuple[str, dict[str, Any]]]:
        """The fits of an update started by :meth:`maybe_train`, in order (run in its :class:`FitThread`); a
        ``"lead"`` job is a predictor update started ahead of time, whose thread this waits for."""
        fits: list[tuple[str, dict[str, Any]]] = []
        for name, job in jobs:
            fits.extend(job.outcome() if name == "lead" else [(name, self._fit_job(name, job))])
        return fits

    def _finish_fits(self, fits: list[tuple[str, dict[str, Any]]]) -> dict[str, float]:
        """Take fits into use, in order (run in place or in a :class:`FitThread`)."""
        out: dict[str, float] = {}
        for name, fit in fits:
            out.update(self._finish_predictor(fit) if name == "predictor" else self._finish_vae(fit))
        return out

    @property
    def update_running(self) -> bool:
        """Whether an update started by :meth:`maybe_train` runs in the background (not yet taken into use)."""
        return self._job is not None

    def _await_overlapped_update(self) -> None:
        """Before the module is used again, take into use an update started by :meth:`maybe_train` with
        ``overlap_ppo_update`` (waiting for it if it still runs). A predictor update started ahead of time
        (``predictor_lead``) pauses meanwhile."""
        if self._lead is not None:
            self._lead_gate.clear()
        if self._job is not None and self._job_until_next_use:
            self._unreported.update(self.finish_background_update())
        elif self._queue and not self._holding_queue:
            self._submit_queue()

    def _submit_queue(self) -> None:
        """Submit the steps queued behind an update (``queue_during_update``), in order, now that it is in use."""
        self._holding_queue = True
        try:
            while self._queue:
                ticket = self._queue[0]
                raw, dones, env_indices, starts = ticket.queued  # type: ignore[misc]
                self._queue.popleft()
                ticket.queued = None
                self._submit_step(raw, dones, env_indices, starts, True, ticket)
        finally:
            self._holding_queue = False

    def finish_background_update(self) -> dict[str, float]:
        """Wait for a background update, if one runs, and take its networks into use.

        :return: statistics of that update (empty if none ran)
        """
        if self._job is None:
            return {}
        t0 = time.perf_counter()
        job = self._job
        if self.split_updates:
            self._split.help(job.finished)  # this thread computes halves of the update's products meanwhile
        job.thread.join()
        if self._job_until_next_use:
            self.time_update_wait += time.perf_counter() - t0
        self._job = None
        self._job_until_next_use = False
        fits = job.take()
        holding, self._holding_queue = self._holding_queue, True  # the queued steps meet the finished update
        try:
            out = self._finish_fits(fits)
        finally:
            self._holding_queue = holding
        if self._queue and not holding:
            self._submit_queue()
        return out

    def pop_reward_stats(self) -> dict[str, float]:
        """Mean and std of the raw r_gc recorded since the last call, and the other running figures."""
        out = {
            "goal_buffer_size": float(self.goal_buffer.size),
            "memory_size": float(self.memory.size),
            "return_std": self.normalizer.std,
            "cache_hit_rate": self._cache_hits / max(1, self._cache_lookups),
            "time_inference": self.time_inference,
            "time_training": self.time_training,
        }
        if self._reward_count:
            mean = self._reward_sum / self._reward_count
            out["reward_mean"] = mean
            out["reward_std"] = math.sqrt(max(0.0, self._reward_sq_sum / self._reward_count - mean**2))
        self._reward_sum = self._reward_sq_sum = 0.0
        self._reward_count = self._cache_hits = self._cache_lookups = 0
        return out

    # ------------------------------------------------------------------ non-finite guards
    @staticmethod
    def _snapshot(network: th.nn.Module, optimizer: th.optim.Optimizer) -> tuple[dict, dict]:
        """Copies of a network's and its optimiser's state, to roll a whole update back."""
        return copy.deepcopy(network.state_dict()), copy.deepcopy(optimizer.state_dict())

    @staticmethod
    def _restore(network: th.nn.Module, optimizer: th.optim.Optimizer, snapshot: tuple[dict, dict]) -> None:
        """Put a network and its optimiser back to a :meth:`_snapshot`."""
        network.load_state_dict(snapshot[0])
        optimizer.load_state_dict(snapshot[1])

    @staticmethod
    def _grads_finite(network: th.nn.Module) -> bool:
        """Whether every gradient of ``network`` is finite (a step on a NaN/inf gradient is skipped)."""
        grads = [p.grad for p in network.parameters() if p.grad is not None]
        # the 2-norm (fused over tensors) is non-finite iff some entry is (or squares overflow: a diverged step,
        # skipped too); 10x cheaper than the inf-norm, which cost a third of a predictor step
        return not grads or bool(th.isfinite(th.nn.utils.get_total_norm(grads, norm_type=2.0)))

    def _guarded_step(
        self, network: th.nn.Module, optimizer: th.optim.Optimizer, loss: th.Tensor, grads: Sequence[th.Tensor] | None = None
    ) -> bool:
        """One optimiser step on ``loss``, unless the loss or a gradient is non-finite; whether it stepped.

        :param grads: the gradient of ``loss``, one tensor per parameter of ``network`` in ``parameters()`` order,
            when computed already (e.g. by parts); None: by ``loss.backward()``
        """
        if not th.isfinite(loss):
            return False
        optimizer.zero_grad()
        if grads is None:
            loss.backward()
        else:
            for p, g in zip(network.parameters(), grads):
                p.grad = g
        if not self._grads_finite(network):
            return False
        optimizer.step()
        return True

    @staticmethod
    def nonfinite_entries(state: dict[str, th.Tensor]) -> list[str]:
        """Names of the floating-point tensors of a state_dict that hold a NaN or an infinity."""
        return [k for k, v in state.items() if isinstance(v, th.Tensor) and v.is_floating_point() and not bool(th.isfinite(v).all())]

    def _guard_update(self, name: str, network: th.nn.Module, optimizer: th.optim.Optimizer, snapshot: tuple[dict, dict], skipped: int) -> bool:
        """After an update of ``network``: count its skipped steps and, if its parameters or buffers are no longer
        finite, restore the state of before the update (network and optimiser).

        Counted in :attr:`stats` (logged as ``gocu/...`` by the callback): ``{name}_skipped_updates_total``
        (minibatch steps skipped for a non-finite loss or gradient, since construction), ``{name}_restored_updates``
        (updates rolled back) and ``{name}_nonfinite_parameters`` (tensors still non-finite: the network was
        broken before the update, e.g. set by hand; its rewards are then 0 and counted in ``nonfinite_rewards``).

        :return: whether the update was rolled back
        """
        self.stats[f"{name}_skipped_updates_total"] = self.stats.get(f"{name}_skipped_updates_total", 0.0) + skipped
        bad = self.nonfinite_entries(network.state_dict())
        self.stats[f"{name}_nonfinite_parameters"] = 0.0
        if not bad:
            return False
        if self.nonfinite_entries(snapshot[0]):
            self.stats[f"{name}_nonfinite_parameters"] = float(len(bad))
            warnings.warn(f"GoCu: the {name} holds non-finite values in {bad[:3]} from before this update; nothing finite to restore")
            return False
        self._restore(network, optimizer, snapshot)
        self.stats[f"{name}_restored_updates"] = self.stats.get(f"{name}_restored_updates", 0.0) + 1
        warnings.warn(f"GoCu: a {name} update made {bad[:3]} non-finite; the update was rolled back")
        return True

    # ------------------------------------------------------------------ persistence
    def state_dict(self) -> dict[str, Any]:
        """Everything the module learned and remembers, as tensors and plain Python values (loadable with
        ``torch.load(..., weights_only=True)``). A background update still running is waited for and taken
        into use first (:meth:`finish_updates`), and so are scores still being computed (:meth:`submit`)."""
        self.collect_all()
        self.finish_updates()
        return {
            "vae": self.vae.state_dict(),
            "vae_optimizer": self.vae_optimizer.state_dict(),
            "predictor": self.predictor.state_dict(),
            "predictor_optimizer": self.predictor_optimizer.state_dict(),
            "goal_buffer": self.goal_buffer.state_dict(),
            "memory": self.memory.state_dict(),
            "trajectories": self.trajectories.state_dict(),
            "normalizer": self.normalizer.state_dict(),
            "rng": self.rng.bit_generator.state,
            "torch_rng": self._torch_gen.get_state(),
            "envs": {
                "goal_obs": th.from_numpy(self._goal_obs.copy()),
                "goal_valid": th.from_numpy(self._has_goals.copy())[:, None].expand(-1, self.n_goals).clone(),
                "episode_ids": th.from_numpy(self._episode_ids.copy()),
                "episodes": [th.from_numpy(np.stack(ep)) if len(ep) else th.zeros(0) for ep in self._episodes],
                "finished_episodes": [th.from_numpy(ep) for ep in self.finished_episodes],
                "next_episode_id": self._next_episode_id,
                # memoised values: recomputing them in other batches can change the last bits (float sums are not
                # batch-invariant), so they are saved for a bit-exact resumption
                "goal_parts": self._goal_parts.clone(),
                "reward_cache": [_cache_to_state(c) for c in self._reward_cache],
                "visit_counts": [_counts_to_state(c) for c in self._visit_counts],
            },
            "phi_cache": _cache_to_state(self._phi_cache),
            # the loss the VAE trains with goes with the VAE, so a resumed run keeps it (see load_state_dict)
            "settings": {"vae_pixel_weighting": self.vae_pixel_weighting},
            "counters": {
                "pretrained": self.pretrained,
                "n_recorded_steps": self.n_recorded_steps,
                "last_vae_update": self.last_vae_update,
                "last_predictor_update": self.last_predictor_update,
                "recorded_at_last_train": self._recorded_at_last_train,
            },
        }

    def load_state_dict(self, state: dict[str, Any], strict: bool = True) -> None:
        """Restore a :meth:`state_dict` (``strict`` is accepted for SB3's ``set_parameters``).

        The state's ``vae_pixel_weighting`` replaces the module's, so a resumed run trains its VAE as before; a
        state saved before the setting existed (no ``"settings"``) trained with 0, which it gets unless the module
        was given a value explicitly."""
        missing = {"vae", "predictor", "goal_buffer", "memory", "normalizer", "counters"} - set(state)
        if missing:
            raise ValueError(f"curiosity state is missing {sorted(missing)}: not a GoalCuriosityModule state_dict")
        for net in ("vae", "predictor"):
            bad = self.nonfinite_entries(state[net])
            if bad:
                raise ValueError(f"curiosity state: the {net} holds non-finite values in {bad[:3]} (a corrupt file or a diverged run)")
        self.collect_all()
        self.finish_updates()
        self.vae.load_state_dict(state["vae"], strict=strict)
        self._phi_cache.clear()
        self.predictor.load_state_dict(state["predictor"], strict=strict)
        for name in ("vae_optimizer", "predictor_optimizer"):
            if name in state:
                optimizer = getattr(self, name)
                optimizer.load_state_dict(state[name])
                for group in optimizer.param_groups:  # a state saved before foreach was on keeps the multi-tensor step
                    group["foreach"] = True
        self.vae.eval()
        self._sync_encoder()
        self.predictor.eval()
        self.goal_buffer.load_state_dict(state["goal_buffer"])
        self.memory.load_state_dict(state["memory"])
        self.normalizer.load_state_dict(state["normalizer"])
        if "rng" in state:
            self.rng.bit_generator.state = state["rng"]
        if "torch_rng" in state:
            self._torch_gen.set_state(state["torch_rng"])
        settings = state.get("settings", {})
        if "vae_pixel_weighting" in settings:
            self.vae_pixel_weighting = float(settings["vae_pixel_weighting"])
        elif not self._pixel_weighting_given:
            self.vae_pixel_weighting = 0.0  # saved before the weighting existed: the VAE trained without it
        c = state["counters"]
        self.pretrained = bool(c["pretrained"])
        self.n_recorded_steps = int(c["n_recorded_steps"])
        self.last_vae_update = int(c["last_vae_update"])
        self.last_predictor_update = int(c["last_predictor_update"])
        self._recorded_at_last_train = int(c.get("recorded_at_last_train", self.n_recorded_steps))  # saved from predictor_lead on
        self._folded = self._fold()
        envs = state.get("envs")
        if envs is not None:
            n = int(envs["episode_ids"].shape[0])
            self.n_envs = 0
            self._goal_obs = self._goal_obs[:0]
            self._has_goals = self._has_goals[:0]
            self._goal_parts = self._goal_parts[:0]
            self._episode_ids = self._episode_ids[:0]
            self._episodes, self._reward_cache, self._visit_counts, self._pending = [], [], [], []
            t = self.trajectories
            self.trajectories = TrajectoryStore(t.total_capacity, t.embed_dim, t.min_per_env, t.obs_shape, t.obs_dtype)
            self.normalizer.returns = self.normalizer.returns[:0]
            rng_state = self.rng.bit_generator.state
            self.ensure_envs(n)  # allocates; the goals it draws are overwritten below
            self.rng.bit_generator.state = rng_state
            self.normalizer.load_state_dict(state["normalizer"])
            self._goal_obs[:] = envs["goal_obs"].numpy()
            self._has_goals[:] = envs["goal_valid"][:, 0].numpy()  # (n_envs, K), all or none of K per env
            self._episode_ids[:] = envs["episode_ids"].numpy()
            self._next_episode_id = int(envs["next_episode_id"])
            for e, ep in enumerate(envs["episodes"]):
                if ep.ndim > 1:
                    self._episodes[e].extend(ep.numpy())
            self.finished_episodes.clear()
            self.finished_episodes.extend(ep.numpy() for ep in envs["finished_episodes"])
            self.trajectories.load_state_dict(state["trajectories"])
            self._refresh_active_goals()
            if "goal_parts" in envs:
                self._goal_parts[:] = envs["goal_parts"]
                self._touch_goals(np.arange(self.n_envs))
            for cache, saved in zip(self._reward_cache, envs.get("reward_cache", [])):
                cache.update(_cache_from_state(saved))
            for counts, saved in zip(self._visit_counts, envs.get("visit_counts", [])):
                counts.update(_counts_from_state(saved))
        if "phi_cache" in state:
            self._phi_cache.update(_cache_from_state(state["phi_cache"]))
