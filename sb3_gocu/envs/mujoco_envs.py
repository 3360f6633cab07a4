"""Gymnasium MuJoCo ``Reacher-v5`` / ``Pusher-v5`` observed as 32x32 RGB renders with a sparse reward.

Import this module only when one of these environments is made (the ``GoCu/VisualReacher-v0`` and
``GoCu/VisualPusher-v0`` ids use string entry points): it imports ``mujoco``, and sets
``MUJOCO_GL=egl`` (headless OpenGL) first unless ``MUJOCO_GL`` is already set. ``MUJOCO_GL`` is
read by ``mujoco`` when it is imported, so to use another backend (``osmesa``, ``glfw``) set the
variable before anything imports ``mujoco``.
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")

from typing import Any, Callable, Optional, SupportsFloat  # noqa: E402

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402
from gymnasium import spaces  # noqa: E402

from sb3_gocu._extras import missing_extra  # noqa: E402

try:
    import cv2
    import mujoco
    from gymnasium.envs.mujoco.pusher_v5 import PusherEnv
    from gymnasium.envs.mujoco.reacher_v5 import ReacherEnv
except ModuleNotFoundError as e:  # the [mujoco] extra brings them (gymnasium[mujoco]: mujoco, imageio, ...)
    raise missing_extra(e, "sb3_gocu.envs.mujoco_envs (GoCu/VisualReacher-v0, GoCu/VisualPusher-v0)", "mujoco") from e

from sb3_gocu.envs.small_frames import free_camera, small_frame_renderer  # noqa: E402

__all__ = [
    "PUSHER_CAMERA",
    "REACHER_CAMERA",
    "SparseVisualMujoco",
    "make_visual_pusher",
    "make_visual_reacher",
    "pusher_distance",
    "reacher_distance",
]

#: Top-down camera over the Reacher arena: the square shown is about 0.51 m wide, centred on the
#: arm's base; the arm reaches 0.21 m (+ 0.01 m fingertip) and targets are sampled within 0.2 m.
REACHER_CAMERA: dict[str, Any] = {"lookat": (0.0, 0.0, 0.0), "distance": 0.62, "azimuth": 90.0, "elevation": -90.0}
#: Oblique camera behind the Pusher arm, looking down at the table: shows the arm (shoulder at the
#: left), the whole initial object region and the goal. Image right is +x, image up is +y.
PUSHER_CAMERA: dict[str, Any] = {"lookat": (0.35, -0.25, -0.325), "distance": 1.4, "azimuth": 90.0, "elevation": -65.0}


def reacher_distance(env: gym.Env) -> float:
    """
    Planar (x, y) distance between Reacher's fingertip and target, in metres.

    (Both are at z = 0.01 m, so this equals the 3-D distance used by Reacher-v5's dense reward.)

    :param env: The unwrapped ``ReacherEnv``.
    :return: The distance.
    """
    vec = env.get_body_com("fingertip") - env.get_body_com("target")
    return float(np.linalg.norm(vec[:2]))


def pusher_distance(env: gym.Env) -> float:
    """
    Planar (x, y) distance between the centres of Pusher's object and goal, in metres.

    The 3-D distance used by Pusher-v5's dense reward never goes below 0.048 m (the object's centre
    is 0.048 m above the goal disc), hence the planar distance.

    :param env: The unwrapped ``PusherEnv``.
    :return: The distance.
    """
    vec = env.get_body_com("object") - env.get_body_com("goal")
    return float(np.linalg.norm(vec[:2]))


class SparseVisualMujoco(gym.Wrapper):
    """
    Replace a MuJoCo env's state observation by a small RGB render and its reward by a sparse one.

    Reward: ``1.0`` when ``distance_fn(env.unwrapped) < distance_threshold`` after the step, else ``0.0``.
    ``info`` gets ``distance`` (the current distance), ``is_success`` (``distance < distance_threshold``)
    and ``dense_reward`` (the wrapped env's original reward). Termination, truncation and the action
    space are the wrapped env's.

    Observations are rendered off-screen with a dedicated ``mujoco.Renderer`` at
    ``image_size * supersample`` pixels and, if ``supersample > 1``, downsampled with ``cv2.INTER_AREA``
    (cheap anti-aliasing: thin arm links and the 1.8 cm Reacher target stay visible). Shadows and
    multisampling are disabled (``model.vis.quality.shadowsize = 0``, ``offsamples = 0``) because
    they dominate the rendering cost on a CPU. ``env.render()`` still uses the wrapped env's own
    renderer (e.g. 480x480 frames for videos).

    :param env: A Gymnasium ``MujocoEnv`` (or a wrapper of one).
    :param distance_fn: Computes the task distance from the unwrapped env.
    :param distance_threshold: Success radius, in the units of ``distance_fn`` (metres).
    :param camera: Free-camera parameters: ``lookat`` (3 floats), ``distance``, ``azimuth``, ``elevation``.
    :param image_size: Side length in pixels of the square observation.
    :param supersample: Render at ``image_size * supersample`` pixels, then downsample.
    """

    def __init__(
        self,
        env: gym.Env,
        distance_fn: Callable[[gym.Env], float],
        distance_threshold: float,
        camera: dict[str, Any],
        image_size: int = 32,
        supersample: int = 2,
    ) -> None:
        super().__init__(env)
        if distance_threshold <= 0:
            raise ValueError(f"distance_threshold must be > 0, got {distance_threshold}")
        if supersample < 1:
            raise ValueError(f"supersample must be >= 1, got {supersample}")
        self.distance_fn = distance_fn
        self.distance_threshold = float(distance_threshold)
        self.image_size = int(image_size)
        self.supersample = int(supersample)
        self.observation_space = spaces.Box(
            low=0, high=255, shape=(self.image_size, self.image_size, 3), dtype=np.uint8
        )

        render_px = self.image_size * self.supersample
        self._renderer: Optional[mujoco.Renderer] = small_frame_renderer(env.unwrapped.model, render_px)
        self._camera = free_camera(camera)

    def _render_obs(self) -> np.ndarray:
        assert self._renderer is not None, "The environment was closed"
        self._renderer.update_scene(self.env.unwrapped.data, camera=self._camera)
        frame = self._renderer.render()
        if self.supersample > 1:
            frame = cv2.resize(frame, (self.image_size, self.image_size), interpolation=cv2.INTER_AREA)
        return np.ascontiguousarray(frame, dtype=np.uint8)

    def _distance_info(self) -> tuple[float, bool]:
        distance = float(self.distance_fn(self.env.unwrapped))
        return distance, distance < self.distance_threshold

    def reset(
        self, *, seed: Optional[int] = None, options: Optional[dict[str, Any]] = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """
        Reset the environment.

        :param seed: Seed for the wrapped env.
        :param options: Passed to the wrapped env.
        :return: The first image observation and an info dict with ``distance`` and ``is_success``.
        """
        _, info = self.env.reset(seed=seed, options=options)
        distance, success = self._distance_info()
        info = dict(info)
        info["distance"] = distance
        info["is_success"] = success
        return self._render_obs(), info

    def step(self, action: Any) -> tuple[np.ndarray, SupportsFloat, bool, bool, dict[str, Any]]:
        """
        Step the environment.

        :param action: A continuous action for the wrapped env.
        :return: image observation, sparse reward, terminated, truncated, info.
        """
        _, dense_reward, terminated, truncated, info = self.env.step(action)
        distance, success = self._distance_info()
        info = dict(info)
        info["distance"] = distance
        info["is_success"] = success
        info["dense_reward"] = float(dense_reward)
        reward = 1.0 if success else 0.0
        return self._render_obs(), reward, terminated, truncated, info

    def close(self) -> None:
        """Free the observation renderer, then close the wrapped env."""
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
        super().close()


def make_visual_reacher(
    distance_threshold: float = 0.02,
    image_size: int = 32,
    supersample: int = 2,
    camera: Optional[dict[str, Any]] = None,
    render_mode: Optional[str] = None,
    **kwargs: Any,
) -> SparseVisualMujoco:
    """
    Create Reacher-v5 observed as an RGB image, with reward 1 when the fingertip is near the target.

    Entry point of ``GoCu/VisualReacher-v0`` (registered with ``max_episode_steps=50``, as Reacher-v5).

    :param distance_threshold: Success radius in metres between fingertip and target centres.
        The default 0.02 m is about contact: fingertip radius 0.01 m + target radius 0.009 m.
    :param image_size: Side length in pixels of the observation.
    :param supersample: Render at ``image_size * supersample`` pixels, then downsample.
    :param camera: Free-camera parameters; defaults to :data:`REACHER_CAMERA`.
    :param render_mode: Render mode of the underlying ``ReacherEnv`` (for ``env.render()``).
    :param kwargs: Extra keyword arguments for ``gymnasium.envs.mujoco.reacher_v5.ReacherEnv``.
    :return: The wrapped environment.
    """
    env = ReacherEnv(render_mode=render_mode, **kwargs)
    return SparseVisualMujoco(
        env,
        distance_fn=reacher_distance,
        distance_threshold=distance_threshold,
        camera=REACHER_CAMERA if camera is None else camera,
        image_size=image_size,
        supersample=supersample,
    )


def make_visual_pusher(
    distance_threshold: float = 0.05,
    image_size: int = 32,
    supersample: int = 2,
    camera: Optional[dict[str, Any]] = None,
    render_mode: Optional[str] = None,
    **kwargs: Any,
) -> SparseVisualMujoco:
    """
    Create Pusher-v5 observed as an RGB image, with reward 1 when the object is on the goal.

    Entry point of ``GoCu/VisualPusher-v0`` (registered with ``max_episode_steps=100``, as Pusher-v5).

    :param distance_threshold: Success radius in metres between the object's and the goal's centres
        in the table plane. The default 0.05 m (the object's radius; the goal disc's radius is
        0.08 m) means the object mostly covers the goal; the object starts more than 0.17 m away.
    :param image_size: Side length in pixels of the observation.
    :param supersample: Render at ``image_size * supersample`` pixels, then downsample.
    :param camera: Free-camera parameters; defaults to :data:`PUSHER_CAMERA`.
    :param render_mode: Render mode of the underlying ``PusherEnv`` (for ``env.render()``).
    :param kwargs: Extra keyword arguments for ``gymnasium.envs.mujoco.pusher_v5.PusherEnv``.
    :return: The wrapped environment.
    """
    env = PusherEnv(render_mode=render_mode, **kwargs)
    return SparseVisualMujoco(
        env,
        distance_fn=pusher_distance,
        distance_threshold=distance_threshold,
        camera=PUSHER_CAMERA if camera is None else camera,
        image_size=image_size,
        supersample=supersample,
    )
