"""Training the VAE (eq 8) and the mastery predictor (eq 15-16): jobs in, typed fits out.

An update has three steps. Its *job* is prepared from the module's stores (a copy of what it trains on, drawn with
the module's generator); :class:`Trainer` *fits* the network to the job (it touches only the network, its optimiser
and the torch generator); the module then *takes the fit into use* (re-embeds goals, clears memos). Every step that meets a non-finite loss or gradient is skipped,
and an update that leaves the weights non-finite is rolled back (:func:`guard_update`). No SB3 import.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import time
import warnings
from typing import Any, Callable, Iterator, Sequence

import numpy as np
import torch as th

from sb3_gocu.curiosity.config import VAE_HOLDOUT, CuriosityConfig
from sb3_gocu.curiosity.networks import ConvVAE, MasteryPredictor, MlpVAE, PixelWeights, mastery_loss, vae_loss
from sb3_gocu.curiosity.observations import ObservationAdapter
from sb3_gocu.curiosity.reachability import QualityPairs
from sb3_gocu.curiosity.reward import complexity_score, mastered_probability
from sb3_gocu.curiosity.stores import distinct_rows

Snapshot = tuple[dict, dict]


@contextlib.contextmanager
def torch_threads(n: int | None) -> Iterator[None]:
    """Run the block with ``n`` torch threads in the calling thread (None: leave the count alone), then restore
    the count it had. Torch keeps the count per thread once the thread has read it, so a fit thread can set
    its own count while the training thread keeps its own."""
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


@dataclasses.dataclass
class VaeJob:
    """What a VAE update trains on: observations weighted by multiplicity, and a held-out part for early stopping."""

    data: np.ndarray  #: raw observations to train on
    weights: np.ndarray  #: their multiplicities, mean 1 over the distinct observations
    epochs: int  #: the most epochs
    patience: int = 0  #: early stopping's patience (0: all epochs)
    val_data: np.ndarray | None = None  #: held-out observations (None: no early stopping)
    val_weights: np.ndarray | None = None  #: their multiplicities
    pixel_weights: PixelWeights | None = None  #: weights of the pixels in eq 8's reconstruction term (None: all 1)
    threads: int | None = None  #: torch threads of the fit (None: the fitting thread's)


@dataclasses.dataclass
class VaeFit:
    """The outcome of a VAE fit, before it is taken into use."""

    snapshot: Snapshot  #: the VAE and its optimiser before the fit
    losses: list[float]  #: training loss of every step taken
    skipped: int  #: steps skipped for a non-finite loss or gradient
    n: int  #: observations of the job (held-out ones included)
    time: float  #: seconds
    epochs_run: int
    best_epoch: int  #: the epoch whose weights the VAE keeps (0: the starting ones)
    val_loss_start: float  #: held-out loss before the fit (NaN without early stopping)
    val_loss: float  #: best held-out loss (NaN without early stopping)
    collapsed: bool = False  #: the fit embedded distinct frames to one point and was rolled back

    def stats(self, seconds: float) -> dict[str, float]:
        """The figures logged for the update (``seconds``: its whole time)."""
        return {"vae_loss": mean_or_nan(self.losses), "vae_observations": float(self.n), "vae_skipped_updates": float(self.skipped),
                "vae_epochs_run": float(self.epochs_run), "vae_best_epoch": float(self.best_epoch), "vae_val_loss": self.val_loss,
                "vae_collapsed": float(self.collapsed), "vae_time": seconds}


@dataclasses.dataclass
class PredictorJob:
    """What a predictor update trains on: drawn pairs (s, g) with their step distance."""

    phi_s: th.Tensor  #: phi(s), (n, d)
    phi_g: th.Tensor  #: phi(g), (n, d)
    dist: th.Tensor  #: dist(s, g) of eq 15, (n,)
    weights: th.Tensor  #: multiplicity of each pair, mean 1
    drawn: int  #: pairs drawn before de-duplication
    threads: int | None = None  #: torch threads of the fit (None: the fitting thread's)
    target: th.Tensor | None = None  #: each pair's label (None: eq 15-16's p_skill, computed when the fit starts)
    quality: QualityPairs | None = None  #: held-out pairs that score the fit


@dataclasses.dataclass
class PredictorFit:
    """The outcome of a predictor fit, before it is taken into use."""

    snapshot: Snapshot  #: the predictor and its optimiser before the fit
    losses: list[float]
    accs: list[float]  #: weighted accuracy against the labels, per step
    skipped: int
    n: int  #: distinct pairs
    drawn: int  #: pairs drawn
    mastered: float  #: weighted fraction of pairs labelled mastered
    time: float
    quality: dict[str, float] = dataclasses.field(default_factory=dict)  #: held-out AUCs after the fit

    def stats(self, seconds: float) -> dict[str, float]:
        """The figures logged for the update (``seconds``: its whole time)."""
        return {"predictor_loss": mean_or_nan(self.losses), "predictor_accuracy": mean_or_nan(self.accs), "mastered_fraction": self.mastered,
                "predictor_pairs": float(self.drawn), "predictor_distinct_pairs": float(self.n), "predictor_skipped_updates": float(self.skipped),
                "predictor_adam_steps": float(len(self.losses)), "predictor_time": seconds, **self.quality}


def snapshot(network: th.nn.Module, optimizer: th.optim.Optimizer) -> Snapshot:
    """Copies of a network's and its optimiser's state, to roll a whole update back."""
    return copy.deepcopy(network.state_dict()), copy.deepcopy(optimizer.state_dict())


def restore(network: th.nn.Module, optimizer: th.optim.Optimizer, saved: Snapshot) -> None:
    """Put a network and its optimiser back to a :func:`snapshot`."""
    network.load_state_dict(saved[0])
    optimizer.load_state_dict(saved[1])


def nonfinite_entries(state: dict[str, Any]) -> list[str]:
    """Names of the floating-point tensors of a state_dict that hold a NaN or an infinity."""
    return [k for k, v in state.items() if isinstance(v, th.Tensor) and v.is_floating_point() and not bool(th.isfinite(v).all())]


def guarded_step(network: th.nn.Module, optimizer: th.optim.Optimizer, loss: th.Tensor) -> bool:
    """One optimiser step on ``loss``, unless the loss or a gradient is non-finite; whether it stepped."""
    if not th.isfinite(loss):
        return False
    optimizer.zero_grad()
    loss.backward()
    grads = [p.grad for p in network.parameters() if p.grad is not None]
    # the 2-norm (fused over tensors) is non-finite iff some entry is (or squares overflow: a diverged step, skipped too)
    if grads and not bool(th.isfinite(th.nn.utils.get_total_norm(grads, norm_type=2.0))):
        return False
    optimizer.step()
    return True


def guard_update(name: str, network: th.nn.Module, optimizer: th.optim.Optimizer, saved: Snapshot, skipped: int,
                 stats: dict[str, float]) -> bool:
    """After an update of ``network``: count its skipped steps in ``stats`` and, if its parameters or buffers are no
    longer finite, restore the state of before the update. Counted: ``{name}_skipped_updates_total``,
    ``{name}_restored_updates`` and ``{name}_nonfinite_parameters`` (tensors non-finite since before the update,
    e.g. set by hand: nothing finite to restore). :return: whether the update was rolled back"""
    stats[f"{name}_skipped_updates_total"] = stats.get(f"{name}_skipped_updates_total", 0.0) + skipped
    bad = nonfinite_entries(network.state_dict())
    stats[f"{name}_nonfinite_parameters"] = 0.0
    if not bad:
        return False
    if nonfinite_entries(saved[0]):
        stats[f"{name}_nonfinite_parameters"] = float(len(bad))
        warnings.warn(f"GoCu: the {name} holds non-finite values in {bad[:3]} from before this update; nothing finite to restore")
        return False
    restore(network, optimizer, saved)
    stats[f"{name}_restored_updates"] = stats.get(f"{name}_restored_updates", 0.0) + 1
    warnings.warn(f"GoCu: a {name} update made {bad[:3]} non-finite; the update was rolled back")
    return True


class Trainer:
    """Fits the module's VAE and predictor, each with its Adam optimiser, drawing noise and minibatch orders from
    one torch generator.

    :param vae: the VAE
    :param predictor: the mastery predictor
    :param config: the module's settings
    :param adapter: raw observations -> network inputs
    :param device: torch device of the networks
    :param generator: torch generator of the fits (minibatch order, VAE noise)
    """

    def __init__(self, vae: ConvVAE | MlpVAE, predictor: MasteryPredictor, config: CuriosityConfig, adapter: ObservationAdapter,
                 device: th.device, generator: th.Generator) -> None:
        self.vae, self.predictor, self.config, self.adapter, self.device, self.generator = vae, predictor, config, adapter, device, generator
        # foreach: Adam's multi-tensor step, the same values as its per-parameter loop (tested) in fewer calls
        self.vae_optimizer = th.optim.Adam(vae.parameters(), lr=config.vae_lr, foreach=True)
        self.predictor_optimizer = th.optim.Adam(predictor.parameters(), lr=config.predictor_lr, foreach=True)

    # ------------------------------------------------------------------ VAE
    def vae_job(self, observations: np.ndarray, rng: np.random.Generator, pixel_weighting: float, epochs: int | None = None,
                patience: int | None = None) -> VaeJob | None:
        """The job of a VAE update on ``observations`` (the memory bank's; copied), or None if there is nothing to do.

        :param rng: draws the held-out part
        :param pixel_weighting: exponent of the rare-colour weighting (0: none)
        :param epochs: default ``vae_update_epochs``
        :param patience: default ``vae_patience``
        """
        cfg = self.config
        epochs = cfg.vae_update_epochs if epochs is None else epochs
        patience = cfg.vae_patience if patience is None else patience
        data = observations.copy()
        if len(data) == 0 or epochs == 0:
            return None
        weights = np.ones(len(data), dtype=np.float32)
        if cfg.vae_dedupe:
            first, inverse = distinct_rows(data)
            data = data[first]
            c = np.bincount(inverse, minlength=len(first)).astype(np.float64)
            weights = (c * len(c) / c.sum()).astype(np.float32)
        job = VaeJob(data, weights, epochs, patience, threads=th.get_num_threads())
        if pixel_weighting > 0:  # fitted to all the update's observations, the held-out ones included
            job.pixel_weights = PixelWeights.fit_observations(data, weights, self.adapter.to_tensor, pixel_weighting)
        n_val = int(round(VAE_HOLDOUT * len(data)))
        if patience > 0 and n_val >= 1:
            order = rng.permutation(len(data))
            val, train = np.sort(order[:n_val]), np.sort(order[n_val:])
            job.data, job.weights, job.val_data, job.val_weights = data[train], weights[train], data[val], weights[val]
        return job

    @th.no_grad()
    def vae_val_loss(self, data: np.ndarray, weights: np.ndarray, pixel_weights: PixelWeights | None = None) -> float:
        """Loss of eq 8 (weighted mean, eval mode: z = mu) on held-out observations, by chunks of 1024."""
        was_training = self.vae.training
        self.vae.eval()
        total = 0.0
        for start in range(0, len(data), 1024):
            x = self.adapter.to_tensor(data[start : start + 1024], self.device)
            w = th.from_numpy(weights[start : start + 1024]).to(self.device)
            total += float(vae_loss(self.vae, x, self.config.vae_beta, w, pixel_weights=pixel_weights)[0]) * len(x)
        self.vae.train(was_training)
        return total / len(data)

    def fit_vae(self, job: VaeJob, on_epoch: Callable[[int], None] | None = None) -> VaeFit:
        """Fit the VAE (eq 8) to a job; with held-out data, stop early and keep the best epoch's weights (the
        starting ones if no epoch beats them).

        :param on_epoch: called with the epoch number after each epoch (the VAE in train mode), for probes
        """
        cfg = self.config
        with torch_threads(job.threads):
            t0 = time.perf_counter()
            saved = snapshot(self.vae, self.vae_optimizer)
            early = job.val_data is not None and job.val_weights is not None and job.patience > 0
            start_loss = self.vae_val_loss(job.val_data, job.val_weights, job.pixel_weights) if early else float("nan")
            stopping, best_state = EarlyStopping(start_loss, job.patience), None
            self.vae.train()
            losses, skipped = [], 0
            n = len(job.data)
            epoch = -1
            for epoch in range(job.epochs):
                order = th.randperm(n, generator=self.generator).numpy()
                for start in range(0, n, cfg.vae_batch_size):
                    idx = order[start : start + cfg.vae_batch_size]
                    x = self.adapter.to_tensor(job.data[idx], self.device)
                    w = th.from_numpy(job.weights[idx]).to(self.device)
                    loss, _, _ = vae_loss(self.vae, x, cfg.vae_beta, w, generator=self.generator, pixel_weights=job.pixel_weights)
                    if not guarded_step(self.vae, self.vae_optimizer, loss):
                        skipped += 1
                        continue
                    losses.append(float(loss.detach()))
                if on_epoch is not None:
                    on_epoch(epoch)
                if early:
                    if stopping.update(epoch + 1, self.vae_val_loss(job.val_data, job.val_weights, job.pixel_weights)):
                        best_state = copy.deepcopy(self.vae.state_dict())
                    elif stopping.stop:
                        break
            epochs_run = epoch + 1
            best_epoch = stopping.best_epoch if early else epochs_run
            if early and stopping.best_epoch < epochs_run:
                self.vae.load_state_dict(best_state if best_state is not None else saved[0])
            self.vae.eval()
            collapsed = best_epoch > 0 and self.embeds_to_one_point(job.data if job.val_data is None else job.val_data)
            if collapsed:  # every goal would share one embedding: keep the encoder of before the fit
                restore(self.vae, self.vae_optimizer, saved)  # a state dict: the VAE stays in eval mode
                best_epoch = 0
                warnings.warn("GoCu: a VAE update embedded every frame to one point (dead encoder units); the update was rolled back")
            return VaeFit(saved, losses, skipped, n + (0 if job.val_data is None else len(job.val_data)), time.perf_counter() - t0,
                          epochs_run, best_epoch, start_loss, stopping.best_loss, collapsed)

    @th.no_grad()
    def embeds_to_one_point(self, data: np.ndarray) -> bool:
        """Whether the VAE embeds the first 1024 of ``data`` to one finite point although they hold distinct observations
        (non-finite embeddings are :func:`guard_update`'s)."""
        data = data[:1024]
        if len(distinct_rows(data)[0]) < 2:
            return False
        phi = self.vae.embed(self.adapter.to_tensor(data, self.device))
        return bool(th.isfinite(phi).all()) and bool(th.equal(phi.amin(0), phi.amax(0)))

    # ------------------------------------------------------------------ predictor
    def predictor_job(self, phi_s: th.Tensor, phi_g: th.Tensor, dist: th.Tensor, target: th.Tensor | None = None,
                      quality: QualityPairs | None = None) -> PredictorJob | None:
        """The job of a predictor update on drawn pairs: non-finite embeddings dropped, each distinct pair kept once
        and weighted by its count (the same objective as the whole draw, fewer optimiser steps); None when fewer than
        two pairs are left.

        :param target: each pair's label (None: eq 15-16, at fit time)
        :param quality: held-out pairs that score the fit"""
        keep = th.isfinite(phi_s).all(1) & th.isfinite(phi_g).all(1)  # a broken VAE's embeddings teach nothing
        columns = [phi_s[keep], phi_g[keep], dist[keep, None]] + ([] if target is None else [target[keep, None]])
        if len(columns[0]) < 2 and not (self.config.predictor_epochs == 0 and quality is not None):  # nothing to fit or score
            return None
        drawn = len(columns[0])
        weights = th.ones(drawn)
        if drawn:
            rows = np.ascontiguousarray(th.cat(columns, dim=1).numpy())
            _, first, counts = np.unique(rows.view(np.dtype((np.void, rows.itemsize * rows.shape[1]))).ravel(), return_index=True, return_counts=True)
            if len(first) < 2:
                first, counts = np.arange(drawn), np.ones(drawn, dtype=np.int64)
            first = th.from_numpy(first)
            columns = [c[first] for c in columns]
            weights = th.from_numpy(counts * (len(counts) / counts.sum())).float()  # mean 1 over the distinct pairs
        d = self.device
        phi_s, phi_g, dist = (c.to(d) for c in columns[:3])
        return PredictorJob(phi_s, phi_g, dist[:, 0], weights.to(d), drawn, th.get_num_threads(),
                            None if target is None else columns[3][:, 0].to(d), None if quality is None else quality.to(d))

    @th.no_grad()
    def label_pairs(self, phi_s: th.Tensor, phi_g: th.Tensor, dist: th.Tensor) -> th.Tensor:
        """p_skill of eq 15-16 for each pair, with the predictor's current belief as the prior
        (``prior = 1 - m(phi(s), phi(g))``, the belief that the skill is *not* mastered)."""
        cfg = self.config
        prior = 1.0 - self.predictor.mastery(phi_s, phi_g)
        return mastered_probability(complexity_score(prior, dist, cfg.prior_weight, cfg.distance_weight), cfg.label_threshold, cfg.label_slope)

    def fit_predictor(self, job: PredictorJob, on_epoch: Callable[[int], None] | None = None) -> PredictorFit:
        """Fit the predictor to the job's labels (eq 15-16's when it has none) for ``predictor_epochs`` epochs, then
        score it on the job's held-out pairs.

        :param on_epoch: called with the epoch number after each epoch (the predictor in train mode), for probes
        """
        cfg = self.config
        with torch_threads(job.threads):
            t0 = time.perf_counter()
            if job.target is not None:
                p_skill = target = job.target
            else:
                p_skill = target = self.label_pairs(job.phi_s, job.phi_g, job.dist)  # soft targets
            saved = snapshot(self.predictor, self.predictor_optimizer)
            self.predictor.train()
            n = len(job.phi_s)
            losses, accs, skipped = [], [], 0
            for epoch in range(cfg.predictor_epochs):
                order = th.randperm(n, generator=self.generator)
                for start in range(0, n, cfg.predictor_batch_size):
                    idx = order[start : start + cfg.predictor_batch_size]
                    if len(idx) < 2:  # batch norm needs two samples
                        continue
                    logits = self.predictor(job.phi_s[idx], job.phi_g[idx])
                    t, w = target[idx], job.weights[idx]
                    loss, logp = mastery_loss(logits, t, w)
                    if not guarded_step(self.predictor, self.predictor_optimizer, loss):
                        skipped += 1
                        continue
                    losses.append(loss.item())
                    accs.append(float((w * ((logp[:, 1] > logp[:, 0]) == (t > 0.5)).float()).sum() / w.sum()))
                if on_epoch is not None:
                    on_epoch(epoch)
            self.predictor.eval()
            mastered = float((job.weights * (p_skill > 0.5).float()).sum() / job.weights.sum()) if n else float("nan")
            quality = {} if job.quality is None else job.quality.score(self.predictor.mastery)
            return PredictorFit(saved, losses, accs, skipped, n, job.drawn, mastered, time.perf_counter() - t0, quality)


def mean_or_nan(values: Sequence[float]) -> float:
    """The mean of ``values``, NaN when there are none."""
    return float(np.mean(values)) if len(values) else float("nan")

