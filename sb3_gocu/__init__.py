"""sb3-gocu: goal-based curiosity (GoCu) for Stable-Baselines3.

``from sb3_gocu import PPO_GoCu, GoCuVecEnvWrapper, GoCuWrapper, GoCuCallback, GoalCuriosityModule``.
Importing the package also registers the ``GoCu/...`` environment ids.
"""

from sb3_gocu.callbacks import GoCuCallback
from sb3_gocu.checkpoints import GoCuCheckpointCallback, latest_checkpoint
from sb3_gocu.curiosity import PAPER_CURIOSITY_KWARGS, CuriosityConfig, GoalCuriosityModule
from sb3_gocu.envs import register_envs
from sb3_gocu.exploration import ExplorationCallback, RoomInfoWrapper
from sb3_gocu.policies import PaperCNN
from sb3_gocu.ppo_gocu import PAPER_N_ENVS, PAPER_PPO_KWARGS, PPO_GoCu
from sb3_gocu.wrappers import GoCuVecEnvWrapper, GoCuWrapper, find_gocu_module

__version__ = "0.1.0"

register_envs()

__all__ = [
    "GoCuCallback",
    "GoCuCheckpointCallback",
    "GoCuVecEnvWrapper",
    "GoCuWrapper",
    "CuriosityConfig",
    "ExplorationCallback",
    "GoalCuriosityModule",
    "PAPER_CURIOSITY_KWARGS",
    "PAPER_N_ENVS",
    "PAPER_PPO_KWARGS",
    "PPO_GoCu",
    "PaperCNN",
    "RoomInfoWrapper",
    "find_gocu_module",
    "latest_checkpoint",
    "register_envs",
    "__version__",
]
