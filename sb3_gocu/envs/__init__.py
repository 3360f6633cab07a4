"""The paper's environments, registered as Gymnasium ids.

Importing this package registers the ids (via :func:`register_envs`, which is idempotent) without
importing ``minigrid`` or ``mujoco``: the entry points are strings, resolved by ``gym.make``.

- ``GoCu/DoorKey-5x5-v0``, ``GoCu/DoorKey-8x8-v0``, ``GoCu/DoorKey-11x11-v0``, ``GoCu/DoorKey-16x16-v0``:
  MiniGrid DoorKey, observed as a 32x32x3 uint8 RGB image of the agent's view (see ``minigrid_envs``).
- ``GoCu/VisualReacher-v0``, ``GoCu/VisualPusher-v0``: Reacher-v5 / Pusher-v5 observed as 32x32x3
  uint8 renders with a sparse success reward (see ``mujoco_envs``).
- ``GoCu/VisualSawyerReacher-v1``, ``GoCu/VisualSawyerDoorHook-v1``, ``GoCu/VisualSawyerPusher-v1``,
  ``GoCu/VisualSawyerMultiObjectPusher-v1``, ``GoCu/VisualSawyerPickAndPlace-v1``: the paper's Sawyer tasks as it defines
  them (a hand held to a plane or a small box, small workspaces, short episodes), 32x32x3 uint8 frames, sparse success
  reward (see ``sawyer_envs``).
- Atari: the ale-py ids in :data:`ATARI_HARD_EXPLORATION` are used directly (nothing to register).

Because registration happens on import, ``gym.make("sb3_gocu.envs:GoCu/DoorKey-8x8-v0")`` works in
a fresh process (e.g. a ``SubprocVecEnv`` worker started with ``spawn``/``forkserver``).

Making the envs needs an extra of the package: ``[minigrid]`` (DoorKey), ``[mujoco]`` (VisualReacher,
VisualPusher, VisualSawyer*) or ``[atari]`` (ale-py); without it, ``gym.make`` raises a ``ModuleNotFoundError`` naming the extra.
"""

from __future__ import annotations

import gymnasium as gym

__all__ = [
    "ATARI_HARD_EXPLORATION",
    "DOORKEY_IDS",
    "DOORKEY_SIZES",
    "GOCU_ENV_IDS",
    "MUJOCO_IDS",
    "SAWYER_IDS",
    "SAWYER_LENGTHS",
    "register_envs",
]

#: Hard-exploration Atari games (ale-py ids; ale-py ships the ROMs). Register them with
#: ``import ale_py; gym.register_envs(ale_py)`` and wrap with SB3's ``AtariWrapper``.
ATARI_HARD_EXPLORATION: tuple[str, ...] = ("ALE/MontezumaRevenge-v5", "ALE/PrivateEye-v5", "ALE/Pitfall-v5")

#: Grid sizes of the registered DoorKey ids.
DOORKEY_SIZES: tuple[int, ...] = (5, 8, 11, 16)
#: Registered DoorKey ids, smallest grid first.
DOORKEY_IDS: tuple[str, ...] = tuple(f"GoCu/DoorKey-{n}x{n}-v0" for n in DOORKEY_SIZES)
#: Registered MuJoCo ids (Gymnasium's Reacher and Pusher).
MUJOCO_IDS: tuple[str, ...] = ("GoCu/VisualReacher-v0", "GoCu/VisualPusher-v0")
#: Registered ids of the paper's Sawyer tasks (:mod:`sb3_gocu.envs.sawyer_envs`), with their episode lengths.
SAWYER_LENGTHS: dict[str, int] = {
    "GoCu/VisualSawyerReacher-v1": 50,
    "GoCu/VisualSawyerDoorHook-v1": 100,
    "GoCu/VisualSawyerPusher-v1": 100,
    "GoCu/VisualSawyerMultiObjectPusher-v1": 150,
    "GoCu/VisualSawyerPickAndPlace-v1": 50,
}
SAWYER_IDS: tuple[str, ...] = tuple(SAWYER_LENGTHS)
#: All ids registered by :func:`register_envs`.
GOCU_ENV_IDS: tuple[str, ...] = DOORKEY_IDS + MUJOCO_IDS + SAWYER_IDS


def register_envs() -> None:
    """
    Register the ``GoCu/*`` Gymnasium ids. Safe to call several times: ids already present in
    ``gymnasium.envs.registry`` are left untouched.

    DoorKey ids have no ``max_episode_steps`` (MiniGrid truncates itself after
    ``max_steps = 10 * size**2`` steps, which can be changed with the ``max_steps`` kwarg);
    VisualReacher / VisualPusher keep Reacher-v5's 50 and Pusher-v5's 100 steps (``TimeLimit``).
    """
    registry = gym.envs.registry
    for size in DOORKEY_SIZES:
        env_id = f"GoCu/DoorKey-{size}x{size}-v0"
        if env_id not in registry:
            gym.register(
                id=env_id,
                entry_point="sb3_gocu.envs.minigrid_envs:make_doorkey",
                kwargs={"size": size},
            )
    mujoco_specs = (
        ("GoCu/VisualReacher-v0", "sb3_gocu.envs.mujoco_envs:make_visual_reacher", 50),
        ("GoCu/VisualPusher-v0", "sb3_gocu.envs.mujoco_envs:make_visual_pusher", 100),
    )
    for env_id, entry_point, max_episode_steps in mujoco_specs:
        if env_id not in registry:
            gym.register(id=env_id, entry_point=entry_point, max_episode_steps=max_episode_steps)
    for env_id, max_episode_steps in SAWYER_LENGTHS.items():
        if env_id not in registry:
            gym.register(
                id=env_id, entry_point="sb3_gocu.envs.sawyer_envs:make_visual_sawyer", kwargs={"env_id": env_id},
                max_episode_steps=max_episode_steps,
            )


register_envs()
