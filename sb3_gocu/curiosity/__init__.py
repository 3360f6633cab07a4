"""The curiosity maths of GoCu on tensors alone (torch, numpy and gymnasium spaces; no Stable-Baselines3)."""

from sb3_gocu.curiosity.config import PAPER_CURIOSITY_KWARGS, CuriosityConfig
from sb3_gocu.curiosity.goals import GOAL_STRATEGIES, GoalBuffer, select_goal_steps
from sb3_gocu.curiosity.module import GoalCuriosityModule
from sb3_gocu.curiosity.networks import ConvVAE, FoldedPredictor, MasteryPredictor, MlpVAE, PixelWeights, mastery_loss, vae_loss
from sb3_gocu.curiosity.observations import ObservationAdapter
from sb3_gocu.curiosity.reward import (
    AGGREGATIONS,
    IntrinsicReturnNormalizer,
    RunningMean,
    RunningMeanStd,
    complexity_score,
    curiosity_reward,
    revisit_factor,
    mastered_probability,
)
from sb3_gocu.curiosity.stores import MemoryBank, TrajectoryStore

__all__ = [
    "AGGREGATIONS",
    "PAPER_CURIOSITY_KWARGS",
    "CuriosityConfig",
    "GOAL_STRATEGIES",
    "ConvVAE",
    "FoldedPredictor",
    "GoalBuffer",
    "GoalCuriosityModule",
    "IntrinsicReturnNormalizer",
    "MasteryPredictor",
    "MemoryBank",
    "MlpVAE",
    "ObservationAdapter",
    "PixelWeights",
    "RunningMean",
    "RunningMeanStd",
    "TrajectoryStore",
    "complexity_score",
    "curiosity_reward",
    "revisit_factor",
    "mastered_probability",
    "mastery_loss",
    "select_goal_steps",
    "vae_loss",
]
