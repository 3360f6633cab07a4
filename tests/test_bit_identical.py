"""The default configuration trains the same networks, bit for bit, as when these hashes were recorded.

A fixed-seed DoorKey-8x8 run of PPO_GoCu with every default (16 envs, one torch thread) for 61,440 steps: the
random-policy pretraining, the VAE's pretraining update and three predictor updates (on reachability pairs, each
scored on held-out pairs). The test hashes the policy's,
the VAE's and the predictor's weights at the end, and every rollout's extrinsic and intrinsic rewards as stored in
the rollout buffer. A refactor of the curiosity core that keeps the defaults' arithmetic keeps these hashes; a
change that moves any value by one bit does not.

Float sums take other paths on other CPUs, so the hashes are recorded per CPU model (``/proc/cpuinfo``'s model
name, with the widest vector instructions it offers: a virtual machine may name two generations alike); on a CPU with
none recorded the test is skipped, saying so. To record them for a new CPU model, run
``python tests/test_bit_identical.py`` at a commit whose defaults are the reference, and add its output below.
"""

from __future__ import annotations

import hashlib
import platform

import pytest
import torch as th
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env

from sb3_gocu import PPO_GoCu

STEPS, SEED, N_ENVS = 61_440, 0, 16

#: CPU model name -> {"policy", "vae", "predictor", "rewards"}: SHA-256 prefixes of the reference run
RECORDED: dict[str, dict[str, str]] = {
    "Intel(R) Xeon(R) Processor (AVX-512)": {"policy": "1386df8cf6bf80ef", "vae": "0959c3d3674a648d", "predictor": "b9f7035fb3388db1", "rewards": "7f294fa064d8db41"},
}


def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo``) and its widest vector extension ("AVX-512", "AVX2" or none), else
    the platform's processor string."""
    name, flags = None, set()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name") and name is None:
                    name = line.split(":", 1)[1].strip()
                elif line.startswith("flags") and not flags:
                    flags = set(line.split(":", 1)[1].split())
    except OSError:
        pass
    if name is None:
        return platform.processor() or platform.machine()
    simd = "AVX-512" if "avx512f" in flags else "AVX2" if "avx2" in flags else None
    return f"{name} ({simd})" if simd else name


def digest(*arrays) -> str:
    h = hashlib.sha256()
    for a in arrays:
        h.update(a.tobytes())
    return h.hexdigest()[:16]


def network_digest(network: th.nn.Module) -> str:
    return digest(*(v.detach().cpu().numpy() for v in network.state_dict().values()))


class RewardHash(BaseCallback):
    """Hashes each rollout's stored extrinsic and intrinsic rewards, in order."""

    def __init__(self) -> None:
        super().__init__()
        self.sha = hashlib.sha256()
        self.rollouts = 0

    def _on_step(self) -> bool:
        return True

    def _on_rollout_end(self) -> None:
        buffer = self.model.rollout_buffer
        self.sha.update(buffer.rewards.tobytes())
        self.sha.update(buffer.intrinsic_rewards.tobytes())
        self.rollouts += 1


def reference_run() -> dict[str, str]:
    """The run the hashes record; returns its hashes."""
    threads = th.get_num_threads()
    th.set_num_threads(1)
    try:
        env = make_vec_env("GoCu/DoorKey-8x8-v0", n_envs=N_ENVS, seed=SEED)
        model = PPO_GoCu("CnnPolicy", env, seed=SEED)
        rewards = RewardHash()
        model.learn(STEPS, callback=rewards)
        module = model.curiosity
        assert module.pretrained and rewards.rollouts == STEPS // (N_ENVS * model.n_steps)
        return {
            "policy": network_digest(model.policy),
            "vae": network_digest(module.vae),
            "predictor": network_digest(module.predictor),
            "rewards": rewards.sha.hexdigest()[:16],
        }
    finally:
        th.set_num_threads(threads)


@pytest.mark.slow
def test_default_configuration_trains_the_recorded_networks():
    recorded = RECORDED.get(cpu_model())
    if recorded is None:
        pytest.skip(f"no hashes recorded for the CPU model {cpu_model()!r} (see this file's docstring)")
    assert reference_run() == recorded


if __name__ == "__main__":
    print(f"    {cpu_model()!r}: {reference_run()!r},")
