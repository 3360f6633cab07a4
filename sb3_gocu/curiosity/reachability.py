"""What the mastery predictor learns from, and how well it knows it: labelled pairs (s, g) drawn from the trajectory
store and the goal buffer, and held-out AUCs of near goals against far ones. No SB3 import.

r_gc asks the predictor about the K goals of an episode, drawn from the goal buffer: states of *other* episodes
(other layouts on DoorKey). Pairs of one episode at a gap of 1..d_max alone (eq 15-16's pairs) never show it such a
goal. The reachability pairs do, with clean labels, as the reachability network of Episodic Curiosity (Savinov et
al., 2019) is trained:

* mastered (1): g comes at most k = 5 steps after s in the same episode (``NEAR_DISTANCE``);
* not mastered (0): g is first seen ``far`` (d_max) or more steps after s in the same episode, or g is a goal of the
  goal buffer;
* nothing between: a pair 6 to 29 steps apart teaches little either way.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch as th

from sb3_gocu.curiosity.goals import GoalBuffer
from sb3_gocu.curiosity.stores import TrajectoryStore

#: fraction of each env's trajectory window (the newest states) held out of a predictor update to score it
PREDICTOR_HOLDOUT = 0.1
#: pairs of each kind (near, far, against goals) that score an update
QUALITY_PAIRS = 1024
#: the gap of the near pairs that score an update (positives), whatever the training labels
QUALITY_NEAR = 5
#: the figures of a scored update
QUALITY_KEYS = ("predictor_auc_far", "predictor_auc_goals")


def auc(positive: th.Tensor | np.ndarray, negative: th.Tensor | np.ndarray) -> float:
    """The area under the ROC curve of scores meant to be higher for ``positive`` than for ``negative``: the chance
    that a positive drawn at random scores above a negative drawn at random, ties counting one half (Mann-Whitney U).
    NaN when either side is empty."""
    pos = np.asarray(positive, dtype=np.float64).ravel()
    neg = np.asarray(negative, dtype=np.float64).ravel()
    if len(pos) == 0 or len(neg) == 0:
        return float("nan")
    scores = np.concatenate([pos, neg])
    _, inverse, counts = np.unique(scores, return_inverse=True, return_counts=True)
    mid_rank = np.cumsum(counts) - (counts - 1) / 2  # the mean rank of each distinct score (ties share it)
    u = mid_rank[inverse[: len(pos)]].sum() - len(pos) * (len(pos) + 1) / 2
    return float(u / (len(pos) * len(neg)))


def _goal_negatives(store: TrajectoryStore, goals: GoalBuffer, n: int, rng: np.random.Generator, holdout: int,
                    held_out: bool) -> tuple[th.Tensor, th.Tensor]:
    """``n`` states of the store (training or held-out part) each against a goal drawn uniformly from the buffer."""
    if goals.size == 0 or n == 0:
        return th.zeros(0, store.embed_dim), th.zeros(0, store.embed_dim)
    # a pair at gap 0 is the state itself: any state of the part
    phi_s, _, _ = store.sample_pairs(n, None, rng, min_distance=0, holdout=holdout, held_out=held_out)
    return phi_s, goals.embeddings[th.from_numpy(rng.integers(goals.size, size=len(phi_s)))]


def _far(store: TrajectoryStore, n: int, far: int, rng: np.random.Generator, holdout: int, held_out: bool) -> tuple[th.Tensor, th.Tensor]:
    """Up to ``n`` pairs of one episode whose goal is first seen ``far`` or more steps after the state."""
    phi_s, phi_g, dist = store.sample_pairs(n, None, rng, first_visit=True, min_distance=far, holdout=holdout, held_out=held_out)
    keep = dist >= far
    return phi_s[keep], phi_g[keep]


def reachability_pairs(store: TrajectoryStore, goals: GoalBuffer, n_pairs: int, near: int, far: int, rng: np.random.Generator,
                       holdout: int) -> tuple[th.Tensor, th.Tensor, th.Tensor, th.Tensor]:
    """About ``n_pairs`` training pairs: half mastered (gap 1..``near``), a quarter far in the same episode, a quarter
    against goals of the buffer (far pairs in their stead while the buffer is empty).

    :param holdout: the newest states of each env that no pair touches (they score the update)
    :return: phi(s), phi(g), the gap (-1 against a buffer goal) and the label (1 mastered, 0 not), each (n,)"""
    n_near = n_pairs // 2
    n_goal = n_pairs // 4 if goals.size else 0
    s_near, g_near, d_near = store.sample_pairs(n_near, near, rng, holdout=holdout)
    s_far, g_far = _far(store, n_pairs - n_near - n_goal, far, rng, holdout, held_out=False)
    s_goal, g_goal = _goal_negatives(store, goals, n_goal, rng, holdout, held_out=False)
    dist = th.cat([d_near, th.full((len(s_far),), float(far)), th.full((len(s_goal),), -1.0)])
    target = th.cat([th.ones(len(s_near)), th.zeros(len(s_far) + len(s_goal))])
    return th.cat([s_near, s_far, s_goal]), th.cat([g_near, g_far, g_goal]), dist, target


@dataclasses.dataclass
class QualityPairs:
    """Held-out pairs that score a predictor: near (gap <= 5), far (first seen >= d_max steps later, same episode) and
    the near pairs' states against goals of the buffer."""

    near: tuple[th.Tensor, th.Tensor]
    far: tuple[th.Tensor, th.Tensor]
    goals: tuple[th.Tensor, th.Tensor]

    @classmethod
    def draw(cls, store: TrajectoryStore, goals: GoalBuffer, far: int, rng: np.random.Generator, holdout: int) -> "QualityPairs":
        """:param far: d_max
        :param holdout: the newest states of each env, which the pairs are drawn from"""
        s, g, _ = store.sample_pairs(QUALITY_PAIRS, QUALITY_NEAR, rng, holdout=holdout, held_out=True)
        n_goal = len(s) if goals.size else 0
        g_goal = goals.embeddings[th.from_numpy(rng.integers(max(goals.size, 1), size=n_goal))]
        return cls((s, g), _far(store, QUALITY_PAIRS, far, rng, holdout, held_out=True), (s[:n_goal], g_goal))

    def to(self, device: th.device) -> "QualityPairs":
        return QualityPairs(*(tuple(x.to(device) for x in pair) for pair in (self.near, self.far, self.goals)))

    @th.no_grad()
    def score(self, mastery) -> dict[str, float]:
        """``predictor_auc_far`` and ``predictor_auc_goals`` of ``mastery(phi_s, phi_g) -> (n,)`` (NaN where a side
        has no pair)."""
        m_near = mastery(*self.near).cpu() if len(self.near[0]) else th.zeros(0)
        m_far = mastery(*self.far).cpu() if len(self.far[0]) else th.zeros(0)
        m_goal = mastery(*self.goals).cpu() if len(self.goals[0]) else th.zeros(0)
        return {"predictor_auc_far": auc(m_near, m_far), "predictor_auc_goals": auc(m_near, m_goal)}
