"""The paper's five Sawyer tasks (Sect. 5.2, Table 2) as the paper defines them, seen as 32x32 RGB frames.

Import this module only when one of the ``GoCu/VisualSawyer*-v1`` ids is made (they use string entry points): it
imports ``mujoco`` and sets ``MUJOCO_GL=egl`` first unless it is already set.

The paper's tasks are those of the RIG / Skew-Fit line of work (multiworld's ``sawyer_xyz`` envs): a Sawyer hand moved
by mocap 2 cm a step at most along each axis it may use, held to a plane or a small box, in a small workspace, for
short episodes. The scene here is our own, built from MuJoCo primitives: a table, the hand (a wrist and what the task
puts on it: a pusher tip, a hook, or two fingers), the objects and a goal marker; the arm above the wrist is not drawn.
The hand is a mocap body moved in equal parts over the physics substeps of a step, so what it pushes moves smoothly.

Each task's facts (workspace, object and goal ranges, episode length, success radius, and where we chose a figure
multiworld does not give) are in docs/environments.md; :data:`SAWYER_TASKS` holds them. The reward is 1 at a step
where the success test holds, else 0; ``info["distance"]`` is the paper's final distance of the task (metres, or
radians for the door) and ``info["is_success"]`` the test. :meth:`SawyerTask.expert_action` is a scripted policy that
reads the simulator's state (tests and ``examples/sawyer_curiosity.py``).
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")

from typing import Any, Optional, SupportsFloat  # noqa: E402

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402
from gymnasium import spaces  # noqa: E402

from sb3_gocu._extras import missing_extra  # noqa: E402

try:
    import cv2
    import mujoco
except ModuleNotFoundError as e:  # the [mujoco] extra brings them
    raise missing_extra(e, "sb3_gocu.envs.sawyer_envs (the GoCu/VisualSawyer* ids)", "mujoco") from e

from sb3_gocu.envs.small_frames import free_camera, small_frame_renderer  # noqa: E402

__all__ = ["SAWYER_TASKS", "SawyerTask", "VisualSawyer", "make_visual_sawyer"]

#: largest hand move along one axis in one step, metres (multiworld's action scale)
STEP = 0.02
#: physics substeps of one env step, and their length (seconds)
SUBSTEPS, TIMESTEP = 10, 0.005

# Collision groups: the table collides with the objects only; the hand's parts with the objects only.
_TABLE = 'contype="1" conaffinity="1"'
_OBJECT = 'contype="1" conaffinity="3"'
_HAND = 'contype="2" conaffinity="2"'
_VISUAL = 'contype="0" conaffinity="0"'


def _puck(name: str, xy: tuple[float, float], radius: float, rgba: str) -> str:
    return (
        f'<body name="{name}" pos="{xy[0]} {xy[1]} 0.02"><joint name="{name}" type="free" damping="0.01"/>'
        f'<geom type="cylinder" size="{radius} 0.02" mass="0.1" rgba="{rgba}" friction="0.5 0.005 0.0001" {_OBJECT}/>'
        "</body>"
    )


def _marker(name: str, size: float, rgba: str) -> str:
    return f'<body name="{name}" mocap="true"><geom type="sphere" size="{size}" rgba="{rgba}" {_VISUAL}/></body>'


def _scene(hand: str, objects: str, extra: str = "") -> str:
    """The MJCF of a task: table, mocap hand (wrist plus ``hand``), ``objects`` (bodies), ``extra`` (actuators)."""
    return f"""
<mujoco model="gocu_sawyer">
  <option timestep="{TIMESTEP}" integrator="implicitfast" cone="elliptic" impratio="10"/>
  <visual><headlight ambient="0.5 0.5 0.5" diffuse="0.5 0.5 0.5"/></visual>
  <worldbody>
    <light pos="0 0.6 1.5" dir="0 0 -1" directional="true" diffuse="0.5 0.5 0.5"/>
    <geom name="table" type="plane" pos="0 0.6 0" size="0.45 0.35 0.02" rgba="0.55 0.45 0.35 1" {_TABLE}/>
    <body name="mocap" mocap="true" pos="0 0.6 0.1"/>
    <body name="hand" pos="0 0.6 0.1" gravcomp="1"><freejoint name="hand"/>
      <geom type="box" pos="0 0 0.05" size="0.02 0.015 0.015" mass="0.5" rgba="0.15 0.15 0.15 1" {_VISUAL}/>
      {hand}
    </body>
    {objects}
  </worldbody>
  <equality><weld body1="mocap" body2="hand" solref="0.005 1"/></equality>
  {extra}
</mujoco>"""


# ---------------------------------------------------------------------------------------------- the tasks
class SawyerTask:
    """One task: its scene, workspace, layout, distance, success test and scripted policy.

    A subclass sets the class attributes and :meth:`layout`, :meth:`distance`; the env calls them with itself.

    :cvar axes: the hand's axes the action moves (0: x, 1: y, 2: z), in action order
    :cvar gripper: whether the action ends with a gripper effort (:meth:`PickAndPlace.set_gripper`)
    :cvar hand_low, hand_high: the hand's workspace (x, y, z), metres: the mocap point is kept in it
    :cvar hand_start: where the hand starts each episode
    :cvar success_radius: the success test: :meth:`distance` below it
    :cvar max_episode_steps: the episode length (the registration's time limit)
    :cvar camera: free camera: ``lookat``, ``distance``, ``azimuth``, ``elevation``
    """

    axes: tuple[int, ...] = (0, 1)
    gripper = False
    hand_low = np.array([-0.1, 0.5, 0.06])
    hand_high = np.array([0.1, 0.7, 0.06])
    hand_start = np.array([0.0, 0.5, 0.06])
    success_radius = 0.06
    max_episode_steps = 100
    camera: dict[str, Any] = {"lookat": (0.0, 0.6, 0.0), "distance": 0.55, "azimuth": 90.0, "elevation": -75.0}
    hand_xml = f'<geom type="cylinder" pos="0 0 -0.03" size="0.015 0.02" rgba="0.7 0.1 0.1 1" {_HAND}/>'

    def xml(self) -> str:
        raise NotImplementedError

    def layout(self, env: "VisualSawyer", rng: np.random.Generator) -> None:
        """Place the objects and the goal for a new episode (the hand is already at :attr:`hand_start`)."""
        raise NotImplementedError

    def distance(self, env: "VisualSawyer") -> float:
        raise NotImplementedError

    def expert_action(self, env: "VisualSawyer") -> np.ndarray:
        """A scripted action from the simulator's state: it solves the task in most episodes (the tests: >= 90%)."""
        raise NotImplementedError


def _goal_away_from(rng: np.random.Generator, low: Any, high: Any, start: Any, min_distance: float) -> np.ndarray:
    """A goal (x, y) uniform in [low, high], drawn again until it lies at least ``min_distance`` from ``start``."""
    while True:
        goal = rng.uniform(low, high)
        if np.linalg.norm(goal - np.asarray(start)) >= min_distance:
            return goal


def _towards(env: "VisualSawyer", target: Any) -> np.ndarray:
    """The action along the task's axes that moves the hand's mocap point to ``target`` (x, y, z), at most one full
    step."""
    delta = (np.asarray(target, dtype=np.float64) - env.mocap)[list(env.task.axes)]
    return np.clip(delta / STEP, -1.0, 1.0)


def _push_action(
    env: "VisualSawyer", puck: np.ndarray, goal: np.ndarray, contact: float, obstacle: Optional[np.ndarray] = None
) -> np.ndarray:
    """Push a puck (x, y) toward ``goal`` (x, y) with the hand's tip: circle round it to its far side from the goal,
    then push along the line to the goal, slowing near it; stop within 1.5 cm. :param contact: puck + tip radius
    :param obstacle: another puck (x, y) to keep clear of while circling"""
    to_goal = goal - puck
    remaining = np.linalg.norm(to_goal)
    if remaining < 0.015:  # there: hold the mocap point where the hand is, so the hand does not catch up with it
        return _towards(env, env.hand)
    u = to_goal / remaining
    rel = env.hand[:2] - puck
    behind = np.arctan2(-u[1], -u[0])
    turn = (behind - np.arctan2(rel[1], rel[0]) + np.pi) % (2 * np.pi) - np.pi  # how far round the puck to go
    radius = contact + 0.015
    behind_point = puck - u * radius
    low, high = env.task.hand_low[:2], env.task.hand_high[:2]
    reachable = bool(((low <= behind_point) & (behind_point <= high)).all())
    if np.linalg.norm(rel) < contact + 0.02:
        if abs(turn) < 0.2:  # behind it: push, onto the line as we go
            across = rel @ np.array([-u[1], u[0]])
            aim = puck - u * (contact - 0.003) + u * min(remaining, 0.02) * 0.5 - np.array([-u[1], u[0]]) * across
            return _towards(env, np.array([*aim, env.hand[2]]))
        if not reachable and abs(turn) < 1.2:  # its far side is beyond the workspace: push it off the edge first
            return _towards(env, np.array([*(puck - rel / np.linalg.norm(rel) * (contact - 0.01)), env.hand[2]]))
    outward = puck + rel / max(np.linalg.norm(rel), 1e-9) * radius
    if np.linalg.norm(rel) < radius - 0.01 and ((low <= outward) & (outward <= high)).all():  # too near: step back
        waypoint = outward
    else:  # round the puck, toward its far side
        angle = np.arctan2(rel[1], rel[0]) + np.clip(turn, -0.7, 0.7)
        waypoint = puck + radius * np.array([np.cos(angle), np.sin(angle)])
    action = _towards(env, np.array([*waypoint, env.hand[2]]))
    if obstacle is not None:  # pushed away from the other puck when near it
        away = env.hand[:2] - obstacle
        if np.linalg.norm(away) < contact + 0.02:
            action = np.clip(action + away / np.linalg.norm(away), -1.0, 1.0)
    return action


class Reacher(SawyerTask):
    """Move the hand to the goal (a green dot) in a 40 x 20 cm rectangle, the hand held at z = 0.055."""

    hand_low = np.array([-0.2, 0.55, 0.055])
    hand_high = np.array([0.2, 0.75, 0.055])
    hand_start = np.array([0.0, 0.65, 0.055])
    max_episode_steps = 50
    camera = {"lookat": (0.0, 0.65, 0.0), "distance": 0.6, "azimuth": 90.0, "elevation": -75.0}
    hand_xml = f'<geom type="sphere" size="0.02" rgba="0.7 0.1 0.1 1" {_VISUAL}/>'

    def xml(self) -> str:
        return _scene(self.hand_xml, _marker("goal", 0.02, "0.1 0.8 0.1 1"))

    #: goals are drawn at least this far from the hand's start (nearer, an episode could start solved)
    min_goal_distance = 0.1

    def layout(self, env: "VisualSawyer", rng: np.random.Generator) -> None:
        goal = _goal_away_from(rng, self.hand_low[:2], self.hand_high[:2], self.hand_start[:2], self.min_goal_distance)
        env.set_marker("goal", [*goal, 0.055])

    def distance(self, env: "VisualSawyer") -> float:
        return float(np.linalg.norm(env.hand - env.marker("goal")))

    def expert_action(self, env: "VisualSawyer") -> np.ndarray:
        return _towards(env, env.marker("goal"))


class Pusher(SawyerTask):
    """Push a puck (red, 4 cm radius, from (0, 0.6)) to the goal (a green dot); the hand held at z = 0.06."""

    puck_radius, tip_radius = 0.04, 0.015
    goal_low, goal_high = np.array([-0.15, 0.5]), np.array([0.15, 0.7])
    puck_start = (0.0, 0.6)
    #: goals are drawn at least this far from the puck's start (nearer, an episode would start solved)
    min_goal_distance = 0.1

    def xml(self) -> str:
        objects = _puck("puck", self.puck_start, self.puck_radius, "0.8 0.1 0.1 1")
        return _scene(self.hand_xml, objects + _marker("goal", 0.02, "0.1 0.8 0.1 1"))

    def layout(self, env: "VisualSawyer", rng: np.random.Generator) -> None:
        goal = _goal_away_from(rng, self.goal_low, self.goal_high, self.puck_start, self.min_goal_distance)
        env.set_marker("goal", [*goal, 0.02])

    def distance(self, env: "VisualSawyer") -> float:
        return float(np.linalg.norm(env.body_pos("puck")[:2] - env.marker("goal")[:2]))

    def expert_action(self, env: "VisualSawyer") -> np.ndarray:
        contact = self.puck_radius + self.tip_radius
        return _push_action(env, env.body_pos("puck")[:2], env.marker("goal")[:2], contact)


class MultiObjectPusher(SawyerTask):
    """Push two pucks (red from (0.06, 0.6), blue from (-0.06, 0.6); 3.5 cm radius) each to its own goal (green to
    the right, yellow to the left); the hand held at z = 0.06. The distance is the sum of the two."""

    puck_radius, tip_radius = 0.035, 0.015
    starts = ((0.06, 0.6), (-0.06, 0.6))
    goal_ranges = ((np.array([0.0, 0.5]), np.array([0.15, 0.7])), (np.array([-0.15, 0.5]), np.array([0.0, 0.7])))
    goal_separation = 0.08
    max_episode_steps = 150

    def xml(self) -> str:
        objects = (
            _puck("puck", self.starts[0], self.puck_radius, "0.8 0.1 0.1 1")
            + _puck("puck2", self.starts[1], self.puck_radius, "0.1 0.2 0.9 1")
            + _marker("goal", 0.018, "0.1 0.8 0.1 1")
            + _marker("goal2", 0.018, "0.95 0.85 0.0 1")
        )
        return _scene(self.hand_xml, objects)

    def layout(self, env: "VisualSawyer", rng: np.random.Generator) -> None:
        while True:
            goals = [rng.uniform(low, high) for low, high in self.goal_ranges]
            if np.linalg.norm(goals[0] - goals[1]) >= self.goal_separation:
                break
        env.set_marker("goal", [*goals[0], 0.02])
        env.set_marker("goal2", [*goals[1], 0.02])

    def puck_distances(self, env: "VisualSawyer") -> np.ndarray:
        """Each puck's centre to its own goal (x, y), metres."""
        return np.array([
            np.linalg.norm(env.body_pos(puck)[:2] - env.marker(goal)[:2]) for puck, goal in (("puck", "goal"), ("puck2", "goal2"))
        ])

    def distance(self, env: "VisualSawyer") -> float:
        return float(self.puck_distances(env).sum())

    def expert_action(self, env: "VisualSawyer") -> np.ndarray:
        (puck, goal), other = (("puck", "goal"), "puck2") if self.puck_distances(env)[0] > 0.025 else (("puck2", "goal2"), "puck")
        contact = self.puck_radius + self.tip_radius
        return _push_action(env, env.body_pos(puck)[:2], env.marker(goal)[:2], contact, env.body_pos(other)[:2])


class DoorHook(SawyerTask):
    """Pull a door open to the goal angle (a green dot where the handle then is) with a hook under the hand.

    The door (hinge at x = 0.1, y = 0.66, vertical axis; 0-60 degrees) swings toward the hand; its handle is an L, a bar
    3 cm in front of the door joined to it at its foot, so the hook goes in from above and pulls.
    """

    axes = (0, 1, 2)
    hand_low = np.array([-0.1, 0.45, 0.1])
    hand_high = np.array([0.05, 0.65, 0.25])
    hand_start = np.array([-0.025, 0.5, 0.22])
    hinge = np.array([0.1, 0.66])
    #: hinge to the middle of the handle's slot, along the door; the slot's distance in front of the door's face
    slot_radius, slot_depth = 0.15, 0.03
    goal_high = 0.83
    success_radius = 0.02
    camera = {"lookat": (0.0, 0.57, 0.05), "distance": 0.55, "azimuth": 90.0, "elevation": -80.0}
    hand_xml = (
        f'<geom type="capsule" fromto="0 0 0.03 0 0 -0.07" size="0.007" rgba="0.2 0.2 0.7 1" {_HAND}/>'
        f'<geom type="box" pos="0 0 0.03" size="0.015 0.015 0.01" rgba="0.2 0.2 0.7 1" {_VISUAL}/>'
    )

    def xml(self) -> str:
        r, d = self.slot_radius, self.slot_depth
        handle = f'{_HAND} solref="0.004 1"'  # stiff, so the hook does not pass through it; the door's parts touch the hand only
        door = f"""
    <body name="door" pos="{self.hinge[0]} {self.hinge[1]} 0">
      <joint name="hinge" type="hinge" axis="0 0 1" range="0 60" damping="1" armature="0.01"/>
      <geom type="box" pos="-0.11 0.01 0.12" size="0.11 0.01 0.12" rgba="0.45 0.6 0.75 1" mass="1" {_HAND}/>
      <geom type="box" pos="{-r} {-d / 2} 0.04" size="0.03 {d / 2 + 0.01} 0.008" rgba="0.3 0.3 0.3 1" {handle}/>
      <geom type="box" pos="{-r} {-d - 0.01} 0.085" size="0.03 0.01 0.05" rgba="0.3 0.3 0.3 1" {handle}/>
    </body>"""
        post = f'pos="{self.hinge[0] + 0.02} {self.hinge[1] + 0.01} 0.12"'
        walls = f'<geom type="box" {post} size="0.015 0.02 0.12" rgba="0.4 0.4 0.4 1" {_TABLE}/>'
        return _scene(self.hand_xml, door + f"<body>{walls}</body>" + _marker("goal", 0.015, "0.1 0.8 0.1 1"))

    def slot(self, angle: float) -> np.ndarray:
        """The middle of the handle's slot (x, y) with the door at ``angle`` radians."""
        c, s = np.cos(angle), np.sin(angle)
        x, y = -self.slot_radius, -self.slot_depth / 2  # in the door's frame, turned by the angle about z
        return self.hinge + np.array([c * x - s * y, s * x + c * y])

    def layout(self, env: "VisualSawyer", rng: np.random.Generator) -> None:
        env.goal_angle = float(rng.uniform(0.0, self.goal_high))
        env.set_marker("goal", [*self.slot(env.goal_angle), 0.2])

    def angle(self, env: "VisualSawyer") -> float:
        return float(env.data.joint("hinge").qpos[0])

    def distance(self, env: "VisualSawyer") -> float:
        return abs(self.angle(env) - env.goal_angle)

    def expert_action(self, env: "VisualSawyer") -> np.ndarray:
        angle = self.angle(env)
        slot = self.slot(angle)
        if np.linalg.norm(env.hand[:2] - slot) > 0.008 and env.hand[2] > 0.14:  # above the slot first
            return _towards(env, [*slot, 0.22])
        if env.hand[2] > 0.135:  # then down into it
            return _towards(env, [*slot, 0.13])
        # then round the door's arc, hooked: the hook leads the slot's middle by its play against the bar
        error = env.goal_angle - angle
        play = (self.slot_depth / 2 - 0.007) / self.slot_radius
        return _towards(env, [*self.slot(angle + np.clip(error, -0.1, 0.1) + np.sign(error) * play), 0.13])


class PickAndPlace(SawyerTask):
    """Pick up a ball (1.75 cm radius, from (0, 0.6) on the table) with two fingers and hold it at the goal (a green
    dot in the air); the hand held to the plane x = 0, the action (dy, dz, gripper: -1 open, 1 closed)."""

    axes = (1, 2)
    gripper = True
    hand_low = np.array([0.0, 0.55, 0.02])
    hand_high = np.array([0.0, 0.65, 0.13])
    hand_start = np.array([0.0, 0.6, 0.1])
    ball_radius = 0.0175
    goal_low, goal_high = np.array([0.55, 0.08]), np.array([0.65, 0.13])
    max_episode_steps = 50
    camera = {"lookat": (0.0, 0.6, 0.06), "distance": 0.35, "azimuth": 0.0, "elevation": -15.0}
    #: each finger's offset from the middle with the gripper open, metres
    open_offset = 0.04

    def xml(self) -> str:
        fingers = "".join(
            f'<body name="finger{i}" pos="{sign * self.open_offset} 0 0">'
            f'<joint name="finger{i}" type="slide" axis="{sign} 0 0" range="-0.04 0.0"/>'
            f'<geom type="box" pos="{-sign * 0.004} 0 0.01" size="0.004 0.012 0.022" mass="0.05" friction="2 0.05 0.001"'
            f' condim="4" solref="0.005 1" rgba="0.2 0.2 0.2 1" {_HAND}/></body>'
            for i, sign in ((0, 1), (1, -1))
        )
        ball = (
            f'<body name="ball" pos="0 0.6 {self.ball_radius}"><joint name="ball" type="free" damping="0.001"/>'
            f'<geom type="sphere" size="{self.ball_radius}" mass="0.05" condim="4" friction="2 0.05 0.001"'
            f' rgba="0.8 0.1 0.1 1" {_OBJECT}/></body>'
        )
        actuators = "<actuator>" + "".join(
            f'<position joint="finger{i}" kp="300" kv="5" ctrlrange="-0.04 0"/>' for i in (0, 1)
        ) + "</actuator>"
        return _scene(fingers, ball + _marker("goal", 0.015, "0.1 0.8 0.1 1"), actuators)

    def set_gripper(self, env: "VisualSawyer", effort: float) -> None:
        """The fingers' targets from the gripper action: open at -1, closing as it rises, shut from 0.6 on (on the
        ball, they squeeze it)."""
        env.data.ctrl[:] = -min(0.025 * (effort + 1.0), self.open_offset)

    def layout(self, env: "VisualSawyer", rng: np.random.Generator) -> None:
        env.set_marker("goal", [0.0, *rng.uniform(self.goal_low, self.goal_high)])

    def distance(self, env: "VisualSawyer") -> float:
        return float(np.linalg.norm(env.body_pos("ball") - env.marker("goal")))

    def expert_action(self, env: "VisualSawyer") -> np.ndarray:
        ball, hand = env.body_pos("ball"), env.hand
        if ball[2] < self.ball_radius + 0.01 and np.linalg.norm(ball[1:] - hand[1:]) > 0.012:  # on the table: go there
            above = [0.0, ball[1], max(hand[2], 0.06)] if abs(hand[1] - ball[1]) > 0.008 else [0.0, ball[1], 0.02]
            return np.array([*_towards(env, above), -1.0])
        if env.grip_steps < 4:  # close on it for 4 steps
            env.grip_steps += 1
            return np.array([0.0, 0.0, 1.0])
        return np.array([*_towards(env, env.marker("goal") + (hand - ball)), 1.0])


#: the registered tasks, by id
SAWYER_TASKS: dict[str, SawyerTask] = {
    "GoCu/VisualSawyerReacher-v1": Reacher(),
    "GoCu/VisualSawyerDoorHook-v1": DoorHook(),
    "GoCu/VisualSawyerPusher-v1": Pusher(),
    "GoCu/VisualSawyerMultiObjectPusher-v1": MultiObjectPusher(),
    "GoCu/VisualSawyerPickAndPlace-v1": PickAndPlace(),
}


# ---------------------------------------------------------------------------------------------- the env
class VisualSawyer(gym.Env):
    """A Sawyer task seen as small RGB frames, rewarded 1 at the steps where it is solved.

    :param task: the task (:data:`SAWYER_TASKS`)
    :param image_size: frame side, pixels
    :param supersample: draw at ``image_size * supersample`` pixels, then average down (anti-aliasing)
    :param render_mode: ``"rgb_array"``: ``render()`` returns the observation frame
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 20}

    def __init__(self, task: SawyerTask, image_size: int = 32, supersample: int = 2, render_mode: Optional[str] = None) -> None:
        if image_size < 8:
            raise ValueError(f"image_size must be >= 8, got {image_size}")
        if supersample < 1:
            raise ValueError(f"supersample must be >= 1, got {supersample}")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.task = task
        self.image_size, self.supersample, self.render_mode = int(image_size), int(supersample), render_mode
        self.model = mujoco.MjModel.from_xml_string(task.xml())
        self.data = mujoco.MjData(self.model)
        self.renderer = small_frame_renderer(self.model, self.image_size * self.supersample)
        self.camera = free_camera(task.camera)
        self.observation_space = spaces.Box(0, 255, (self.image_size, self.image_size, 3), np.uint8)
        n_actions = len(task.axes) + int(task.gripper)
        self.action_space = spaces.Box(-1.0, 1.0, (n_actions,), np.float32)
        self.goal_angle = 0.0  # the door's goal
        self.grip_steps = 0  # the scripted pick-and-place policy's count of closing steps
        self._frame: Optional[np.ndarray] = None

    # -- the simulator's state, for the tasks
    @property
    def hand(self) -> np.ndarray:
        """The hand's position (x, y, z), metres (it follows the mocap point the actions move, a few mm behind)."""
        return self.data.body("hand").xpos.copy()

    @property
    def mocap(self) -> np.ndarray:
        """The point the actions move (x, y, z), metres: the hand is welded to it."""
        return self.data.mocap_pos[0].copy()

    def _mocap(self, name: str) -> int:
        return int(self.model.body_mocapid[self.model.body(name).id])

    def marker(self, name: str) -> np.ndarray:
        return self.data.mocap_pos[self._mocap(name)].copy()

    def set_marker(self, name: str, pos: Any) -> None:
        self.data.mocap_pos[self._mocap(name)] = pos

    def body_pos(self, name: str) -> np.ndarray:
        return self.data.body(name).xpos.copy()

    def _observe(self) -> np.ndarray:
        self.renderer.update_scene(self.data, camera=self.camera)
        frame = self.renderer.render()
        if self.supersample > 1:
            frame = cv2.resize(frame, (self.image_size, self.image_size), interpolation=cv2.INTER_AREA)
        self._frame = np.ascontiguousarray(frame, dtype=np.uint8)
        return self._frame

    def reset(self, *, seed: Optional[int] = None, options: Optional[dict[str, Any]] = None) -> tuple[np.ndarray, dict[str, Any]]:
        """Start an episode: the hand at its start, the objects at theirs, a goal drawn at random.

        :param seed: seeds the goals of this and later episodes
        :param options: unused
        :return: the first frame, and ``info`` with ``distance`` and ``is_success``
        """
        super().reset(seed=seed)
        mujoco.mj_resetData(self.model, self.data)
        self.data.mocap_pos[0] = self.task.hand_start
        self.data.joint("hand").qpos[:3] = self.task.hand_start
        self.grip_steps = 0
        self.task.layout(self, self.np_random)
        if self.task.gripper:
            self.task.set_gripper(self, -1.0)
        mujoco.mj_forward(self.model, self.data)
        return self._observe(), {"distance": self.task.distance(self), "is_success": False}

    def step(self, action: Any) -> tuple[np.ndarray, SupportsFloat, bool, bool, dict[str, Any]]:
        """Move the hand (and close or open the gripper). :return: frame, reward (1 if solved now), terminated (never),
        truncated (never: the registration's time limit ends episodes), info"""
        action = np.asarray(action, dtype=np.float64).reshape(-1)
        if action.shape != self.action_space.shape:
            raise ValueError(f"action must have shape {self.action_space.shape}, got {action.shape}")
        if not np.all(np.abs(action) <= 1.0):
            raise ValueError(f"action must lie in [-1, 1] on every axis, got {action}")
        start = self.mocap
        target = start.copy()
        target[list(self.task.axes)] += STEP * action[: len(self.task.axes)]
        target = np.clip(target, self.task.hand_low, self.task.hand_high)
        if self.task.gripper:
            self.task.set_gripper(self, float(action[-1]))
        for i in range(1, SUBSTEPS + 1):
            self.data.mocap_pos[0] = start + (target - start) * i / SUBSTEPS
            mujoco.mj_step(self.model, self.data)
        distance = self.task.distance(self)
        success = distance < self.task.success_radius
        info = {"distance": distance, "is_success": success}
        return self._observe(), 1.0 if success else 0.0, False, False, info

    def render(self) -> Optional[np.ndarray]:
        """The last observation frame (``render_mode="rgb_array"``)."""
        return None if self.render_mode is None else self._frame

    def close(self) -> None:
        self.renderer.close()


def make_visual_sawyer(env_id: str, **kwargs: Any) -> VisualSawyer:
    """Entry point of the ``GoCu/VisualSawyer*-v1`` ids. :param env_id: the id (:data:`SAWYER_TASKS`) :param kwargs:
    of :class:`VisualSawyer`"""
    return VisualSawyer(SAWYER_TASKS[env_id], **kwargs)
