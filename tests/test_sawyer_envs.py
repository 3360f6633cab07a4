"""The paper's Sawyer tasks (sb3_gocu/envs/sawyer_envs.py): frames, reward, distance, workspace, scripted policies."""

import gymnasium as gym
import numpy as np
import pytest

from sb3_gocu.envs import SAWYER_IDS, SAWYER_LENGTHS
from sb3_gocu.envs.sawyer_envs import SAWYER_TASKS, STEP

IMAGE_SPACE = gym.spaces.Box(0, 255, (32, 32, 3), np.uint8)
#: the action size of each task: the hand's axes, and the gripper on Pick and Place
ACTIONS = {"Reacher": 2, "DoorHook": 3, "Pusher": 2, "MultiObjectPusher": 2, "PickAndPlace": 3}


def task_name(env_id: str) -> str:
    return env_id.split("VisualSawyer")[1].split("-")[0]


def expert_episode(env: gym.Env, seed: int) -> dict:
    base = env.unwrapped
    env.reset(seed=seed)
    truncated = False
    while not truncated:
        _, _, _, truncated, info = env.step(base.task.expert_action(base).astype(np.float32))
    return info


@pytest.mark.parametrize("env_id", SAWYER_IDS)
def test_spaces_length_reward_and_the_hand_in_its_workspace(env_id):
    env = gym.make(env_id)
    task = env.unwrapped.task
    assert env.observation_space == IMAGE_SPACE and env.action_space.shape == (ACTIONS[task_name(env_id)],)
    env.action_space.seed(0)
    obs0, info = env.reset(seed=0)
    assert env.observation_space.contains(obs0) and obs0.astype(float).var() > 0
    assert info["distance"] >= task.success_radius and info["is_success"] is False
    t, moved = 0, False
    while True:
        t += 1
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        assert env.observation_space.contains(obs) and not terminated
        assert reward == float(info["is_success"]) and info["is_success"] == (info["distance"] < task.success_radius)
        mocap = env.unwrapped.mocap
        assert (task.hand_low - 1e-9 <= mocap).all() and (mocap <= task.hand_high + 1e-9).all()
        held = [axis for axis in range(3) if axis not in task.axes]  # the axes the hand is held on
        assert np.allclose(env.unwrapped.hand[held], task.hand_start[held], atol=0.005)
        moved |= np.abs(obs.astype(int) - obs0.astype(int)).max() > 40
        if truncated:
            break
    assert t == SAWYER_LENGTHS[env_id] == task.max_episode_steps and moved
    env.close()


@pytest.mark.parametrize("env_id", SAWYER_IDS)
def test_the_scripted_policy_solves_at_least_18_of_20_episodes(env_id):
    env = gym.make(env_id)
    solved = sum(expert_episode(env, seed)["is_success"] for seed in range(20))
    assert solved >= 18, f"{env_id}: the scripted policy ended {solved} of 20 episodes in success"
    env.close()


def test_a_step_moves_the_hand_two_centimetres_at_most():
    env = gym.make("GoCu/VisualSawyerReacher-v1")
    env.reset(seed=0)
    base = env.unwrapped
    start = base.mocap.copy()
    env.step(np.array([1.0, -0.5], np.float32))
    assert base.mocap == pytest.approx(start + [STEP, -0.5 * STEP, 0.0])
    for _ in range(3):
        env.step(np.zeros(2, np.float32))
    assert np.linalg.norm(base.hand - base.mocap) < 0.002  # the hand follows its mocap point
    env.close()


def moved_frame(env_id: str, move) -> tuple[np.ndarray, np.ndarray]:
    """The frame before and after ``move(base)`` changes the simulator's state (re-rendered, no step)."""
    import mujoco

    env = gym.make(env_id)
    frame, _ = env.reset(seed=3)
    base = env.unwrapped
    move(base)
    mujoco.mj_forward(base.model, base.data)
    after = base._observe()
    env.close()
    return frame.astype(int), after.astype(int)


def shift(body: str, dx: float, dy: float, dz: float = 0.0):
    def move(base):
        qpos = base.data.joint(body).qpos
        qpos[:3] += [dx, dy, dz]
    return move


@pytest.mark.parametrize(
    "env_id, move",
    [
        ("GoCu/VisualSawyerPusher-v1", shift("puck", 0.05, 0.0)),
        ("GoCu/VisualSawyerPusher-v1", shift("puck", 0.0, 0.05)),
        ("GoCu/VisualSawyerMultiObjectPusher-v1", shift("puck", 0.05, 0.0)),
        ("GoCu/VisualSawyerMultiObjectPusher-v1", shift("puck2", 0.0, -0.05)),
        ("GoCu/VisualSawyerPickAndPlace-v1", shift("ball", 0.0, 0.05)),
        ("GoCu/VisualSawyerPickAndPlace-v1", shift("ball", 0.0, 0.0, 0.05)),
        ("GoCu/VisualSawyerDoorHook-v1", lambda base: base.data.joint("hinge").qpos.__setitem__(0, 0.35)),
    ],
)
def test_moving_an_object_5cm_or_the_door_changes_the_frame(env_id, move):
    before, after = moved_frame(env_id, move)
    changed = (np.abs(after - before).max(axis=2) > 40).sum()
    assert changed >= 3, f"{env_id}: {changed} pixels changed"


def test_forced_success_pays_and_the_distances_are_the_papers():
    env = gym.make("GoCu/VisualSawyerPusher-v1")
    env.reset(seed=1)
    base = env.unwrapped
    goal = base.marker("goal")
    assert np.linalg.norm(goal[:2] - [0.0, 0.6]) >= 0.1  # drawn away from the puck's start
    base.data.joint("puck").qpos[:2] = goal[:2] + [0.0, 0.03]  # the puck 3 cm from its goal
    _, reward, _, _, info = env.step(np.zeros(2, np.float32))
    assert info["distance"] == pytest.approx(0.03, abs=0.003) and info["is_success"] is True and reward == 1.0
    env.close()

    env = gym.make("GoCu/VisualSawyerMultiObjectPusher-v1")
    env.reset(seed=1)
    base = env.unwrapped
    distances = base.task.puck_distances(base)
    _, _, _, _, info = env.step(np.zeros(2, np.float32))
    assert info["distance"] == pytest.approx(distances.sum(), abs=1e-3)  # the sum over the two pucks
    env.close()

    env = gym.make("GoCu/VisualSawyerDoorHook-v1")
    env.reset(seed=1)
    base = env.unwrapped
    _, _, _, _, info = env.step(np.zeros(3, np.float32))
    assert info["distance"] == pytest.approx(base.goal_angle, abs=1e-3)  # radians: the door starts shut
    env.close()


def test_seeds_draw_the_goals():
    env = gym.make("GoCu/VisualSawyerReacher-v1")
    first, _ = env.reset(seed=5)
    goal = env.unwrapped.marker("goal")
    again, _ = env.reset(seed=5)
    assert np.array_equal(first, again) and np.array_equal(goal, env.unwrapped.marker("goal"))
    env.reset(seed=6)
    assert not np.array_equal(goal, env.unwrapped.marker("goal"))
    env.close()


def test_bad_actions_and_arguments_are_refused():
    env = gym.make("GoCu/VisualSawyerPusher-v1")
    env.reset(seed=0)
    with pytest.raises(ValueError, match="action must have shape"):
        env.step(np.zeros(3, np.float32))
    with pytest.raises(ValueError, match=r"action must lie in \[-1, 1\]"):
        env.step(np.array([1.5, 0.0], np.float32))
    env.close()
    for kwargs, match in (({"image_size": 4}, "image_size"), ({"supersample": 0}, "supersample"), ({"render_mode": "human"}, "render_mode")):
        with pytest.raises(ValueError, match=match):
            gym.make("GoCu/VisualSawyerPusher-v1", **kwargs)


def test_every_task_is_registered_with_its_length():
    assert set(SAWYER_IDS) == set(SAWYER_TASKS)
    for env_id in SAWYER_IDS:
        assert gym.spec(env_id).max_episode_steps == SAWYER_TASKS[env_id].max_episode_steps


def test_the_reference_probe_reports_the_scripted_and_the_random_policy(capsys):
    from conftest import load_script

    probe = load_script("sawyer_tasks", "benchmarks/probes/sawyer_tasks.py")
    results = probe.main(["--episodes", "2", "--ids", "GoCu/VisualSawyerPickAndPlace-v1"])
    expert, rand = results["GoCu/VisualSawyerPickAndPlace-v1"]["expert"], results["GoCu/VisualSawyerPickAndPlace-v1"]["random"]
    assert expert["ends"] == 1.0 and expert["final"] < 0.06 < rand["final"]
    assert "| GoCu/VisualSawyerPickAndPlace-v1 | 1.00 / 1.00 /" in capsys.readouterr().out
    with pytest.raises(ValueError, match="--episodes"):
        probe.main(["--episodes", "0"])


def test_the_behaviour_probe_tells_a_moved_object_and_the_hands_spread(tmp_path):
    """sawyer_behaviour.py on an untrained PPO (a random-ish policy): it moves the puck in some episodes, makes no
    progress on average, and its hand ends spread over the workspace."""
    import torch as th
    from stable_baselines3 import PPO

    from conftest import load_script
    from sb3_gocu.policies import PaperCNN

    th.set_num_threads(1)
    model = PPO("CnnPolicy", gym.make("GoCu/VisualSawyerPusher-v1"), n_steps=64, seed=0,
                policy_kwargs={"features_extractor_class": PaperCNN, "normalize_images": True})
    model.save(tmp_path / "ppo.zip")
    probe = load_script("sawyer_behaviour", "benchmarks/probes/sawyer_behaviour.py")
    out = probe.main([str(tmp_path / "ppo.zip"), "--algo", "ppo", "--env", "GoCu/VisualSawyerPusher-v1", "--episodes", "4"])
    stochastic, deterministic = out["stochastic"], out["deterministic"]
    assert 0.0 <= stochastic["moved"] <= 1.0 and stochastic["hand_spread"] > 0.01  # random actions: the hand wanders
    assert deterministic["hand_spread"] < stochastic["hand_spread"]  # one policy, one place whatever the goal
