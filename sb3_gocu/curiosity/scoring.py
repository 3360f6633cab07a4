"""Scoring states against their episodes' goals (eq 13), behind one interface: :class:`Scorer`.

Between two updates of the networks, the reward of a state against an episode's goals is a fixed function, so
it is memoised per episode on the observation's bytes (an observation seen again in the same episode costs a
hash), and phi on the observation alone until the next VAE update. A batch of states is a
:class:`ScoringTicket`: :meth:`Scorer.lookup` finds what is memoised, :meth:`Scorer.dispatch` computes the rest
(the embedding of new observations and eq 13) in the caller or in a worker thread, and :meth:`Scorer.take` commits
the results, in submission order. Where it is computed does not change a value. No SB3 import.
"""

from __future__ import annotations

import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Callable

import numpy as np
import torch as th

from sb3_gocu.curiosity.episodes import Episodes
from sb3_gocu.curiosity.networks import FoldedPredictor
from sb3_gocu.curiosity.reward import curiosity_reward

#: phi memo entries kept before the memo is cleared
PHI_MEMO_SIZE = 100_000


@th.inference_mode()
def eq13_rows(
    phi: th.Tensor, goal_parts: th.Tensor, has_goals: np.ndarray, folded: FoldedPredictor, alpha: float, aggregation: str, reward_scale: float
) -> th.Tensor:
    """Raw r_gc of states (phi, (n, d)) against their episodes' goals (goal halves, (n, K, h)); ``has_goals`` says
    whether each state's episode has its K goals, and a state whose episode has none yet gets h = 0, i.e. alpha / delta."""
    if has_goals.all():
        mastery = folded.mastery_from_parts(folded.state_part(phi), goal_parts)
        return curiosity_reward(mastery, alpha, aggregation, reward_scale)
    r = th.full((len(phi),), alpha / reward_scale)
    rows = th.from_numpy(np.flatnonzero(has_goals))
    if len(rows):
        mastery = folded.mastery_from_parts(folded.state_part(phi[rows]), goal_parts[rows])
        r[rows] = curiosity_reward(mastery, alpha, aggregation, reward_scale)
    return r


@th.inference_mode()
def score_rows(
    phi: np.ndarray, embed_pos: np.ndarray, raw: np.ndarray | None, encoder: Any, to_tensor: Any, goal_parts: th.Tensor,
    has_goals: np.ndarray, folded: FoldedPredictor, eq13_args: tuple[float, str, float],
) -> np.ndarray:
    """Embed ``raw`` into the rows ``embed_pos`` of ``phi`` (in place: (n, d) float32, the other rows known), then eq 13
    of every row. :return: raw r_gc, (n,) float32"""
    if len(embed_pos):
        phi[embed_pos] = encoder.embed(to_tensor(raw)).cpu().numpy()
    return eq13_rows(th.from_numpy(phi), goal_parts, has_goals, folded, *eq13_args).numpy()


class ScoringTicket:
    """One batch of states, one per env of ``env_indices``, from its submission until its rewards are taken."""

    def __init__(self, n: int, embed_dim: int) -> None:
        self.rewards = np.zeros(n, dtype=np.float32)  # raw r_gc (eq 13), filled at collection
        self.phi = np.zeros((n, embed_dim), dtype=np.float32)
        self.miss = np.zeros(0, dtype=np.int64)  # rows scored by the predictor
        self.embed_rows = np.zeros(0, dtype=np.int64)  # rows of ``miss`` whose phi is not memoised: embedded with the scoring
        self.phi_from: list[tuple[int, ScoringTicket, int]] = []  # (row, earlier ticket, its row): phi being embedded there
        self.pending: list[tuple[int, ScoringTicket, int]] = []  # (row, earlier ticket, its row): same state, same episode
        self.computed: np.ndarray | None = None  # eq 13 of the miss rows, when computed in the caller
        self.raw: np.ndarray | None = None  # raw observations of the embed rows (a copy: the env reuses its buffers)
        self.encoder: Any = None  # the encoder of the submission (a VAE update swaps the module's)
        self.env_indices = np.zeros(0, dtype=np.int64)
        self.keys: list[bytes] = []
        self.episode_ids = np.zeros(0, dtype=np.int64)
        self.has_goals = np.zeros(0, dtype=bool)  # whether each miss row's episode has its K goals
        self.goal_parts: th.Tensor | None = None  # the miss rows' goal halves (copied)
        self.folded: FoldedPredictor | None = None
        self.factor: np.ndarray | None = None  # revisit factor
        self.recording = False
        self.future: Any = None  # the worker's computation
        self.compute_time = 0.0  # seconds the computation took
        self.result: tuple[np.ndarray, np.ndarray] | None = None


class Scorer:
    """Memoised scoring of tickets, in the caller or in one worker thread (in submission order).

    :param episodes: the per-env episode state (its reward memos, ids and goal halves)
    :param embed_dim: size of phi
    :param to_tensor: raw batch -> the encoder's input on the networks' device
    :param eq13_args: (alpha, h, delta) of eq 13
    """

    def __init__(self, episodes: Episodes, embed_dim: int, to_tensor: Callable[[np.ndarray], th.Tensor],
                 eq13_args: tuple[float, str, float]) -> None:
        self.episodes, self.embed_dim, self.to_tensor, self.eq13_args = episodes, embed_dim, to_tensor, eq13_args
        self.worker: ThreadPoolExecutor | None = None  # started by the first background ticket
        self.pending: list[dict[bytes, tuple[ScoringTicket, int]]] = []  # states of each episode being scored
        self.outstanding: deque[ScoringTicket] = deque()
        self.phi_memo: dict[bytes, Any] = {}  # key -> phi, or (ticket, row) while that ticket embeds it
        self.cache_hits = self.cache_lookups = 0  # cumulative
        self.time_in_worker = 0.0  # the worker's scoring (overlaps the caller's work)
        self.time_waiting = 0.0  # the caller waiting for the worker's scores

    def grow(self, n_envs: int) -> None:
        self.pending += [{} for _ in range(n_envs - len(self.pending))]

    def lookup(self, raw: np.ndarray, env_indices: np.ndarray, keys: list[bytes], encoder: Any, folded: FoldedPredictor) -> ScoringTicket:
        """Memo lookups of one observation per env: rewards known from the episode's memo, rows equal to a row still
        being scored (``pending``), and the rows to score (``miss``), with their phi where memoised."""
        n = len(raw)
        ticket = ScoringTicket(n, self.embed_dim)
        episodes = self.episodes
        ticket.env_indices, ticket.keys = env_indices, keys
        ticket.episode_ids = episodes.ids[env_indices].copy()
        miss = []
        for j, (e, key) in enumerate(zip(env_indices, keys)):
            hit = episodes.rewards[e].get(key)
            if hit is not None:
                ticket.rewards[j], ticket.phi[j] = hit
                continue
            earlier = self.pending[e].get(key)
            if earlier is not None:  # seen earlier in this episode, its score (and maybe phi) not taken yet
                ticket.pending.append((j, earlier[0], earlier[1]))
                continue
            miss.append(j)
        self.cache_lookups += n
        self.cache_hits += n - len(miss)
        if miss:
            m_idx = np.asarray(miss)
            ticket.miss = m_idx
            todo = []
            for j in miss:
                hit = self.phi_memo.get(keys[j])
                if hit is None:
                    todo.append(j)
                elif isinstance(hit, tuple):
                    ticket.phi_from.append((j, *hit))
                else:
                    ticket.phi[j] = hit
            if todo:
                ticket.embed_rows = np.asarray(todo, dtype=np.int64)
                ticket.raw = raw[ticket.embed_rows]
                ticket.encoder = encoder
                if len(self.phi_memo) + len(todo) > PHI_MEMO_SIZE:
                    self.phi_memo.clear()
                for j in todo:
                    self.phi_memo[keys[j]] = (ticket, j)
            ticket.has_goals = episodes.has_goals[env_indices[m_idx]]
            ticket.folded = folded
            for j in miss:
                self.pending[env_indices[j]][keys[j]] = (ticket, j)
        return ticket

    def dispatch(self, ticket: ScoringTicket, background: bool) -> None:
        """Compute the ticket's ``miss`` rows: in the worker thread if ``background`` (it computes the tickets in
        submission order, so a ticket's phi taken from an earlier one is there), else now."""
        if len(ticket.miss):
            # a copy (indexing) of the episodes' goal halves: a new episode may start before the rewards are taken
            ticket.goal_parts = self.episodes.goal_parts[th.from_numpy(ticket.env_indices[ticket.miss])]
            if background:
                if self.worker is None:  # its torch thread count: the caller's, so that it computes the caller's bits
                    self.worker = ThreadPoolExecutor(1, "gocu-score", initializer=th.set_num_threads, initargs=(th.get_num_threads(),))
                ticket.future = self.worker.submit(self._compute, ticket)
            else:
                for _, earlier, _ in ticket.phi_from:  # now, so that a later ticket may read this one's phi
                    if earlier.future is not None:
                        earlier.future.result()
                ticket.computed = self._compute(ticket)
        self.outstanding.append(ticket)

    @th.inference_mode()
    def _compute(self, ticket: ScoringTicket) -> np.ndarray:
        """phi of the ticket's ``embed_rows`` and eq 13 for its ``miss`` rows (pure: reads what the ticket holds,
        writes its phi rows; the caller or the worker)."""
        t0 = time.perf_counter()
        for j, earlier, row in ticket.phi_from:
            ticket.phi[j] = earlier.phi[row]
        phi = ticket.phi[ticket.miss]
        embed_pos = np.searchsorted(ticket.miss, ticket.embed_rows)
        r = score_rows(phi, embed_pos, ticket.raw, ticket.encoder, self.to_tensor, ticket.goal_parts, ticket.has_goals, ticket.folded, self.eq13_args)
        ticket.phi[ticket.miss] = phi
        ticket.compute_time = time.perf_counter() - t0
        return r

    def take(self, ticket: ScoringTicket) -> None:
        """Wait for the oldest outstanding ticket (``ticket``) and commit it: its raw rewards and phi filled, the
        scored rows memoised in their episode (unless it has ended since)."""
        if not self.outstanding or self.outstanding[0] is not ticket:
            raise ValueError("this scoring ticket is not the oldest outstanding one of this module")
        self.outstanding.popleft()
        if not len(ticket.miss):
            computed = np.zeros(0, dtype=np.float32)
        elif ticket.future is not None:
            t_wait = time.perf_counter()
            computed = ticket.future.result()
            self.time_waiting += time.perf_counter() - t_wait
            self.time_in_worker += ticket.compute_time
        else:
            computed = ticket.computed
        env_indices, keys, episodes = ticket.env_indices, ticket.keys, self.episodes
        if len(ticket.miss):
            ticket.rewards[ticket.miss] = computed
        for j, earlier, row in ticket.pending:
            ticket.rewards[j] = earlier.rewards[row]
            ticket.phi[j] = earlier.phi[row]
        for j in ticket.embed_rows:
            entry = self.phi_memo.get(keys[j])
            if isinstance(entry, tuple) and entry[0] is ticket and entry[1] == j:
                self.phi_memo[keys[j]] = th.from_numpy(ticket.phi[j].copy())
        ticket.raw = ticket.encoder = None
        for j, rj in zip(ticket.miss, ticket.rewards[ticket.miss]):
            e = env_indices[j]
            if self.pending[e].get(keys[j], (None,))[0] is ticket:
                del self.pending[e][keys[j]]
            if episodes.ids[e] != ticket.episode_ids[j]:
                continue  # that episode is over: its memo was dropped
            episodes.remember_reward(e, keys[j], rj, ticket.phi[j])
