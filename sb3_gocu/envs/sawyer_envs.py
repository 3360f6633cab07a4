"""The paper's Sawyer manipulation tasks (Sect. 5.2, Table 2) on Meta-World, seen as 32x32 RGB frames, with a sparse reward.

Import this module only when one of the ``GoCu/VisualSawyer*`` ids is made (they use string entry points): it imports
``metaworld`` (which pins ``mujoco==3.3.0``) and sets ``MUJOCO_GL=egl`` first unless it is already set.

Each task is a Meta-World v3 task (MT1: 50 fixed variations of object and goal positions, drawn with the env's seed;
each reset picks one at random). The agent sees a 32x32 RGB frame from a fixed camera that shows the gripper, the
objects and the goal; its action is Meta-World's (hand displacement x, y, z and gripper effort, each in [-1, 1]).
The reward is 1 at a step where Meta-World's success test holds, else 0; ``info["distance"]`` is the task's distance
(docs/environments.md), ``info["is_success"]`` the success test, ``info["dense_reward"]`` Meta-World's own reward.

Rendering cost. Meta-World's Sawyer scene holds about 46,000 mesh vertices, and with Mesa's software renderer a
32x32 frame of it costs far more than the physics. Frames are therefore drawn from a copy of the model whose meshes
are simplified by vertex clustering (``mesh_cell``, 1 cm: half of what a 32x32 pixel covers here), the parts of the
robot the camera never shows are left out (:attr:`SawyerTask.hidden_bodies`), and the copy is posed from the
simulation's state before each frame; shadows, reflections and multisampling are off. The simulation itself runs on
Meta-World's own model. Frames differ from those of the whole scene by about 1/255 on average at most
(``tests/test_sawyer_envs.py``); docs/environments.md has the speeds.
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")

import pathlib  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from typing import Any, Callable, Optional, SupportsFloat  # noqa: E402

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402
from gymnasium import spaces  # noqa: E402

from sb3_gocu._extras import missing_extra  # noqa: E402

try:
    import cv2
    import metaworld
    import mujoco
except ModuleNotFoundError as e:  # the [robotics] extra brings them
    raise missing_extra(e, "sb3_gocu.envs.sawyer_envs (the GoCu/VisualSawyer* ids)", "robotics") from e

__all__ = ["SAWYER_TASKS", "SawyerTask", "VisualSawyer", "make_visual_sawyer"]


def _target(env: Any) -> np.ndarray:
    return np.asarray(env._target_pos, dtype=np.float64)


def _reach_distance(env: Any) -> float:
    """Gripper centre (between the fingers) to the goal, metres (Meta-World's reach test: <= 0.05)."""
    return float(np.linalg.norm(env.tcp_center - _target(env)))


def _object_distance(env: Any) -> float:
    """Object centre to the goal, metres (push: <= 0.05; pick-and-place: <= 0.07)."""
    return float(np.linalg.norm(env._get_pos_objects()[:3] - _target(env)))


def _door_distance(env: Any) -> float:
    """Door handle to its open position along x, metres (Meta-World's door-open test: <= 0.08)."""
    return float(abs(env._get_pos_objects()[0] - _target(env)[0]))


@dataclass(frozen=True)
class SawyerTask:
    """One task: its Meta-World name, distance and camera (its episode length: ``sb3_gocu.envs.SAWYER_LENGTHS``).

    :param metaworld_name: the Meta-World v3 task (``reach-v3``, ...)
    :param distance: the task's distance from the unwrapped Meta-World env, metres
    :param camera: free camera: ``lookat`` (3 floats), ``distance``, ``azimuth``, ``elevation``
    :param hidden_bodies: bodies left out of the frames: those the camera never shows, wherever the hand goes in its
        workspace (:func:`visible_bodies`; ``tests/test_sawyer_envs.py`` checks it)
    """

    metaworld_name: str
    distance: Callable[[Any], float]
    camera: dict[str, Any]
    hidden_bodies: tuple[str, ...] = ()


#: Looks at the table from the far side, down at 60 degrees: the gripper near the top edge, the objects' and the goals'
#: regions (x in [-0.1, 0.1], y in [0.6, 0.9]) below it; the robot's base is out of view.
TABLE_CAMERA: dict[str, Any] = {"lookat": (0.0, 0.75, 0.05), "distance": 0.65, "azimuth": -90.0, "elevation": -60.0}

#: Looks straight down on the door and the arm: the door swings open toward the bottom left of the frame, where its
#: goal marker is.
DOOR_CAMERA: dict[str, Any] = {"lookat": (-0.1, 0.65, 0.05), "distance": 0.75, "azimuth": -90.0, "elevation": -89.0}

#: the robot's parts that neither camera ever shows (its base, head, shoulder and the floor below the table)
_UNSEEN = ("world", "pedestal", "pedestal_feet", "torso", "controller_box", "head", "screen", "right_arm_base_link",
           "right_l0", "right_l1", "right_l1_2")
#: ... and the upper arm, which TABLE_CAMERA never shows either
_UNSEEN_FROM_THE_TABLE = (*_UNSEEN, "right_l2", "right_l3")

#: the registered tasks, by id
SAWYER_TASKS: dict[str, SawyerTask] = {
    "GoCu/VisualSawyerReacher-v0": SawyerTask("reach-v3", _reach_distance, TABLE_CAMERA, _UNSEEN_FROM_THE_TABLE),
    "GoCu/VisualSawyerDoorHook-v0": SawyerTask("door-open-v3", _door_distance, DOOR_CAMERA, (*_UNSEEN, "RetainingWall")),
    "GoCu/VisualSawyerPusher-v0": SawyerTask("push-v3", _object_distance, TABLE_CAMERA, _UNSEEN_FROM_THE_TABLE),
    "GoCu/VisualSawyerPickAndPlace-v0": SawyerTask("pick-place-v3", _object_distance, TABLE_CAMERA, _UNSEEN_FROM_THE_TABLE),
}


# ---------------------------------------------------------------------------------------------- rendering
def read_stl(path: pathlib.Path) -> np.ndarray:
    """The triangles of a binary STL file as a (3 x triangles, 3) float64 array of corner positions."""
    data = path.read_bytes()
    n = int.from_bytes(data[80:84], "little")
    if len(data) != 84 + 50 * n:
        raise ValueError(f"{path} is not a binary STL file")
    triangles = np.frombuffer(data, np.dtype([("normal", "<f4", 3), ("corners", "<f4", (3, 3)), ("attr", "<u2")]), n, 84)
    return triangles["corners"].reshape(-1, 3).astype(np.float64)


def cluster_mesh(corners: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """Vertex clustering: every corner moves to the mean of the corners in its ``cell``-sized cube; triangles that
    collapse, and repeats, are dropped. :return: (vertices, faces)"""
    keys = np.floor(corners / cell).astype(np.int64)
    _, index, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    index = index.ravel()
    vertices = np.zeros((len(counts), 3))
    np.add.at(vertices, index, corners)
    vertices /= counts[:, None]
    faces = index.reshape(-1, 3)
    faces = faces[(faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])]
    _, first = np.unique(np.sort(faces, axis=1), axis=0, return_index=True)
    faces = faces[np.sort(first)]
    used, faces = np.unique(faces, return_inverse=True)
    return vertices[used], faces.reshape(-1, 3)


def visible_bodies(env: "VisualSawyer", grid: int = 4, scale: int = 4) -> set[str]:
    """The bodies whose geoms show in at least one frame, with the hand held at each point of a ``grid`` x ``grid`` x
    ``grid`` lattice over its whole workspace (Meta-World's mocap bounds), gripper open and closed, seen at ``scale``
    times the frame's resolution. What never shows can be left out of the frames (:attr:`SawyerTask.hidden_bodies`).
    """
    sim = env.sim
    scene = SceneRenderer(sim.model_name, env.image_size * scale, env.task.camera, mesh_cell=0.0)  # nothing hidden
    segmenter = scene.renderer
    segmenter.enable_segmentation_rendering()
    seen: set[int] = set()
    env.reset(seed=0)
    lows, highs = np.asarray(sim.mocap_low, dtype=np.float64), np.asarray(sim.mocap_high, dtype=np.float64)
    try:
        for point in np.stack(np.meshgrid(*[np.linspace(lo, hi, grid) for lo, hi in zip(lows, highs)]), -1).reshape(-1, 3):
            for grip in (-1.0, 1.0):
                for _ in range(30):  # the arm follows the mocap body over a few steps
                    sim.data.mocap_pos[0] = point
                    sim.do_simulation([grip, -grip], sim.frame_skip)
                ids = scene.render(sim.model, sim.data)
                seen |= {int(g) for g in np.unique(ids[..., 0][ids[..., 1] == mujoco.mjtObj.mjOBJ_GEOM])}
    finally:
        scene.close()
    model = scene.model
    return {model.body(int(model.geom_bodyid[g])).name for g in seen}


class SceneRenderer:
    """Small frames of a MuJoCo scene from a simplified copy of its model.

    :param xml_path: the scene's MJCF file (meshes: binary STL files, paths relative to it)
    :param size: frame side, pixels
    :param camera: free camera: ``lookat``, ``distance``, ``azimuth``, ``elevation``
    :param mesh_cell: vertex-clustering cell, metres (0: the meshes as they are)
    :param hidden_bodies: bodies whose geoms are not drawn
    """

    def __init__(
        self, xml_path: str, size: int, camera: dict[str, Any], mesh_cell: float = 0.01, hidden_bodies: tuple[str, ...] = ()
    ) -> None:
        if mesh_cell < 0:
            raise ValueError(f"mesh_cell must be >= 0, got {mesh_cell}")
        spec = mujoco.MjSpec.from_file(xml_path)
        if mesh_cell > 0:
            folder = pathlib.Path(xml_path).parent
            for mesh in spec.meshes:
                vertices, faces = cluster_mesh(read_stl(folder / mesh.file), mesh_cell)
                mesh.file = ""
                mesh.uservert = vertices.astype(np.float32).ravel().tolist()
                mesh.userface = faces.astype(np.int32).ravel().tolist()
        self.model = spec.compile()
        for name in hidden_bodies:
            body = self.model.body(name).id  # a KeyError names a body the scene does not have
            self.model.geom_rgba[self.model.geom_bodyid == body, 3] = 0.0  # MuJoCo skips fully transparent geoms
        self.data = mujoco.MjData(self.model)
        self.model.vis.quality.shadowsize = 0  # set before the renderer's context copies them
        self.model.vis.quality.offsamples = 0
        self.renderer = mujoco.Renderer(self.model, height=size, width=size)
        self.renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = False
        self.renderer.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = False
        self.camera = mujoco.MjvCamera()
        self.camera.type = mujoco.mjtCamera.mjCAMERA_FREE
        self.camera.lookat[:] = np.asarray(camera["lookat"], dtype=np.float64)
        self.camera.distance = float(camera["distance"])
        self.camera.azimuth = float(camera["azimuth"])
        self.camera.elevation = float(camera["elevation"])

    def render(self, model: Any, data: Any) -> np.ndarray:
        """A frame of the simulation's ``(model, data)`` (same MJCF): its state and the model fields Meta-World moves
        at reset (body and site positions) are copied first. :return: (size, size, 3) uint8"""
        m, d = self.model, self.data
        m.body_pos[:] = model.body_pos
        m.body_quat[:] = model.body_quat
        m.site_pos[:] = model.site_pos
        d.qpos[:] = data.qpos
        d.mocap_pos[:] = data.mocap_pos
        d.mocap_quat[:] = data.mocap_quat
        mujoco.mj_kinematics(m, d)
        d.site_xpos[:] = data.site_xpos  # sites Meta-World places in data directly (its goal markers)
        self.renderer.update_scene(d, camera=self.camera)
        return self.renderer.render()

    def close(self) -> None:
        self.renderer.close()


# ---------------------------------------------------------------------------------------------- the env
class VisualSawyer(gym.Env):
    """A Meta-World task seen as small RGB frames, rewarded 1 at the steps where it is solved.

    :param task: the task (:data:`SAWYER_TASKS`)
    :param image_size: frame side, pixels
    :param supersample: draw at ``image_size * supersample`` pixels, then average down (anti-aliasing: the 4 cm
        puck stays visible)
    :param mesh_cell: vertex-clustering cell of the drawn meshes, metres (0: Meta-World's meshes)
    :param render_mode: ``"rgb_array"``: ``render()`` returns the observation frame
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 80}

    def __init__(
        self,
        task: SawyerTask,
        image_size: int = 32,
        supersample: int = 2,
        mesh_cell: float = 0.01,
        render_mode: Optional[str] = None,
    ) -> None:
        if image_size < 8:
            raise ValueError(f"image_size must be >= 8, got {image_size}")
        if supersample < 1:
            raise ValueError(f"supersample must be >= 1, got {supersample}")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.task = task
        self.image_size = int(image_size)
        self.supersample = int(supersample)
        self.render_mode = render_mode
        self.sim = metaworld.env_dict.ALL_V3_ENVIRONMENTS[task.metaworld_name]()
        self._tasks: list[Any] = []
        self._task_seed: Optional[int] = None
        self.scene = SceneRenderer(
            self.sim.model_name, self.image_size * self.supersample, task.camera, mesh_cell, task.hidden_bodies
        )
        self.observation_space = spaces.Box(0, 255, (self.image_size, self.image_size, 3), np.uint8)
        self.action_space = spaces.Box(-1.0, 1.0, self.sim.action_space.shape, np.float32)
        self._frame: Optional[np.ndarray] = None

    def _observe(self) -> np.ndarray:
        frame = self.scene.render(self.sim.model, self.sim.data)
        if self.supersample > 1:
            frame = cv2.resize(frame, (self.image_size, self.image_size), interpolation=cv2.INTER_AREA)
        self._frame = np.ascontiguousarray(frame, dtype=np.uint8)
        return self._frame

    def reset(self, *, seed: Optional[int] = None, options: Optional[dict[str, Any]] = None) -> tuple[np.ndarray, dict[str, Any]]:
        """Pick one of the task's 50 variations at random and start an episode in it.

        :param seed: seeds the variations (the first reset draws them) and the choice among them
        :param options: unused
        :return: the first frame, and ``info`` with ``distance``, ``is_success`` and ``variation``
        """
        super().reset(seed=seed)
        if not self._tasks or seed is not None:
            task_seed = int(self.np_random.integers(2**31 - 1))
            self._tasks = list(metaworld.MT1(self.task.metaworld_name, seed=task_seed).train_tasks)
        variation = int(self.np_random.integers(len(self._tasks)))
        self.sim.set_task(self._tasks[variation])
        self.sim.reset()
        distance = self.task.distance(self.sim)
        return self._observe(), {"distance": distance, "is_success": False, "variation": variation}

    def step(self, action: Any) -> tuple[np.ndarray, SupportsFloat, bool, bool, dict[str, Any]]:
        """Move the hand and gripper. :return: frame, reward (1 if solved now), terminated (never), truncated (never:
        the registration's time limit ends episodes), info"""
        _, dense, _, _, sim_info = self.sim.step(np.asarray(action, dtype=np.float32))
        success = bool(sim_info["success"])
        info = {"distance": self.task.distance(self.sim), "is_success": success, "dense_reward": float(dense)}
        return self._observe(), 1.0 if success else 0.0, False, False, info

    def render(self) -> Optional[np.ndarray]:
        """The last observation frame (``render_mode="rgb_array"``)."""
        return None if self.render_mode is None else self._frame

    def close(self) -> None:
        self.scene.close()
        self.sim.close()


def make_visual_sawyer(env_id: str, **kwargs: Any) -> VisualSawyer:
    """Entry point of the ``GoCu/VisualSawyer*`` ids. :param env_id: the id (:data:`SAWYER_TASKS`) :param kwargs: of
    :class:`VisualSawyer`"""
    return VisualSawyer(SAWYER_TASKS[env_id], **kwargs)
