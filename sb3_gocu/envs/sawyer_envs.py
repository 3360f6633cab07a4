"""The paper's Sawyer manipulation tasks (Sect. 5.2, Table 2) on Meta-World, seen as 32x32 RGB frames, with a sparse reward.

Import this module only when one of the ``GoCu/VisualSawyer*`` ids is made (they use string entry points): it imports
``metaworld`` (which pins ``mujoco==3.3.0``) and sets ``MUJOCO_GL=egl`` first unless it is already set.

Each task is a Meta-World v3 task (MT1: 50 fixed variations of object and goal positions, drawn with the env's seed;
each reset picks one at random). The agent sees a 32x32 RGB frame from a fixed camera that shows the gripper, the
objects and the goal; its action is Meta-World's (hand displacement x, y, z and gripper effort, each in [-1, 1]).
The reward is 1 at a step where Meta-World's success test holds, else 0; ``info["distance"]`` is the task's distance
(docs/environments.md), ``info["is_success"]`` the success test, ``info["dense_reward"]`` Meta-World's own shaped
reward (with two pucks: minus the sum of their distances to their goals), for reference only.

Rendering cost. Meta-World's Sawyer scene holds about 46,000 mesh vertices, and with Mesa's software renderer a
32x32 frame of it costs far more than the physics. Frames are therefore drawn from a copy of the model whose meshes
are simplified by vertex clustering (:attr:`SawyerTask.mesh_cell`, 1-2 cm: what a 32x32 pixel covers here), the parts of the
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
    from scipy.spatial.transform import Rotation
except ModuleNotFoundError as e:  # the [robotics] extra brings them
    raise missing_extra(e, "sb3_gocu.envs.sawyer_envs (the GoCu/VisualSawyer* ids)", "robotics") from e

from sb3_gocu.envs.small_frames import free_camera, small_frame_renderer  # noqa: E402

__all__ = ["N_VARIATIONS", "SAWYER_TASKS", "SawyerTask", "TwoPuckPushEnv", "VisualSawyer", "make_visual_sawyer"]

#: object and goal layouts of a task (Meta-World's MT1 count), drawn from the env's seed
N_VARIATIONS = 50


def _target(env: Any) -> np.ndarray:
    return np.asarray(env._target_pos, dtype=np.float64)


def _reach_distance(env: Any) -> float:
    """Gripper centre (between the fingers) to the goal, metres (Meta-World's reach test: <= 0.05)."""
    return float(np.linalg.norm(env.tcp_center - _target(env)))


def _object_distance(env: Any) -> float:
    """Object centre to the goal, metres (push: <= 0.05; pick-and-place: <= 0.07)."""
    return float(np.linalg.norm(env._get_pos_objects()[:3] - _target(env)))


def _two_puck_distance(env: Any) -> float:
    """Mean over the two pucks of puck centre to its own goal, metres (success: each <= 0.05)."""
    return float(np.mean(env.puck_distances()))


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
    :param mesh_cell: vertex-clustering cell of the drawn meshes, metres: 2 cm from the table's far side, where the
        arm is small in the frame; 1 cm from above the door, where it is large
    """

    metaworld_name: str
    distance: Callable[[Any], float]
    camera: dict[str, Any]
    hidden_bodies: tuple[str, ...] = ()
    mesh_cell: float = 0.02


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
    "GoCu/VisualSawyerDoorHook-v0": SawyerTask("door-open-v3", _door_distance, DOOR_CAMERA, (*_UNSEEN, "RetainingWall"), 0.01),
    "GoCu/VisualSawyerPusher-v0": SawyerTask("push-v3", _object_distance, TABLE_CAMERA, _UNSEEN_FROM_THE_TABLE),
    "GoCu/VisualSawyerPickAndPlace-v0": SawyerTask("pick-place-v3", _object_distance, TABLE_CAMERA, _UNSEEN_FROM_THE_TABLE),
    # not a Meta-World task: built here on push-v3's scene (TwoPuckPushEnv)
    "GoCu/VisualSawyerMultiObjectPusher-v0": SawyerTask("two-puck-push", _two_puck_distance, TABLE_CAMERA, _UNSEEN_FROM_THE_TABLE),
}


# ---------------------------------------------------------------------------------------------- two pucks
def add_second_puck(spec: Any) -> None:
    """Adds to push-v3's scene a second puck (``obj2``: blue, the first one's size and mass) and its goal (``goal2``:
    yellow; the first puck is red, its goal green). :param spec: the ``mujoco.MjSpec`` of push-v3's scene"""
    body = spec.worldbody.add_body(name="obj2", pos=[0.1, 0.6, 0.02])
    body.add_freejoint(name="obj2joint")
    body.explicitinertial = True
    body.mass = 0.75
    body.ipos = [0.0, 0.0, 0.0]  # the centre of mass at the puck's centre (unset, it is not)
    body.iquat = [1.0, 0.0, 0.0, 0.0]
    body.inertia = [8.80012e-04] * 3
    body.add_geom(
        name="obj2Geom", type=mujoco.mjtGeom.mjGEOM_CYLINDER, size=[0.02, 0.02, 0], rgba=[0.1, 0.2, 1, 1],
        friction=[1, 0.1, 0.002], condim=4, solimp=[0.99, 0.99, 0.01, 0.5, 2], solref=[0.01, 1],
    )
    spec.worldbody.add_site(name="goal2", pos=[-0.1, 0.8, 0.02], size=[0.02, 0, 0], rgba=[1, 0.85, 0, 1])


class TwoPuckPushEnv(metaworld.envs.SawyerPushEnvV3):
    """push-v3 with two pucks, each to its own goal: solved when both are within 0.05 m of theirs.

    Meta-World's task sets do not know this task: each reset lays out the pucks and goals from :attr:`layout`
    (x, y of puck 1, puck 2, goal 1, goal 2), which :class:`VisualSawyer` draws (:meth:`draw_layout`).
    """

    #: where pucks and goals are drawn: x in [-0.15, 0.15]; pucks at y in [0.6, 0.7], goals at y in [0.8, 0.9]
    PUCK_LOW, PUCK_HIGH = (-0.15, 0.6), (0.15, 0.7)
    GOAL_LOW, GOAL_HIGH = (-0.15, 0.8), (0.15, 0.9)
    #: the least distance between the two pucks, and between the two goals
    SEPARATION = 0.08

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.layout = np.array([-0.08, 0.65, 0.08, 0.65, -0.08, 0.85, 0.08, 0.85])
        self._set_task_called = True  # no Meta-World task: reset_model reads the layout

    def _initialize_simulation(self) -> tuple[Any, Any]:
        spec = mujoco.MjSpec.from_file(self.fullpath)
        add_second_puck(spec)
        model = spec.compile()
        model.vis.global_.offwidth = max(model.vis.global_.offwidth, self.width)
        model.vis.global_.offheight = max(model.vis.global_.offheight, self.height)
        return model, mujoco.MjData(model)

    @classmethod
    def draw_layout(cls, rng: np.random.Generator) -> np.ndarray:
        """A layout: pucks and goals uniform in their regions, each pair at least :attr:`SEPARATION` apart."""
        while True:
            pucks = rng.uniform(cls.PUCK_LOW, cls.PUCK_HIGH, (2, 2))
            goals = rng.uniform(cls.GOAL_LOW, cls.GOAL_HIGH, (2, 2))
            if min(np.linalg.norm(pucks[0] - pucks[1]), np.linalg.norm(goals[0] - goals[1])) >= cls.SEPARATION:
                return np.concatenate([pucks.ravel(), goals.ravel()])

    def _get_pos_objects(self) -> np.ndarray:
        return np.hstack([self.get_body_com("obj"), self.get_body_com("obj2")])

    def _get_quat_objects(self) -> np.ndarray:
        second = Rotation.from_matrix(self.data.geom("obj2Geom").xmat.reshape(3, 3)).as_quat()
        return np.hstack([super()._get_quat_objects(), second])

    @property
    def _target_site_config(self) -> list[tuple[str, np.ndarray]]:
        return [("goal", self._target_pos), ("goal2", self.target2)]

    def puck_distances(self) -> np.ndarray:
        """Each puck's centre to its own goal, metres."""
        pucks = self._get_pos_objects().reshape(2, 3)
        return np.linalg.norm(pucks - np.stack([self._target_pos, self.target2]), axis=1)

    def reset_model(self) -> np.ndarray:
        self._reset_hand()
        z = self.init_config["obj_init_pos"][2]
        p1, p2, g1, g2 = self.layout.reshape(4, 2)
        self._target_pos = np.array([*g1, z])
        self.target2 = np.array([*g2, z])
        self.obj_init_pos = np.array([*p1, z])
        self._set_obj_xyz(self.obj_init_pos)
        qpos, qvel = self.data.qpos.copy(), self.data.qvel.copy()
        adr = self.model.jnt_qposadr[self.model.joint("obj2joint").id]
        qpos[adr:adr + 7] = [*p2, z, 1, 0, 0, 0]
        qvel[self.model.jnt_dofadr[self.model.joint("obj2joint").id]:][:6] = 0
        self.set_state(qpos, qvel)
        self.model.site("goal").pos = self._target_pos
        self.model.site("goal2").pos = self.target2
        return self._get_obs()

    def evaluate_state(self, obs: np.ndarray, action: np.ndarray) -> tuple[float, dict[str, Any]]:
        distances = self.puck_distances()
        return -float(distances.sum()), {"success": float((distances <= 0.05).all()), "obj_to_target": float(distances.mean())}


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
    edit = add_second_puck if isinstance(sim, TwoPuckPushEnv) else None
    scene = SceneRenderer(sim.model_name, env.image_size * scale, env.task.camera, mesh_cell=0.0, edit_spec=edit)  # nothing hidden
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
    :param edit_spec: changes the scene before it is compiled (as the simulation's was: :func:`add_second_puck`)
    """

    def __init__(
        self,
        xml_path: str,
        size: int,
        camera: dict[str, Any],
        mesh_cell: float = 0.01,
        hidden_bodies: tuple[str, ...] = (),
        edit_spec: Optional[Callable[[Any], None]] = None,
    ) -> None:
        if mesh_cell < 0:
            raise ValueError(f"mesh_cell must be >= 0, got {mesh_cell}")
        spec = mujoco.MjSpec.from_file(xml_path)
        if edit_spec is not None:
            edit_spec(spec)
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
        self.renderer = small_frame_renderer(self.model, size)
        self.camera = free_camera(camera)

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
        mujoco.mj_camlight(m, d)  # the scene's lights follow their bodies (mj_kinematics leaves them unplaced)
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
    :param mesh_cell: vertex-clustering cell of the drawn meshes, metres (0: Meta-World's meshes; default: the task's)
    :param render_mode: ``"rgb_array"``: ``render()`` returns the observation frame
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 80}

    def __init__(
        self,
        task: SawyerTask,
        image_size: int = 32,
        supersample: int = 2,
        mesh_cell: Optional[float] = None,
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
        two_pucks = task.metaworld_name == "two-puck-push"
        self.sim = TwoPuckPushEnv() if two_pucks else metaworld.env_dict.ALL_V3_ENVIRONMENTS[task.metaworld_name]()
        self._variations: list[Any] = []  # Meta-World tasks, or two-puck layouts
        self.scene = SceneRenderer(
            self.sim.model_name, self.image_size * self.supersample, task.camera,
            task.mesh_cell if mesh_cell is None else mesh_cell, task.hidden_bodies,
            add_second_puck if two_pucks else None,
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
        """Pick one of the task's :data:`N_VARIATIONS` variations at random and start an episode in it.

        :param seed: seeds the variations (the first reset draws them) and the choice among them
        :param options: unused
        :return: the first frame, and ``info`` with ``distance``, ``is_success`` and ``variation``
        """
        super().reset(seed=seed)
        two_pucks = isinstance(self.sim, TwoPuckPushEnv)
        if not self._variations or seed is not None:
            if two_pucks:
                self._variations = [TwoPuckPushEnv.draw_layout(self.np_random) for _ in range(N_VARIATIONS)]
            else:
                task_seed = int(self.np_random.integers(2**31 - 1))
                self._variations = list(metaworld.MT1(self.task.metaworld_name, seed=task_seed).train_tasks)
        variation = int(self.np_random.integers(len(self._variations)))
        if two_pucks:
            self.sim.layout = self._variations[variation]
        else:
            self.sim.set_task(self._variations[variation])
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
