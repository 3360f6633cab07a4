"""The paper's Sawyer tasks on Meta-World (sb3_gocu/envs/sawyer_envs.py): frames, reward, distance, seeds, speed-ups."""

import gymnasium as gym
import mujoco
import numpy as np
import pytest

from sb3_gocu.envs import SAWYER_IDS, SAWYER_LENGTHS
from sb3_gocu.envs.sawyer_envs import (
    SAWYER_TASKS,
    SceneRenderer,
    VisualSawyer,
    cluster_mesh,
    visible_bodies,
)

IMAGE_SPACE = gym.spaces.Box(0, 255, (32, 32, 3), np.uint8)
#: Meta-World's success radius of each task (its evaluate_state)
SUCCESS_RADIUS = {
    "GoCu/VisualSawyerReacher-v0": 0.05,
    "GoCu/VisualSawyerDoorHook-v0": 0.08,
    "GoCu/VisualSawyerPusher-v0": 0.05,
    "GoCu/VisualSawyerPickAndPlace-v0": 0.07,
    "GoCu/VisualSawyerMultiObjectPusher-v0": 0.05,  # each puck to its own goal; the distance is their mean
}


@pytest.mark.parametrize("env_id", SAWYER_IDS)
def test_spaces_length_reward_distance_and_moving_frames(env_id):
    env = gym.make(env_id)
    assert env.observation_space == IMAGE_SPACE and env.action_space.shape == (4,)
    env.action_space.seed(0)
    obs0, info = env.reset(seed=0)
    assert env.observation_space.contains(obs0) and obs0.astype(float).var() > 0
    assert info["distance"] > SUCCESS_RADIUS[env_id] and info["is_success"] is False
    sim = env.unwrapped.sim
    t = 0
    while True:
        t += 1
        action = np.array([1.0, -1.0, 1.0, 1.0], np.float32) if t <= 10 else env.action_space.sample()
        obs, reward, terminated, truncated, info = env.step(action)
        assert env.observation_space.contains(obs)
        assert reward == float(info["is_success"]) and not terminated
        # the distance is the one the success test reads
        if "MultiObject" in env_id:
            assert info["is_success"] == bool((sim.puck_distances() <= 0.05).all())
            assert info["distance"] == pytest.approx(sim.puck_distances().mean())
        else:
            assert info["is_success"] == (info["distance"] <= SUCCESS_RADIUS[env_id])
        if t == 10:
            assert np.abs(obs.astype(int) - obs0.astype(int)).mean() > 0.5, "the frame did not change when the arm moved"
        if truncated:
            break
    assert t == SAWYER_LENGTHS[env_id]
    assert sim.curr_path_length == t  # Meta-World counted the same steps (its own limit, 500, never hit)
    env.close()


def test_distance_is_meta_worlds_own_and_forced_success_pays():
    env = gym.make("GoCu/VisualSawyerPusher-v0")
    env.reset(seed=1)
    sim = env.unwrapped.sim
    _, _, _, _, info = env.step(np.zeros(4, np.float32))
    _, sim_info = sim.evaluate_state(sim._get_obs(), np.zeros(4, np.float32))
    assert info["distance"] == pytest.approx(sim_info["obj_to_target"], abs=1e-9)
    sim._set_obj_xyz(sim._target_pos.copy())  # the puck onto its goal
    _, reward, _, _, info = env.step(np.zeros(4, np.float32))
    assert info["distance"] < 0.05 and info["is_success"] is True and reward == 1.0
    env.close()


def test_two_pucks_each_to_its_own_goal():
    env = gym.make("GoCu/VisualSawyerMultiObjectPusher-v0")
    obs0, _ = env.reset(seed=1)
    sim = env.unwrapped.sim
    pucks, goals = sim._get_pos_objects().reshape(2, 3), np.stack([sim._target_pos, sim.target2])
    assert np.linalg.norm(pucks[0, :2] - pucks[1, :2]) >= sim.SEPARATION and (goals[:, 1] >= 0.8).all()
    second = sim.model.jnt_qposadr[sim.model.joint("obj2joint").id]

    def place(first_xy, second_xy):
        qpos = sim.data.qpos.copy()
        qpos[9:11], qpos[second:second + 2] = first_xy, second_xy
        sim.set_state(qpos, np.zeros_like(sim.data.qvel))
        return env.step(np.zeros(4, np.float32))

    obs, reward, _, _, info = place(goals[0, :2], pucks[1, :2])  # one puck home: not solved
    assert reward == 0.0 and not info["is_success"] and sim.puck_distances()[0] < 0.01
    assert np.abs(obs.astype(int) - obs0.astype(int)).sum() > 0, "the moved puck shows"
    _, reward, _, _, info = place(goals[1, :2], goals[0, :2])  # each on the other's goal: not solved
    assert reward == 0.0 and not info["is_success"]
    _, reward, _, _, info = place(goals[0, :2], goals[1, :2])  # both home
    assert reward == 1.0 and info["is_success"] and info["distance"] < 0.01
    env.close()


def test_seed_fixes_the_variation_and_the_frames():
    a, b = VisualSawyer(SAWYER_TASKS["GoCu/VisualSawyerReacher-v0"]), VisualSawyer(SAWYER_TASKS["GoCu/VisualSawyerReacher-v0"])
    obs_a, info_a = a.reset(seed=3)
    obs_b, info_b = b.reset(seed=3)
    assert info_a["variation"] == info_b["variation"] and np.array_equal(obs_a, obs_b)
    goals = set()
    for _ in range(8):
        a.reset()
        goals.add(tuple(np.round(a.sim._target_pos, 4)))
    assert len(goals) > 1, "resets draw other variations"
    a.close()
    b.close()


@pytest.mark.parametrize("env_id", ["GoCu/VisualSawyerMultiObjectPusher-v0", "GoCu/VisualSawyerDoorHook-v0"])
def test_fast_frames_match_the_simulations_own_scene(env_id):
    """The simplified copy, posed from the simulation, draws what the simulation's own model draws: against frames of
    a plain renderer of the simulation (whole meshes, nothing hidden, the same camera, size and supersampling; shadows
    and multisampling off in both), under 1.5/255 on average and at most 2% of the pixels (edges of the arm) by more
    than 32/255 (unlit, misplaced or wrongly hidden parts move far more)."""
    import cv2

    env = VisualSawyer(SAWYER_TASKS[env_id])
    model, data = env.sim.model, env.sim.data
    model.vis.quality.shadowsize = 0
    model.vis.quality.offsamples = 0
    full = mujoco.Renderer(model, 64, 64)
    full.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = False
    full.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = False
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    for _ in range(5):
        for _ in range(15):
            obs, *_ = env.step(rng.uniform(-1, 1, 4))
        full.update_scene(data, camera=env.scene.camera)
        reference = cv2.resize(full.render(), (32, 32), interpolation=cv2.INTER_AREA)
        diff = np.abs(obs.astype(int) - reference.astype(int))
        assert diff.mean() < 1.5 and (diff.max(-1) > 32).sum() <= 20, (diff.mean(), (diff.max(-1) > 32).sum())
    full.close()
    env.close()


def test_pucks_rest_where_they_are_put():
    """Both pucks stay put while the arm holds still above them (a puck's centre of mass is at its centre)."""
    env = gym.make("GoCu/VisualSawyerMultiObjectPusher-v0")
    env.reset(seed=0)
    sim = env.unwrapped.sim
    start = sim._get_pos_objects().copy()
    for _ in range(200):
        env.step(np.zeros(4, np.float32))
    assert np.abs(sim._get_pos_objects() - start).max() < 1e-3
    assert np.allclose(sim.model.body("obj2").ipos, 0.0)
    env.close()


@pytest.mark.parametrize("env_id", ["GoCu/VisualSawyerReacher-v0", "GoCu/VisualSawyerDoorHook-v0"])
def test_hidden_bodies_never_show(env_id):
    env = VisualSawyer(SAWYER_TASKS[env_id])
    seen = visible_bodies(env, grid=3)
    assert not seen & set(env.task.hidden_bodies), seen & set(env.task.hidden_bodies)
    assert {"right_hand", "right_l5"} <= seen  # the check sees what it should
    env.close()


def test_cluster_mesh_merges_close_corners_and_drops_collapsed_triangles():
    # two triangles sharing an edge, and a sliver whose corners all fall in one cell
    corners = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0],
                        [5, 5, 5], [5.01, 5, 5], [5, 5.01, 5]], dtype=float)
    vertices, faces = cluster_mesh(corners, 0.1)
    assert len(vertices) == 4  # the shared corners merged, the sliver's vertices gone with it
    assert vertices[faces].tolist() == corners[:6].reshape(2, 3, 3).tolist()  # both triangles kept, in their orientation
    with pytest.raises(ValueError, match="mesh_cell must be >= 0"):
        SceneRenderer("unused.xml", 32, SAWYER_TASKS["GoCu/VisualSawyerPusher-v0"].camera, mesh_cell=-1)


def test_bad_arguments_are_refused():
    task = SAWYER_TASKS["GoCu/VisualSawyerPusher-v0"]
    for kwargs, message in [({"image_size": 4}, "image_size must be >= 8"), ({"supersample": 0}, "supersample must be >= 1"),
                            ({"render_mode": "human"}, "render_mode must be None or 'rgb_array'")]:
        with pytest.raises(ValueError, match=message):
            VisualSawyer(task, **kwargs)
    assert mujoco.__version__.startswith("3.3")  # Meta-World's pin, through the [robotics] extra


def test_ppo_gocu_trains_on_a_sawyer_task():
    """A short PPO_GoCu run on the Sawyer family (2 envs, 2,048 steps, tiny curiosity): the curiosity module pretrains,
    holds goals and trains its predictor on 32x32 frames of a continuous-control task."""
    import torch as th
    from stable_baselines3.common.env_util import make_vec_env

    from conftest import TINY_IMAGE_CURIOSITY
    from sb3_gocu import PPO_GoCu

    threads = th.get_num_threads()
    th.set_num_threads(1)
    try:
        env = make_vec_env("GoCu/VisualSawyerPusher-v0", n_envs=2, seed=0)
        model = PPO_GoCu("CnnPolicy", env, n_steps=256, batch_size=128, n_epochs=1, seed=0, curiosity_kwargs=TINY_IMAGE_CURIOSITY)
        model.learn(2048)
        module = model.curiosity
        assert model.num_timesteps == 2048 and module.pretrained and module.goal_buffer.size > 0
        assert module.last_predictor_update > 0, "the predictor was trained"
        assert len(model.ep_info_buffer) == 2 * (1024 // 150)  # each env finished its 150-step episodes
        env.close()
    finally:
        th.set_num_threads(threads)
