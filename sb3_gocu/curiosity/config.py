"""The curiosity module's settings, checked once: :class:`CuriosityConfig`, and the paper's values.

The defaults are the paper's MiniGrid settings (section 5.1.2) except the departures listed in
:data:`PAPER_CURIOSITY_KWARGS`, each measured on DoorKey-8x8 (docs/results.md). No Stable-Baselines3 import.
"""

from __future__ import annotations

import dataclasses
import math
from types import MappingProxyType
from typing import Any, Mapping, Sequence

from sb3_gocu.curiosity.checks import check, is_flag, is_integer, is_number
from sb3_gocu.curiosity.goals import GOAL_STRATEGIES
from sb3_gocu.curiosity.reward import AGGREGATIONS, REVISIT_DECAYS

#: ``vae_pixel_weighting`` of image observations when it is None (the default); measured on DoorKey-8x8
DEFAULT_PIXEL_WEIGHTING = 0.5
#: what the predictor learns from (``pair_labels``)
PAIR_LABELS = ("reachability", "eq16")
#: reachability labels: a goal at most this many steps after the state is mastered (Episodic Curiosity's k)
NEAR_DISTANCE = 5
#: fraction of the distinct observations held out for the VAE's early stopping (``vae_patience``)
VAE_HOLDOUT = 0.1
#: distinct observations remembered per env and episode (goal candidates, reward memo, visit counts)
EPISODE_MEMORY = 4096

#: The paper's value of every setting whose default departs from it. ``GoalCuriosityModule(space,
#: **PAPER_CURIOSITY_KWARGS)`` is the paper's module with three differences that cannot be expressed: the predictor
#: trains on ``predictor_pairs`` pairs drawn from the steps since its last update (the paper: every new pair; 20,000
#: steps x d_max = 30 is 600,000 pairs, which 15 epochs would take hours per update on a CPU), a pair drawn n times
#: trains once with weight n (the same objective, fewer optimiser steps), and s_0, the reset observation of an
#: episode, is not recorded (only states reached by a step are).
PAPER_CURIOSITY_KWARGS: Mapping[str, Any] = MappingProxyType(
    dict(
        revisit_decay="none",  # every visit of a state pays eq 13 (default: only the first visit in an episode)
        pair_labels="eq16",  # pairs of one episode at gaps 1..d_max labelled by eq 15-16 (default: reachability pairs)
        first_visit_distance=False,  # dist(s, g) of eq 15 is the step gap y (default: steps to g's first visit)
        predictor_epochs=15,  # 15 epochs per update (default 1: on a bounded draw 15 epochs overfit it)
        vae_patience=0,  # every epoch of an update on the whole bank (default: early stopping with patience 1)
        vae_update_epochs=20,  # 20 epochs per VAE update, as the pretraining (default: at most 3 from the VAE's weights)
        vae_pixel_weighting=0.0,  # every pixel weighs 1 in eq 8 (default for images: rare colours weigh more)
        vae_dedupe=False,  # the VAE trains on the bank as it is (default: distinct observations weighted by count)
        predictor_hidden=(512, 512, 512, 512, 512),  # five hidden layers of 512 (default: two of 256, a sixteenth of the scoring cost)
    )
)


@dataclasses.dataclass(frozen=True)
class CuriosityConfig:
    """The settings of :class:`~sb3_gocu.curiosity.GoalCuriosityModule` (the paper's symbol in brackets);
    constructing one checks every value and raises a ``ValueError`` naming the setting and its allowed range."""

    n_goals: int = 50  #: K, goals drawn from the goal buffer at each episode start (1 <= K <= goal_buffer_size)
    goal_buffer_size: int = 1500  #: capacity of the goal buffer R_g
    new_goals_per_episode: int = 7  #: l, goals drawn from each finished episode besides its final state
    goal_strategy: str = "proportional"  #: how new goals are drawn: "random", "proportional" or "late"
    goal_novelty: float = 0.0  #: eq 12: keep a goal farther than this times the median nearest-goal distance
    alpha: float = 1.0  #: alpha of eq 13
    aggregation: str = "max"  #: h of eq 13, "max" or "mean"
    reward_scale: float = 10.0  #: delta of eq 13 (> 0)
    revisit_decay: str = "first_visit"  #: pay of a revisit in an episode: "none", "inverse_sqrt" or "first_visit"
    intrinsic_gamma: float = 0.99  #: discount of the intrinsic returns (eq 14 and the curiosity GAE)
    pair_labels: str = "reachability"  #: what the predictor learns: "reachability" (near / far / goal-buffer pairs) or "eq16"
    prior_weight: float = 3.0  #: lambda of eq 15
    distance_weight: float = 1.0  #: beta of eq 15
    label_threshold: float = 15.0  #: a of eq 16 (> 0)
    label_slope: float = 0.8  #: b of eq 16 (> 0)
    max_distance: int = 30  #: d_max: eq16 labels: the largest step gap of a pair; reachability: the smallest gap of a far one
    first_visit_distance: bool = True  #: dist(s, g) of eq 15 is the steps to g's first visit after s, not y
    predictor_hidden: Sequence[int] = (256, 256)  #: hidden layer sizes of the predictor (the paper: five of 512)
    predictor_lr: float = 5e-4  #: Adam learning rate of the predictor
    predictor_batch_size: int = 128  #: minibatch size of predictor training
    predictor_epochs: int = 1  #: epochs over the drawn pairs at each predictor update (0: never trained, only scored)
    predictor_pairs: int = 16384  #: training pairs drawn per predictor update
    predictor_train_freq: int = 20_000  #: P_m, recorded env steps between predictor updates
    embed_dim: int = 128  #: size of the embedding phi (the FC layer after the encoder)
    latent_dim: int = 10  #: size of the VAE latent (mu, sigma)
    vae_beta: float = 1.0  #: beta of eq 8
    vae_pixel_weighting: float | None = None  #: rare-colour weight exponent in [0, 1]; None: 0.5 for images, 0 else
    vae_lr: float = 1e-3  #: Adam learning rate of the VAE
    vae_batch_size: int = 128  #: minibatch size of VAE training
    vae_epochs: int = 20  #: epochs over the memory bank of the VAE's pretraining (all of them)
    vae_update_epochs: int = 3  #: the most epochs over the memory bank of each later VAE update (fewer with vae_patience)
    vae_train_freq: int = 100_000  #: P_vae, recorded env steps between VAE updates
    vae_dedupe: bool = True  #: train the VAE on the bank's distinct observations, each weighted by its count
    vae_patience: int = 1  #: stop a VAE update after this many epochs without a better held-out loss (0: never)
    pretrain_steps: int = 10_000  #: random-policy observations that pretrain the VAE before the first rollout
    memory_size: int = 10_000  #: capacity of the memory bank the VAE trains on
    obs_key: str | None = None  #: for a Dict observation space, the entry to embed
    image_channels: int | None = None  #: keep only the newest this many channels of an image (frame stacks)

    def __post_init__(self) -> None:
        ints = ("n_goals", "goal_buffer_size", "new_goals_per_episode", "max_distance", "predictor_batch_size", "predictor_epochs",
                "predictor_pairs", "predictor_train_freq", "embed_dim", "latent_dim", "vae_batch_size", "vae_epochs",
                "vae_train_freq", "pretrain_steps", "memory_size", "vae_patience", "vae_update_epochs")
        for name in ints:
            check(is_integer(getattr(self, name)), f"{name} must be an integer, got {getattr(self, name)!r}")
        numbers = ("goal_novelty", "alpha", "reward_scale", "intrinsic_gamma", "prior_weight", "distance_weight", "label_threshold",
                   "label_slope", "predictor_lr", "vae_lr", "vae_beta")
        for name in numbers:
            value = getattr(self, name)
            check(is_number(value) and math.isfinite(value), f"{name} must be a finite number, got {value!r}")
        for name in ("first_visit_distance", "vae_dedupe"):
            check(is_flag(getattr(self, name)), f"{name} must be True or False, got {getattr(self, name)!r}")
        check(self.goal_buffer_size >= 1, f"goal_buffer_size must be >= 1, got {self.goal_buffer_size}")
        check(1 <= self.n_goals <= self.goal_buffer_size,
              f"n_goals (K) must be in [1, goal_buffer_size={self.goal_buffer_size}], got {self.n_goals}")
        check(self.new_goals_per_episode >= 0, f"new_goals_per_episode (l) must be >= 0, got {self.new_goals_per_episode}")
        check(self.goal_strategy in GOAL_STRATEGIES, f"goal_strategy must be one of {GOAL_STRATEGIES}, got {self.goal_strategy!r}")
        check(self.goal_novelty >= 0, f"goal_novelty must be >= 0, got {self.goal_novelty}")
        check(self.aggregation in AGGREGATIONS, f"aggregation (h) must be one of {AGGREGATIONS}, got {self.aggregation!r}")
        check(self.revisit_decay in REVISIT_DECAYS, f"revisit_decay must be one of {REVISIT_DECAYS}, got {self.revisit_decay!r}")
        check(self.reward_scale > 0, f"reward_scale (delta) must be > 0, got {self.reward_scale}")
        check(0 <= self.intrinsic_gamma <= 1, f"intrinsic_gamma must be in [0, 1], got {self.intrinsic_gamma}")
        check(self.prior_weight >= 0, f"prior_weight (lambda) must be >= 0, got {self.prior_weight}")
        check(self.distance_weight >= 0, f"distance_weight (beta) must be >= 0, got {self.distance_weight}")
        check(self.label_threshold > 0, f"label_threshold (a) must be > 0, got {self.label_threshold}")
        check(self.label_slope > 0, f"label_slope (b) must be > 0, got {self.label_slope}")
        check(self.max_distance >= 1, f"max_distance (d_max) must be >= 1, got {self.max_distance}")
        check(self.pair_labels in PAIR_LABELS, f"pair_labels must be one of {PAIR_LABELS}, got {self.pair_labels!r}")
        check(self.pair_labels != "reachability" or self.max_distance > NEAR_DISTANCE,
              f"max_distance (d_max) must be > {NEAR_DISTANCE} with pair_labels='reachability' (a far pair is d_max or more steps "
              f"apart, a near one at most {NEAR_DISTANCE}), got {self.max_distance}")
        for name in ("predictor_batch_size", "predictor_pairs", "predictor_train_freq", "embed_dim", "latent_dim", "vae_batch_size",
                     "vae_train_freq", "memory_size"):
            check(getattr(self, name) >= 1, f"{name} must be >= 1, got {getattr(self, name)}")
        for name in ("predictor_epochs", "vae_epochs", "vae_update_epochs", "pretrain_steps", "vae_patience"):
            check(getattr(self, name) >= 0, f"{name} must be >= 0, got {getattr(self, name)}")
        for name in ("predictor_lr", "vae_lr"):
            check(getattr(self, name) > 0, f"{name} must be > 0, got {getattr(self, name)}")
        check(self.vae_beta >= 0, f"vae_beta must be >= 0, got {self.vae_beta}")
        check(self.vae_pixel_weighting is None or (is_number(self.vae_pixel_weighting) and 0 <= self.vae_pixel_weighting <= 1),
              f"vae_pixel_weighting must be None or in [0, 1], got {self.vae_pixel_weighting!r}")
        check(self.obs_key is None or isinstance(self.obs_key, str), f"obs_key must be None or a string, got {self.obs_key!r}")
        check(self.image_channels is None or (is_integer(self.image_channels) and self.image_channels >= 1),
              f"image_channels must be None or an integer >= 1, got {self.image_channels!r}")
        hidden = self.predictor_hidden
        check(isinstance(hidden, Sequence) and len(hidden) >= 1 and all(is_integer(h) and h >= 1 for h in hidden),
              f"predictor_hidden must be a non-empty sequence of integers >= 1, got {hidden!r}")
        object.__setattr__(self, "predictor_hidden", tuple(int(h) for h in hidden))
