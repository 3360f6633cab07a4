"""The two networks of GoCu: the VAE that embeds observations (eq 8) and the mastery predictor m(phi(s), phi(g)).

The predictor's inference path is the hot path of GoCu (K goals x n_envs pairs every step). Its first
layer is split, ``W [phi(s); phi(g)] = W_s phi(s) + W_g phi(g)``, and batch norm is folded into the linear
layers (:class:`FoldedPredictor`), which computes the same function as the module in eval mode.
"""

from __future__ import annotations

from typing import Any, Callable, Iterable, Sequence

import torch as th
from torch import nn
from torch.nn import functional as F



def _noise(like: th.Tensor, generator: th.Generator | None) -> th.Tensor:
    if generator is None or generator.device == like.device:
        return th.randn(like.shape, generator=generator, dtype=like.dtype, device=like.device)
    return th.randn(like.shape, generator=generator, dtype=like.dtype, device=generator.device).to(like.device)  # a CPU generator, a GPU VAE


class ConvVAE(nn.Module):
    """The paper's image VAE (section 5.1.2).

    Encoder: conv 32, 32, 32 filters, kernel 3, strides 2, 1, 1, ReLU, then a fully connected layer of
    ``embed_dim`` units (ReLU): that layer is the embedding phi(s). Gaussian latent of size ``latent_dim``.
    The decoder mirrors the encoder; pixels are modelled as Bernoulli (binary cross-entropy on [0, 1]).

    :param input_shape: (C, H, W) of the float input in [0, 1]
    :param embed_dim: size of the embedding phi (the FC layer after the convolutions)
    :param latent_dim: size of the latent mu and sigma
    """

    def __init__(self, input_shape: Sequence[int], embed_dim: int = 128, latent_dim: int = 10) -> None:
        super().__init__()
        c, h, w = input_shape
        self.input_shape = (c, h, w)
        self.conv = nn.Sequential(
            nn.Conv2d(c, 32, 3, stride=2, padding=1),
            nn.ReLU(),
            nn.Conv2d(32, 32, 3, stride=1, padding=1),
            nn.ReLU(),
            nn.Conv2d(32, 32, 3, stride=1, padding=1),
            nn.ReLU(),
        )
        self.feature_hw = ((h + 1) // 2, (w + 1) // 2)
        n_flat = 32 * self.feature_hw[0] * self.feature_hw[1]
        self.fc = nn.Linear(n_flat, embed_dim)
        self.mu = nn.Linear(embed_dim, latent_dim)
        self.logvar = nn.Linear(embed_dim, latent_dim)
        self.decoder_fc = nn.Sequential(
            nn.Linear(latent_dim, embed_dim), nn.ReLU(), nn.Linear(embed_dim, n_flat), nn.ReLU()
        )
        self.deconv = nn.Sequential(
            # a stride-1 transposed convolution is a convolution: nn.Conv2d is the faster kernel on a CPU
            nn.Conv2d(32, 32, 3, stride=1, padding=1),
            nn.ReLU(),
            nn.Conv2d(32, 32, 3, stride=1, padding=1),
            nn.ReLU(),
            nn.ConvTranspose2d(32, c, 4, stride=2, padding=1),
        )

    def embed(self, x: th.Tensor) -> th.Tensor:
        """phi(x): the embedding used for goals and states (not mu)."""
        return F.relu(self.fc(self.conv(x).flatten(1)))

    def forward(
        self, x: th.Tensor, generator: th.Generator | None = None
    ) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
        """:param generator: source of the reparameterisation noise (training mode); the module's own generator
            keeps training independent of the global torch RNG (which the policy samples from)
        :return: reconstruction logits, mu, log-variance"""
        phi = self.embed(x)
        mu, logvar = self.mu(phi), self.logvar(phi)
        z = mu + _noise(mu, generator) * th.exp(0.5 * logvar) if self.training else mu
        y = self.decoder_fc(z).view(-1, 32, *self.feature_hw)
        logits = self.deconv(y)[..., : self.input_shape[1], : self.input_shape[2]]
        return logits, mu, logvar

    def reconstruction_loss(self, logits: th.Tensor, x: th.Tensor, pixel_weights: th.Tensor | None = None) -> th.Tensor:
        """Binary cross-entropy summed over each image's channels and pixels, the pixels weighted by
        ``pixel_weights`` (n, H, W) if given."""
        bce = F.binary_cross_entropy_with_logits(logits, x, reduction="none")
        if pixel_weights is not None:
            bce = bce * pixel_weights.unsqueeze(1)
        return bce.flatten(1).sum(1)

    def reconstruct(self, x: th.Tensor) -> th.Tensor:
        return th.sigmoid(self(x)[0])


class MlpVAE(nn.Module):
    """VAE for vector observations: MLP encoder (256, ``embed_dim``), Gaussian latent, mirrored decoder,
    Gaussian likelihood (squared error).

    :param input_shape: (D,)
    :param embed_dim: size of the embedding phi
    :param latent_dim: size of the latent
    """

    def __init__(self, input_shape: Sequence[int], embed_dim: int = 128, latent_dim: int = 10) -> None:
        super().__init__()
        (d,) = input_shape
        self.input_shape = (d,)
        self.encoder = nn.Sequential(nn.Linear(d, 256), nn.ReLU(), nn.Linear(256, embed_dim), nn.ReLU())
        self.mu = nn.Linear(embed_dim, latent_dim)
        self.logvar = nn.Linear(embed_dim, latent_dim)
        self.decoder = nn.Sequential(
            nn.Linear(latent_dim, embed_dim), nn.ReLU(), nn.Linear(embed_dim, 256), nn.ReLU(), nn.Linear(256, d)
        )

    def embed(self, x: th.Tensor) -> th.Tensor:
        return self.encoder(x)

    def forward(
        self, x: th.Tensor, generator: th.Generator | None = None
    ) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
        phi = self.embed(x)
        mu, logvar = self.mu(phi), self.logvar(phi)
        z = mu + _noise(mu, generator) * th.exp(0.5 * logvar) if self.training else mu
        return self.decoder(z), mu, logvar

    def reconstruction_loss(self, recon: th.Tensor, x: th.Tensor) -> th.Tensor:
        return 0.5 * ((recon - x) ** 2).sum(1)

    def reconstruct(self, x: th.Tensor) -> th.Tensor:
        return self(x)[0]


class PixelWeights:
    """Per-pixel weights of the reconstruction term of eq 8 that make rare colours count: a pixel of colour c
    weighs ``f_c ** -exponent / sum_c' f_c' ** (1 - exponent)``, where ``f_c`` is the share of colour c among
    the pixels of the data the weights are fitted to. Over that data the mean pixel weight is 1, so the
    reconstruction term keeps its scale against the KL term; exponent 0 weighs every pixel 1 (the paper),
    exponent 1 gives every colour the same total weight.

    On DoorKey the key, the door and the goal square are a few pixels of yellow or green in a grey view: the
    paper's loss lets the VAE drop them and pay almost nothing (``benchmarks/probes/embedding_phases.py``).

    A colour is the pixel's channel values in [0, 1], read as bytes and cut to ``min(8, 15 // C)`` bits each
    (5 bits of red, green and blue for RGB, all 8 for grey), so at most 2**15 colours. A colour the weights
    were not fitted on weighs as one seen in a single pixel.

    :param table: weight of each colour id, shape (2 ** (bits * C),)
    :param channels: C
    """

    def __init__(self, table: th.Tensor, channels: int) -> None:
        self.channels = channels
        if table.shape != (self.n_colours(channels),):
            raise ValueError(f"table must have shape ({self.n_colours(channels)},) for {channels} channels, got {tuple(table.shape)}")
        self.table = table

    @staticmethod
    def bits(channels: int) -> int:
        """Bits kept of each channel's byte."""
        return min(8, 15 // channels)

    @classmethod
    def n_colours(cls, channels: int) -> int:
        return 2 ** (cls.bits(channels) * channels)

    @classmethod
    def colour_ids(cls, x: th.Tensor) -> th.Tensor:
        """Colour id of every pixel of ``x`` (n, C, H, W) in [0, 1]: shape (n, H, W), int64."""
        if x.numel():
            low, high = (float(v) for v in th.aminmax(x))
            if low < 0 or high > 1:
                raise ValueError(f"pixel weights need images in [0, 1] (the VAE's Bernoulli pixels), got values in [{low}, {high}]")
        channels = x.shape[1]
        bits = cls.bits(channels)
        q = th.round(x.float() * 255).to(th.int64) >> (8 - bits)
        ids = q[:, 0]
        for c in range(1, channels):
            ids = (ids << bits) | q[:, c]
        return ids

    @classmethod
    def fit(cls, batches: Iterable[tuple[th.Tensor, th.Tensor]], exponent: float) -> "PixelWeights":
        """Weights from colour shares over ``batches`` of (images (n, C, H, W) in [0, 1], sample weights (n,))
        (a sample weight is an image's multiplicity).

        :param exponent: in [0, 1]
        """
        if not 0 <= exponent <= 1:
            raise ValueError(f"exponent must be in [0, 1], got {exponent}")
        counts, channels = None, None
        for x, w in batches:
            channels = x.shape[1]
            ids = cls.colour_ids(x).flatten(1)
            per_image = w.to(th.float64)[:, None].expand_as(ids)
            part = th.bincount(ids.flatten(), per_image.flatten(), minlength=cls.n_colours(channels))
            counts = part if counts is None else counts + part
        if counts is None or float(counts.sum()) <= 0:
            raise ValueError("PixelWeights.fit needs at least one image of positive weight")
        share = counts / counts.sum()
        seen = share > 0
        share = th.where(seen, share, share[seen].min())
        raw = share ** -exponent
        table = raw / (share[seen] * raw[seen]).sum()
        return cls(table.float(), channels)

    @classmethod
    def fit_observations(
        cls, raw: Any, sample_weights: Any, to_tensor: Callable[[Any], th.Tensor], exponent: float, chunk: int = 1024
    ) -> "PixelWeights":
        """:meth:`fit` over raw observations, turned into images ``chunk`` at a time by ``to_tensor`` (a VAE
        update's data: its images in [0, 1] are never all in memory at once).

        :param raw: the observations (indexable by slices)
        :param sample_weights: their multiplicities, a numpy array of the same length
        """
        return cls.fit(
            ((to_tensor(raw[i : i + chunk]), th.as_tensor(sample_weights[i : i + chunk])) for i in range(0, len(raw), chunk)),
            exponent,
        )

    def __call__(self, x: th.Tensor) -> th.Tensor:
        """Weights of the pixels of ``x`` (n, C, H, W) in [0, 1]: shape (n, H, W)."""
        if x.shape[1] != self.channels:
            raise ValueError(f"x must have {self.channels} channels (the weights were fitted on them), got {x.shape[1]}")
        return self.table.to(x.device)[self.colour_ids(x)]


def vae_loss(
    vae: ConvVAE | MlpVAE,
    x: th.Tensor,
    beta: float = 1.0,
    weights: th.Tensor | None = None,
    generator: th.Generator | None = None,
    pixel_weights: PixelWeights | None = None,
) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
    """Negative of eq 8, averaged over the batch: reconstruction + beta * KL(q(z|x) || N(0, I)).

    :param weights: optional per-sample weights (the multiplicity of a de-duplicated observation)
    :param generator: source of the reparameterisation noise
    :param pixel_weights: weights of the pixels in the reconstruction term (images only; None: all 1, the paper)
    :return: total loss, reconstruction term, KL term
    """
    out, mu, logvar = vae(x, generator)
    if pixel_weights is None:
        recon = vae.reconstruction_loss(out, x)
    elif isinstance(vae, ConvVAE):
        recon = vae.reconstruction_loss(out, x, pixel_weights(x))
    else:
        raise ValueError(f"pixel_weights apply to a ConvVAE (image observations), got {type(vae).__name__}")
    kl = -0.5 * (1 + logvar - mu.pow(2) - logvar.exp()).sum(1)
    if weights is not None:
        recon, kl = recon * weights, kl * weights
    recon, kl = recon.mean(), kl.mean()
    return recon + beta * kl, recon, kl


class MasteryPredictor(nn.Module):
    """m(phi(s), phi(g)): the probability that goal g is mastered from state s (section 4.2.2).

    An MLP on the concatenation [phi(s), phi(g)]: each hidden layer is Linear -> BatchNorm -> ReLU;
    the output is a 2-class softmax (class 1 = mastered).

    :param embed_dim: size of phi
    :param hidden_sizes: hidden layer sizes (paper: five of 512 for MiniGrid, three of 512 for MuJoCo)
    """

    def __init__(self, embed_dim: int, hidden_sizes: Sequence[int] = (512,) * 5) -> None:
        super().__init__()
        if len(hidden_sizes) < 1 or min(hidden_sizes) < 1:
            raise ValueError(f"predictor_hidden must hold at least one positive layer size, got {tuple(hidden_sizes)}")
        self.embed_dim = embed_dim
        layers: list[nn.Module] = []
        n_in = 2 * embed_dim
        for n_out in hidden_sizes:
            layers += [nn.Linear(n_in, n_out), nn.BatchNorm1d(n_out), nn.ReLU()]
            n_in = n_out
        self.hidden = nn.Sequential(*layers)
        self.out = nn.Linear(n_in, 2)

    def forward(self, phi_s: th.Tensor, phi_g: th.Tensor) -> th.Tensor:
        """:return: logits (n, 2)"""
        return self.out(self.hidden(th.cat([phi_s, phi_g], dim=-1)))

    def mastery(self, phi_s: th.Tensor, phi_g: th.Tensor) -> th.Tensor:
        """:return: probability of class "mastered", shape (n,)"""
        return th.softmax(self(phi_s, phi_g), dim=-1)[:, 1]

    def fold(self) -> "FoldedPredictor":
        """The eval-mode function of this network with batch norm folded in and the first layer split."""
        return FoldedPredictor(self)


def mastery_loss(logits: th.Tensor, target: th.Tensor, weights: th.Tensor | None = None) -> tuple[th.Tensor, th.Tensor]:
    """The predictor's training loss: cross-entropy of its two logits against the mastery targets (p_skill of
    eq 16 as soft targets, or 0/1 labels), the mean over the minibatch of ``weights`` x cross-entropy.

    :param logits: (n, 2) the predictor's output (class 1 = mastered); taken in float32
    :param target: (n,) probability that each pair's goal is mastered, in [0, 1]
    :param weights: (n,) each pair's weight (its multiplicity in a de-duplicated draw); None: every pair weighs 1
    :return: the loss (a scalar) and the log-probabilities (n, 2)
    """
    logp = th.log_softmax(logits.float(), dim=-1)
    log_likelihood = target * logp[:, 1] + (1 - target) * logp[:, 0]
    return -(log_likelihood if weights is None else weights * log_likelihood).mean(), logp


class FoldedPredictor:
    """Inference form of :class:`MasteryPredictor` (eval mode), built for scoring K goals per state.

    * batch norm is folded into the preceding linear layer: ``W' = W * s``, ``b' = (b - mu) * s + beta``
      with ``s = gamma / sqrt(var + eps)``;
    * the first layer is split into a state half and a goal half, so the goal half is computed once per
      episode (:meth:`goal_part`) and the state half once per state (:meth:`state_part`);
    * the 2-class softmax is ``sigmoid(l_1 - l_0)``: one output row.

    The result equals ``MasteryPredictor.mastery`` in eval mode up to float rounding.

    :param predictor: the network to fold (its current weights and batch-norm statistics are copied)
    """

    def __init__(self, predictor: MasteryPredictor) -> None:
        with th.no_grad():
            linears = [m for m in predictor.hidden if isinstance(m, nn.Linear)]
            norms = [m for m in predictor.hidden if isinstance(m, nn.BatchNorm1d)]
            folded = []
            for lin, bn in zip(linears, norms):
                s = bn.weight / th.sqrt(bn.running_var + bn.eps)
                folded.append(((lin.weight * s[:, None]).clone(), ((lin.bias - bn.running_mean) * s + bn.bias).clone()))
            d = predictor.embed_dim
            w1, self.b1 = folded[0]
            # on the CPU, where the embeddings and goal halves of scoring live, whatever the predictor's device
            self.b1 = self.b1.cpu()
            self.w_state = w1[:, :d].t().contiguous().cpu()  # (d, h)
            self.w_goal = w1[:, d:].t().contiguous().cpu()  # (d, h)
            self.layers = [(w.t().contiguous().cpu(), b.cpu()) for w, b in folded[1:]]  # x @ w + b
            wo, bo = predictor.out.weight, predictor.out.bias
            self.w_out = (wo[1] - wo[0]).clone()[:, None].cpu()  # (h, 1)
            self.b_out = (bo[1] - bo[0]).clone().cpu()

    def state_part(self, phi_s: th.Tensor) -> th.Tensor:
        """First-layer pre-activation of the state half, bias included: (n, h)."""
        return th.addmm(self.b1, phi_s, self.w_state)

    def goal_part(self, phi_g: th.Tensor) -> th.Tensor:
        """First-layer pre-activation of the goal half: (..., h)."""
        return phi_g @ self.w_goal

    def mastery_from_parts(self, state_part: th.Tensor, goal_part: th.Tensor) -> th.Tensor:
        """Mastery probabilities of every (state, goal) pair.

        :param state_part: (n, h) from :meth:`state_part`
        :param goal_part: (n, K, h), the goals of each state's episode, from :meth:`goal_part`
        :return: (n, K)
        """
        n, k, h = goal_part.shape
        x = (goal_part + state_part[:, None, :]).relu_().view(n * k, h)
        for w, b in self.layers:
            x = th.addmm(b, x, w).relu_()
        return th.sigmoid(th.addmm(self.b_out, x, self.w_out)).view(n, k)

    def mastery(self, phi_s: th.Tensor, phi_g: th.Tensor) -> th.Tensor:
        """Mastery probability of paired rows: (n,)."""
        return self.mastery_from_parts(self.state_part(phi_s), self.goal_part(phi_g)[:, None, :])[:, 0]
