"""Small MuJoCo frames cheaply: a renderer without shadows, reflections or multisampling, and a free camera.

Imported by :mod:`sb3_gocu.envs.mujoco_envs` and :mod:`sb3_gocu.envs.sawyer_envs` after their own (guarded) import of
``mujoco``. At 32x32 these settings do not change what a frame shows, and make it about 20x cheaper with Mesa's
software renderer (docs/environments.md).
"""

from __future__ import annotations

from typing import Any

import mujoco
import numpy as np

__all__ = ["free_camera", "small_frame_renderer"]


def small_frame_renderer(model: Any, size: int) -> mujoco.Renderer:
    """An off-screen renderer of ``size`` x ``size`` frames with shadows, reflections and multisampling off.

    :param model: the ``mujoco.MjModel`` (its ``vis`` settings are changed: the renderer's context copies them)
    :param size: frame side, pixels
    """
    model.vis.quality.shadowsize = 0
    model.vis.quality.offsamples = 0
    model.vis.global_.offwidth = max(int(model.vis.global_.offwidth), size)
    model.vis.global_.offheight = max(int(model.vis.global_.offheight), size)
    renderer = mujoco.Renderer(model, height=size, width=size)
    renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = False
    renderer.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = False
    return renderer


def free_camera(camera: dict[str, Any]) -> mujoco.MjvCamera:
    """A free camera. :param camera: ``lookat`` (3 floats), ``distance``, ``azimuth``, ``elevation``"""
    cam = mujoco.MjvCamera()
    cam.type = mujoco.mjtCamera.mjCAMERA_FREE
    cam.lookat[:] = np.asarray(camera["lookat"], dtype=np.float64)
    cam.distance = float(camera["distance"])
    cam.azimuth = float(camera["azimuth"])
    cam.elevation = float(camera["elevation"])
    return cam
