"""Actor-critic policies with two value heads (V_e, V_gc) on one critic (section 4.1), and the paper's small
CNN for images that SB3's NatureCNN cannot take (it needs at least 36x36)."""

from __future__ import annotations

from functools import partial
from typing import Any

import gymnasium as gym
import torch as th
from gymnasium import spaces
from stable_baselines3.common.preprocessing import get_flattened_obs_dim, is_image_space
from stable_baselines3.common.policies import ActorCriticPolicy, MultiInputActorCriticPolicy
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor, CombinedExtractor, NatureCNN
from stable_baselines3.common.type_aliases import Schedule
from torch import nn

#: smallest image side NatureCNN accepts (8x8 stride 4, 4x4 stride 2, 3x3 stride 1)
NATURE_CNN_MIN_SIDE = 36


class PaperCNN(BaseFeaturesExtractor):
    """The paper's policy CNN (section 5.1.2): three conv layers of 16, 32, 64 filters, kernel 2, stride 2,
    padding 1, ReLU, then a linear layer to ``features_dim`` with ReLU.

    :param observation_space: a channel-first image space
    :param features_dim: number of output features
    :param normalized_image: whether the images are already in [0, 1] (SB3 convention)
    """

    def __init__(self, observation_space: gym.Space, features_dim: int = 256, normalized_image: bool = False) -> None:
        assert isinstance(observation_space, spaces.Box)
        super().__init__(observation_space, features_dim)
        n_channels = observation_space.shape[0]
        self.cnn = nn.Sequential(
            nn.Conv2d(n_channels, 16, kernel_size=2, stride=2, padding=1),
            nn.ReLU(),
            nn.Conv2d(16, 32, kernel_size=2, stride=2, padding=1),
            nn.ReLU(),
            nn.Conv2d(32, 64, kernel_size=2, stride=2, padding=1),
            nn.ReLU(),
            nn.Flatten(),
        )
        with th.no_grad():
            n_flatten = self.cnn(th.as_tensor(observation_space.sample()[None]).float()).shape[1]
        self.linear = nn.Sequential(nn.Linear(n_flatten, features_dim), nn.ReLU())

    def forward(self, observations: th.Tensor) -> th.Tensor:
        return self.linear(self.cnn(observations))


def default_image_extractor(observation_space: gym.Space) -> type[BaseFeaturesExtractor]:
    """NatureCNN where it fits, :class:`PaperCNN` for images smaller than 36x36."""
    assert isinstance(observation_space, spaces.Box)
    return NatureCNN if min(observation_space.shape[1:]) >= NATURE_CNN_MIN_SIDE else PaperCNN


class _TwoValueHeads:
    """Mixin: after the usual build, replace the value head by one with two outputs, (V_e, V_gc)."""

    def _build(self, lr_schedule: Schedule) -> None:
        super()._build(lr_schedule)  # type: ignore[misc]
        self.value_net = nn.Linear(self.mlp_extractor.latent_dim_vf, 2)  # type: ignore[attr-defined]
        if self.ortho_init:  # type: ignore[attr-defined]
            self.value_net.apply(partial(self.init_weights, gain=1))  # type: ignore[attr-defined]
        # the optimizer must see the new head
        self.optimizer = self.optimizer_class(  # type: ignore[attr-defined]
            self.parameters(), lr=lr_schedule(1), **self.optimizer_kwargs  # type: ignore[attr-defined]
        )


class GoCuActorCriticPolicy(_TwoValueHeads, ActorCriticPolicy):
    """``ActorCriticPolicy`` whose critic has two heads: ``predict_values`` and ``forward`` return values of
    shape (n, 2), column 0 the extrinsic value V_e, column 1 the curiosity value V_gc. All other arguments are
    those of SB3's ``ActorCriticPolicy``."""


class GoCuActorCriticCnnPolicy(GoCuActorCriticPolicy):
    """CNN policy with two value heads. The features extractor defaults to NatureCNN where the image is at
    least 36x36 and to the paper's :class:`PaperCNN` otherwise (e.g. 32x32 MiniGrid views).

    All arguments are those of SB3's ``ActorCriticCnnPolicy``.
    """

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        lr_schedule: Schedule,
        *args: Any,
        features_extractor_class: type[BaseFeaturesExtractor] | None = None,
        **kwargs: Any,
    ) -> None:
        if features_extractor_class is None:
            features_extractor_class = default_image_extractor(observation_space)
        super().__init__(observation_space, action_space, lr_schedule, *args, features_extractor_class=features_extractor_class, **kwargs)


class GoCuMultiInputActorCriticPolicy(_TwoValueHeads, MultiInputActorCriticPolicy):
    """``MultiInputActorCriticPolicy`` (Dict observations) with two value heads. Image entries smaller than
    36x36 get :class:`PaperCNN` instead of NatureCNN (:class:`SmallImageCombinedExtractor`)."""

    def __init__(
        self,
        observation_space: spaces.Dict,
        action_space: spaces.Space,
        lr_schedule: Schedule,
        *args: Any,
        features_extractor_class: type[BaseFeaturesExtractor] | None = None,
        **kwargs: Any,
    ) -> None:
        if features_extractor_class is None:
            features_extractor_class = SmallImageCombinedExtractor
        super().__init__(observation_space, action_space, lr_schedule, *args, features_extractor_class=features_extractor_class, **kwargs)


class SmallImageCombinedExtractor(CombinedExtractor):
    """SB3's ``CombinedExtractor`` (its forward is reused), choosing per image entry NatureCNN or, for images
    smaller than 36x36, :class:`PaperCNN`; vector entries are flattened."""

    def __init__(self, observation_space: spaces.Dict, cnn_output_dim: int = 256, normalized_image: bool = False) -> None:
        BaseFeaturesExtractor.__init__(self, observation_space, features_dim=1)
        extractors: dict[str, nn.Module] = {}
        total = 0
        for key, subspace in observation_space.spaces.items():
            if is_image_space(subspace, normalized_image=normalized_image):
                cnn = default_image_extractor(subspace)
                extractors[key] = cnn(subspace, features_dim=cnn_output_dim, normalized_image=normalized_image)
                total += cnn_output_dim
            else:
                extractors[key] = nn.Flatten()
                total += get_flattened_obs_dim(subspace)
        self.extractors = nn.ModuleDict(extractors)
        self._features_dim = total
