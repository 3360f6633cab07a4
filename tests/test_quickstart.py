"""examples/quickstart.py, the README's first command, on a tiny budget (about 20-40 s on 2 busy cores: the
pretraining's 10,000 random steps and 20 VAE epochs are the paper's and run in full)."""

import re

import numpy as np
import torch as th

from conftest import load_script
from sb3_gocu import PPO_GoCu


def test_quickstart_trains_saves_and_evaluates(tmp_path, capsys):
    quickstart = load_script("quickstart", "examples/quickstart.py")
    save = tmp_path / "gocu_doorkey5"
    model, returns = quickstart.main(["--timesteps", "2048", "--eval-episodes", "3", "--save", str(save)])
    assert model.num_timesteps == 2048  # one rollout of the paper's 16 envs x 128 steps
    assert model.curiosity.pretrained and model.curiosity.goal_buffer.size > 0
    # the saved file is the trained model, curiosity included
    loaded = PPO_GoCu.load(save, device="cpu")
    for name, tensor in model.policy.state_dict().items():
        assert th.equal(loaded.policy.state_dict()[name], tensor), name
    for name, tensor in model.curiosity.vae.state_dict().items():
        assert th.equal(loaded.curiosity.vae.state_dict()[name], tensor), name
    # the printed evaluation is that of the returned episodes
    assert len(returns) == 3 and np.all((returns >= 0) & (returns <= 1))
    line = re.search(r"evaluation over (\d+) episodes: success rate ([\d.]+), mean return ([\d.]+)", capsys.readouterr().out)
    assert line is not None
    assert int(line.group(1)) == 3
    assert float(line.group(2)) == round(float(np.mean(returns > 0)), 2)
    assert float(line.group(3)) == round(float(returns.mean()), 3)
