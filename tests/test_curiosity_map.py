"""examples/curiosity_map.py on a PPO_GoCu model trained for a tiny budget on DoorKey-8x8 (about 15-25 s on 2 busy cores)."""


import numpy as np
import pytest
import torch as th
from stable_baselines3.common.env_util import make_vec_env

from sb3_gocu import PPO_GoCu

from conftest import TINY_IMAGE_CURIOSITY, load_script

ENV_ID = "GoCu/DoorKey-8x8-v0"


@pytest.fixture(scope="module")
def curiosity_map():
    return load_script("curiosity_map", "examples/curiosity_map.py")


@pytest.fixture(scope="module")
def model_path(tmp_path_factory):
    th.set_num_threads(1)  # module-scoped: set up before conftest's per-test fixture
    env = make_vec_env(ENV_ID, n_envs=2, seed=0)
    model = PPO_GoCu("CnnPolicy", env, n_steps=32, batch_size=64, n_epochs=1, seed=0, curiosity_kwargs=TINY_IMAGE_CURIOSITY)
    model.learn(1024)
    assert model.curiosity.goal_buffer.size > 0
    path = tmp_path_factory.mktemp("map_model") / "gocu_tiny.zip"
    model.save(path)
    return path


def test_curiosity_map(curiosity_map, model_path, tmp_path):
    out = tmp_path / "maps"
    maps = curiosity_map.make_curiosity_maps(model_path, ENV_ID, seed=3, out=out, n_reconstructions=4)

    for f in ("curiosity_map.png", "vae_reconstructions.png", "curiosity_map.npz"):
        assert (out / f).is_file() and (out / f).stat().st_size > 1000, f
    assert maps["grid_shape"] == (8, 8)
    alpha, delta = maps["alpha"], maps["reward_scale"]
    assert len(maps["goals"]) == TINY_IMAGE_CURIOSITY["n_goals"]

    phases = maps["phases"]
    assert set(phases) == {"no_key", "key", "door_open"}
    for name, ph in phases.items():
        reward, mastery, masked = ph["reward"], ph["mastery"], ph["masked"]
        assert reward.shape == mastery.shape == masked.shape == (8, 8)
        # NaN exactly on the masked cells, and the masked cells include the outer walls
        np.testing.assert_array_equal(np.isnan(reward), masked, err_msg=name)
        np.testing.assert_array_equal(np.isnan(mastery), masked, err_msg=name)
        assert masked[0].all() and masked[-1].all() and masked[:, 0].all() and masked[:, -1].all()
        r, m = reward[~masked], mastery[~masked]
        assert len(r) == len(ph["cells"]) > 0
        assert np.all(r >= 0) and np.all(r <= alpha / delta + 1e-6), (name, r.min(), r.max())
        assert np.all(m >= 0) and np.all(m <= 1), (name, m.min(), m.max())
        assert ph["observations"].shape == (len(ph["cells"]), 4, 32, 32, 3)

    # the right room is reachable only once the door is open; the key's cell only once the key is carried
    n_reach = {k: int((~v["masked"]).sum()) for k, v in phases.items()}
    assert n_reach["no_key"] < n_reach["key"] < n_reach["door_open"]

    # the three phases look different from the same cells
    common = sorted(set(phases["no_key"]["cells"]) & set(phases["key"]["cells"]) & set(phases["door_open"]["cells"]))
    assert common
    obs = {k: np.stack([v["observations"][v["cells"].index(c)] for c in common]) for k, v in phases.items()}
    assert not np.array_equal(obs["no_key"], obs["key"])
    assert not np.array_equal(obs["key"], obs["door_open"])
    assert not np.array_equal(obs["no_key"], obs["door_open"])

    saved = np.load(out / "curiosity_map.npz")
    np.testing.assert_array_equal(saved["door_open_reward"], phases["door_open"]["reward"])
    assert maps["reconstructions"].shape == maps["reconstruction_inputs"].shape == (4, 32, 32, 3)


def test_curiosity_map_cli(curiosity_map, model_path, tmp_path):
    maps = curiosity_map.main(["--model", str(model_path), "--env", ENV_ID, "--seed", "0", "--out", str(tmp_path), "--n-goals", "2", "--fixed-scale"])
    assert len(maps["goals"]) == 2
    assert (tmp_path / "curiosity_map.png").is_file()


def test_sawyer_curiosity(tmp_path):
    """examples/sawyer_curiosity.py on a PPO_GoCu model trained for 1,024 steps on the Sawyer reacher: the task's
    scripted policy reaches the goal (a success; its distance falls below the random policy's) and every frame of both
    episodes is scored."""
    th.set_num_threads(1)
    env = make_vec_env("GoCu/VisualSawyerReacher-v1", n_envs=2, seed=0)
    model = PPO_GoCu("CnnPolicy", env, n_steps=256, batch_size=128, n_epochs=1, seed=0, curiosity_kwargs=TINY_IMAGE_CURIOSITY)
    model.learn(1024)
    env.close()
    assert model.curiosity.goal_buffer.size > 0
    path = tmp_path / "gocu_reacher.zip"
    model.save(path)
    script = load_script("sawyer_curiosity", "examples/sawyer_curiosity.py")
    out = script.main(["--model", str(path), "--env", "GoCu/VisualSawyerReacher-v1", "--max-steps", "40", "--out", str(tmp_path / "out")])
    expert, rand = out["expert"], out["random"]
    assert expert["distance"][-1] < 0.5 * expert["distance"][0] and expert["distance"][-1] < rand["distance"][-1]
    assert expert["success"].any()  # info["is_success"] at some step: the hand within the success radius of the goal
    for ep in (expert, rand):
        assert ep["r_gc"].shape == (41,) and np.isfinite(ep["r_gc"]).all()
        assert ((ep["max_mastery"] >= 0) & (ep["max_mastery"] <= 1)).all()
    assert out["recon"].shape == (8, 32, 32, 3) and 0 <= out["recon"].min() and out["recon"].max() <= 1
    assert (tmp_path / "out" / "sawyer_curiosity.png").stat().st_size > 0
