"""MiniGrid DoorKey observed as a small RGB image of the agent's partial view.

The registered ids ``GoCu/DoorKey-{5x5,8x8,11x11,16x16}-v0`` are built with :func:`make_doorkey`:
``minigrid.envs.DoorKeyEnv(size=N)`` wrapped by :class:`DoorKeyRGB32`, which replaces MiniGrid's
``Dict`` observation by a ``Box(0, 255, (32, 32, 3), uint8)`` RGB image (HWC) of the agent's
point of view and adds ``info["is_success"]`` and ``info["task_phase"]`` (how far the episode has got:
0 nothing yet, 1 key picked up, 2 door opened, 3 goal reached), which tells whether an agent explores.
Actions (``Discrete(7)``), the sparse reward (``1 - 0.9 * step_count / max_steps`` on reaching
the goal, else ``0``) and the episode length (MiniGrid's own ``max_steps = 10 * size**2``,
signalled as ``truncated``) are MiniGrid's, unchanged.
"""

from __future__ import annotations

import os
from typing import Any, Optional, SupportsFloat

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from sb3_gocu._extras import missing_extra

# minigrid imports pygame, which prints a banner on import unless told not to.
os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")

try:
    import cv2
    from minigrid.core.world_object import Door, Key
    from minigrid.envs import DoorKeyEnv
except ModuleNotFoundError as e:  # the [minigrid] extra brings both
    raise missing_extra(e, "sb3_gocu.envs.minigrid_envs (the GoCu/DoorKey-* ids)", "minigrid") from e

__all__ = ["FRAME_CACHE_SIZE", "TASK_PHASES", "DoorKeyRGB32", "DoorKeyViewEnv", "make_doorkey"]

#: Names of the values of ``info["task_phase"]``: the furthest stage of DoorKey reached in the episode so far.
TASK_PHASES = ("start", "key", "door", "goal")

#: Maximum number of memoised observation frames (about 3.3 kB each at 32x32) per process; the cache
#: is emptied when full.
FRAME_CACHE_SIZE = 8192
_FRAME_CACHE: dict[tuple[int, int, bytes, bytes], np.ndarray] = {}


class DoorKeyViewEnv(DoorKeyEnv):
    """
    ``minigrid.envs.DoorKeyEnv`` that remembers the agent-view grid it computes for its observation.

    Behaviour (dynamics, observations, rewards) is exactly ``DoorKeyEnv``'s; the only addition is the
    attribute ``last_view``: the ``(grid, vis_mask)`` pair of the last default ``gen_obs_grid()`` call
    (made by ``gen_obs()`` at the end of every ``step``/``reset``). :class:`DoorKeyRGB32` consumes it
    instead of recomputing the view, which halves MiniGrid's per-step cost.

    :param size: Grid side length (walls included).
    :param kwargs: Keyword arguments for ``DoorKeyEnv``.
    """

    def __init__(self, size: int = 8, **kwargs: Any) -> None:
        self.last_view: Optional[tuple[Any, np.ndarray]] = None
        super().__init__(size=size, **kwargs)

    def gen_obs_grid(self, agent_view_size: Optional[int] = None) -> tuple[Any, np.ndarray]:
        """
        Compute the agent's view grid and visibility mask (``MiniGridEnv.gen_obs_grid``) and remember them.

        :param agent_view_size: View size; ``None`` for the env's ``agent_view_size``.
        :return: ``(grid, vis_mask)``.
        """
        view = super().gen_obs_grid(agent_view_size)
        if agent_view_size is None or agent_view_size == self.agent_view_size:
            self.last_view = view
        return view


class DoorKeyRGB32(gym.ObservationWrapper):
    """
    Observe a MiniGrid env through a small RGB image of the agent's partial (egocentric) view.

    The agent-POV frame (``env.unwrapped.get_frame(tile_size=tile_size, agent_pov=True)``,
    ``agent_view_size * tile_size`` pixels square, i.e. 56x56 by default) is resized to
    ``image_size x image_size`` with ``cv2.INTER_AREA``.
    The wrapper also writes ``info["is_success"]`` on every step and reset: ``True`` only on the step
    where the episode terminates with a positive reward (the agent reached the goal), and
    ``info["task_phase"]``: the furthest stage reached in the episode so far (index into
    :data:`TASK_PHASES`: 0 start, 1 the key was picked up, 2 the door was opened, 3 the goal was reached).
    Stages are counted in that order (the door cannot open before the key is held).

    :param env: A MiniGrid environment (``env.unwrapped`` must be a ``MiniGridEnv``).
    :param image_size: Side length in pixels of the square observation.
    :param tile_size: Pixels per grid cell used to render the agent's view before resizing.
    """

    def __init__(self, env: gym.Env, image_size: int = 32, tile_size: int = 8) -> None:
        super().__init__(env)
        self.image_size = int(image_size)
        self.tile_size = int(tile_size)
        self.observation_space = spaces.Box(
            low=0, high=255, shape=(self.image_size, self.image_size, 3), dtype=np.uint8
        )

    def observation(self, observation: Any) -> np.ndarray:
        """
        Render the agent's view (the MiniGrid ``Dict`` observation is discarded).

        The frame is a pure function of the agent's view grid (object, colour and state of each cell,
        which includes the carried object) and of its visibility mask, so resized frames are memoised
        in a bounded cache shared by all instances with this ``(tile_size, image_size)``: a cache hit
        skips the tile rendering and the resize. The result is always identical to
        ``cv2.resize(env.unwrapped.get_frame(tile_size=tile_size, agent_pov=True), (image_size, image_size),
        interpolation=cv2.INTER_AREA)``.

        :param observation: The MiniGrid observation (unused).
        :return: The ``(image_size, image_size, 3)`` uint8 RGB image.
        """
        base = self.env.unwrapped
        # Reuse the view MiniGrid just computed for its own observation (DoorKeyViewEnv), if any.
        view = getattr(base, "last_view", None)
        if view is None:
            view = base.gen_obs_grid()
        else:
            base.last_view = None  # consume: a later call must not see a stale view
        grid, vis_mask = view
        key = (self.tile_size, self.image_size, grid.encode().tobytes(), np.asarray(vis_mask, dtype=bool).tobytes())
        frame = _FRAME_CACHE.get(key)
        if frame is None:
            frame = base.get_frame(tile_size=self.tile_size, agent_pov=True)
            if getattr(base, "last_view", None) is not None:
                base.last_view = None  # get_frame() recomputed the view; drop it as well
            if frame.shape[0] != self.image_size or frame.shape[1] != self.image_size:
                frame = cv2.resize(frame, (self.image_size, self.image_size), interpolation=cv2.INTER_AREA)
            frame = np.ascontiguousarray(frame, dtype=np.uint8)
            frame.flags.writeable = False
            if len(_FRAME_CACHE) >= FRAME_CACHE_SIZE:
                _FRAME_CACHE.clear()
            _FRAME_CACHE[key] = frame
        return frame.copy()

    def reset(
        self, *, seed: Optional[int] = None, options: Optional[dict[str, Any]] = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """
        Reset the environment.

        :param seed: Seed for the MiniGrid generator.
        :param options: Passed to the wrapped env.
        :return: The first observation and an info dict with ``is_success=False``.
        """
        obs, info = super().reset(seed=seed, options=options)
        base = self.env.unwrapped
        self._door = next((o for o in base.grid.grid if isinstance(o, Door)), None)
        self._phase = 0
        info = dict(info)
        info["is_success"] = False
        info["task_phase"] = 0
        return obs, info

    def step(self, action: Any) -> tuple[np.ndarray, SupportsFloat, bool, bool, dict[str, Any]]:
        """
        Step the environment.

        :param action: One of the 7 MiniGrid actions.
        :return: observation, reward, terminated, truncated, info (with ``is_success``).
        """
        obs, reward, terminated, truncated, info = super().step(action)
        info = dict(info)
        info["is_success"] = bool(terminated and float(reward) > 0.0)
        phase = getattr(self, "_phase", 0)
        if phase == 0 and isinstance(self.env.unwrapped.carrying, Key):
            phase = 1
        if phase == 1 and self._door is not None and self._door.is_open:
            phase = 2
        if info["is_success"]:
            phase = 3
        self._phase = phase
        info["task_phase"] = phase
        return obs, reward, terminated, truncated, info


def make_doorkey(
    size: int = 8,
    image_size: int = 32,
    tile_size: int = 8,
    render_mode: Optional[str] = None,
    **kwargs: Any,
) -> DoorKeyRGB32:
    """
    Create ``DoorKeyEnv(size=size)`` observed as a ``image_size x image_size`` RGB image.

    This is the entry point of the ``GoCu/DoorKey-NxN-v0`` ids. ``env.render()`` (with
    ``render_mode="rgb_array"``) returns MiniGrid's usual full-grid frame, handy for videos; the
    observation is always the agent-POV image.

    :param size: Grid side length (walls included), e.g. 5, 8, 11 or 16.
    :param image_size: Side length in pixels of the observation.
    :param tile_size: Pixels per cell for the agent-POV render before resizing.
    :param render_mode: MiniGrid render mode (``None``, ``"rgb_array"`` or ``"human"``).
    :param kwargs: Extra keyword arguments for ``minigrid.envs.DoorKeyEnv`` (e.g. ``max_steps``,
        ``agent_view_size``).
    :return: The wrapped environment.
    """
    env = DoorKeyViewEnv(size=size, render_mode=render_mode, **kwargs)
    return DoorKeyRGB32(env, image_size=image_size, tile_size=tile_size)
