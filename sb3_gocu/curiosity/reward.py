"""The formulas of GoCu as plain tensor functions: the curiosity reward (eq 13), its normalisation by the
running std of intrinsic returns (eq 14), the complexity score (eq 15) and the label probability (eq 16); and the
running mean of the normalised reward that the drop-in wrapper's sum subtracts (:class:`RunningMean`).
"""

from __future__ import annotations

import numpy as np
import torch as th

AGGREGATIONS = ("max", "mean")
REVISIT_DECAYS = ("none", "inverse_sqrt", "first_visit")


def curiosity_reward(mastery: th.Tensor, alpha: float = 1.0, aggregation: str = "max", scale: float = 10.0) -> th.Tensor:
    """Eq 13: ``r_gc = (alpha - h(m_1, ..., m_K)) / delta``.

    :param mastery: (n, K) probabilities that each of the K goals is mastered from each state; with
        K = 0 (no goal yet) h is taken as 0, so r_gc = alpha / delta
    :param alpha: alpha, the value of the uniform vector (sign and offset of the reward)
    :param aggregation: h, ``"max"`` or ``"mean"``
    :param scale: delta, the divisor
    :return: (n,)
    """
    if mastery.shape[1] == 0:
        h = mastery.new_zeros(mastery.shape[0])
    elif aggregation == "max":
        h = mastery.max(dim=1).values
    elif aggregation == "mean":
        h = mastery.sum(dim=1) / mastery.shape[1]  # a sum over K, then one division: the bits of every recorded run
    else:
        raise ValueError(f"aggregation must be one of {AGGREGATIONS}, got {aggregation!r}")
    return (alpha - h) / scale


def revisit_factor(visits: np.ndarray, decay: str) -> np.ndarray:
    """Share of r_gc paid for the n-th visit of an observation within an episode.

    * ``"none"``: every visit pays r_gc (the paper's eq 13 as it stands);
    * ``"inverse_sqrt"``: the n-th visit pays ``r_gc / sqrt(n)``;
    * ``"first_visit"``: only the first visit pays (n = 1), later ones pay 0.

    Eq 13 scores a state by how unlikely its goals are to be reached *by the current policy*, so a policy that
    stays put (turning into a wall, toggling nothing) makes its own state look unmastered and is paid for
    staying. A decay with the visit count removes that loop: standing still earns nothing after the first step.

    :param visits: n >= 1 for each state, counted within the current episode (this visit included)
    :param decay: one of :data:`REVISIT_DECAYS`
    :return: float32 array of the same shape, in (0, 1]  (or {0, 1} for ``"first_visit"``)
    """
    visits = np.asarray(visits)
    if np.any(visits < 1):
        raise ValueError(f"visits must be >= 1, got min {visits.min()}")
    if decay == "none":
        return np.ones(visits.shape, dtype=np.float32)
    if decay == "inverse_sqrt":
        return (1.0 / np.sqrt(visits)).astype(np.float32)
    if decay == "first_visit":
        return (visits == 1).astype(np.float32)
    raise ValueError(f"revisit_decay must be one of {REVISIT_DECAYS}, got {decay!r}")


def complexity_score(prior: th.Tensor, distance: th.Tensor, prior_weight: float, distance_weight: float) -> th.Tensor:
    """Eq 15: ``sc(s, g) = lambda * prior(s, g) + beta * dist(s, g)``.

    ``prior`` is the predictor's current belief that the skill is *not* mastered, ``1 - m(phi(s), phi(g))``,
    and ``dist`` the number of steps from s to g in the trajectory (with the module's default
    ``first_visit_distance=True``, to the first visit of g's observation after s).
    """
    return prior_weight * prior + distance_weight * distance


def mastered_probability(score: th.Tensor, threshold: float, slope: float) -> th.Tensor:
    """Eq 16: ``p_skill = 1 - 1 / (1 + exp(-b (sc - a)))``, the probability that (s, g) is labelled mastered."""
    return 1.0 - th.sigmoid(slope * (score - threshold))


class RunningMeanStd:
    """Running mean and variance of a stream of batches (parallel algorithm of Chan et al.)."""

    def __init__(self, epsilon: float = 1e-4) -> None:
        self.mean = 0.0
        self.var = 1.0
        self.count = epsilon

    def update(self, x: np.ndarray) -> None:
        batch_mean, batch_var, batch_count = float(np.mean(x)), float(np.var(x)), x.size
        delta = batch_mean - self.mean
        total = self.count + batch_count
        self.mean += delta * batch_count / total
        m2 = self.var * self.count + batch_var * batch_count + delta**2 * self.count * batch_count / total
        self.var = m2 / total
        self.count = total


class RunningMean:
    """Mean of a stream of batches: the plain mean of everything seen until ``horizon`` samples, then an exponential
    moving average over about the last ``horizon`` samples (so that it follows a reward that changes as its networks
    learn).

    :param horizon: samples the average spans once it is full (> 0)
    """

    def __init__(self, horizon: int) -> None:
        if not (isinstance(horizon, int) and horizon > 0):
            raise ValueError(f"horizon must be an int > 0, got {horizon!r}")
        self.horizon = horizon
        self.mean = 0.0
        self.count = 0

    def update(self, x: np.ndarray) -> None:
        if x.size == 0:
            return
        self.count += x.size
        self.mean += x.size / min(self.count, self.horizon) * (float(np.mean(x, dtype=np.float64)) - self.mean)

    def state_dict(self) -> dict:
        return {"mean": self.mean, "count": self.count}

    def load_state_dict(self, state: dict) -> None:
        self.mean, self.count = float(state["mean"]), int(state["count"])


class IntrinsicReturnNormalizer:
    """Eq 14: divides r_gc by the running standard deviation of the discounted intrinsic returns.

    Each env keeps a discounted sum of its intrinsic rewards (not reset at episode ends, as in RND); the
    running variance of these returns is updated with every step before the reward is divided.

    :param gamma: discount of the intrinsic returns
    :param epsilon: added to the variance
    """

    def __init__(self, gamma: float = 0.99, epsilon: float = 1e-8) -> None:
        self.gamma = gamma
        self.epsilon = epsilon
        self.returns = np.zeros(0, dtype=np.float64)
        self.rms = RunningMeanStd()

    def ensure_envs(self, n_envs: int) -> None:
        if n_envs > len(self.returns):
            self.returns = np.concatenate([self.returns, np.zeros(n_envs - len(self.returns))])

    @property
    def std(self) -> float:
        return float(np.sqrt(self.rms.var + self.epsilon))

    def __call__(self, rewards: np.ndarray, env_indices: np.ndarray, update: bool = True) -> np.ndarray:
        if update:
            self.returns[env_indices] = self.returns[env_indices] * self.gamma + rewards
            self.rms.update(self.returns[env_indices])
        return (rewards / self.std).astype(np.float32)

    def state_dict(self) -> dict:
        return {"returns": th.from_numpy(self.returns.copy()), "mean": self.rms.mean, "var": self.rms.var, "count": self.rms.count}

    def load_state_dict(self, state: dict) -> None:
        self.returns = state["returns"].numpy().astype(np.float64)
        self.rms.mean, self.rms.var, self.rms.count = float(state["mean"]), float(state["var"]), float(state["count"])
