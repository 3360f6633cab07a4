"""Scoring eq 13 in bfloat16 (``scoring_dtype="bfloat16"``) against float32: how far the rewards move on a
trained agent's states, and how much faster the scoring runs, measured in the same process.

    python benchmarks/bf16_scoring.py --model path/to/ppo_gocu_model.zip --env GoCu/DoorKey-8x8-v0 \\
        --steps 256 --threads 1 --seed 0

Plays ``--steps`` vector steps of ``--n-envs`` envs with the model's stochastic policy, embeds every
observation with the model's VAE and scores it against K goals drawn from the model's goal buffer for its env
(one draw per env, as at an episode start), with the model's predictor folded in float32 and in bfloat16. Prints:

* precision: the raw r_gc of both (max and mean absolute difference, against the spread of r_gc), and the share
  of states whose most-mastered goal (the ``max`` of eq 13) changes;
* speed: the wall time of ``eq13_rows`` (first-layer halves, the hidden layers and the output for K goals) per
  state at ``--batch-sizes`` states per call (the rows PPO_GoCu scores per vector step are the reward memo's
  misses, a few of 16 on DoorKey), float32 and bfloat16 alternating call by call, and their ratio.

bfloat16 products are fast only on a CPU with AVX512-BF16 (or AMX); the script prints whether this one has it.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch as th
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import VecTransposeImage

import sb3_gocu  # noqa: F401  (registers the GoCu/ ids)
from sb3_gocu import PPO_GoCu
from sb3_gocu.curiosity.scoring import eq13_rows

sys.path.insert(0, str(Path(__file__).resolve().parent))  # also when loaded by path (the tests)
from sample_efficiency import machine_line  # noqa: E402  (same directory)


def cpu_flags() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            flags = next((line.split(":", 1)[1].split() for line in f if line.startswith("flags")), [])
    except OSError:
        return "unknown"
    wanted = ("avx2", "avx512f", "avx512_bf16", "amx_bf16")
    return " ".join(f for f in wanted if f in flags) or "none of " + ", ".join(wanted)


def main(argv: list[str] | None = None) -> dict:
    """Run the comparison; :return: the printed figures (``precision``, ``speed``: {states per call: (float32 ms,
    bfloat16 ms)})."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", required=True, help="a saved PPO_GoCu model (zip)")
    parser.add_argument("--env", default="GoCu/DoorKey-8x8-v0")
    parser.add_argument("--n-envs", type=int, default=16)
    parser.add_argument("--steps", type=int, default=256, help="vector steps to play")
    parser.add_argument("--batch-sizes", type=int, nargs="+", default=[1, 4, 16], help="states per scoring call")
    parser.add_argument("--calls", type=int, default=200, help="timed calls per batch size and dtype")
    parser.add_argument("--threads", type=int, default=1, help="torch.set_num_threads")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    for name in ("n_envs", "steps", "calls", "threads"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    if min(args.batch_sizes) < 1:
        parser.error(f"--batch-sizes must all be >= 1, got {args.batch_sizes}")
    th.set_num_threads(args.threads)
    print("command: python benchmarks/bf16_scoring.py " + " ".join(sys.argv[1:] if argv is None else argv))
    print(f"machine: {machine_line(args.threads)}; seed {args.seed}; CPU flags: {cpu_flags()}")

    venv = VecTransposeImage(make_vec_env(args.env, n_envs=args.n_envs, seed=args.seed))
    model = PPO_GoCu.load(args.model, device="cpu")
    module = model.curiosity
    module.ensure_envs(args.n_envs)
    th.manual_seed(args.seed)
    module.sample_goals(np.arange(args.n_envs))
    if not module._has_goals.all():
        sys.exit("the model's goal buffer is empty: give a trained model")
    obs = venv.reset()
    raw, envs = [], []
    for _ in range(args.steps):
        raw.append(module.adapter.extract(obs))
        envs.append(np.arange(args.n_envs))
        action, _ = model.predict(obs, deterministic=False)
        obs, _, _, _ = venv.step(action)
    raw_all, env_all = np.concatenate(raw), np.concatenate(envs)
    phi = module.embed(raw_all)
    goal_parts = module._goal_parts[th.from_numpy(env_all)]
    has_goals = np.ones(len(phi), dtype=bool)
    f32, bf16 = module.predictor.fold(th.float32), module.predictor.fold(th.bfloat16)
    eq13 = module._eq13_args

    # precision
    r32 = eq13_rows(phi, goal_parts, has_goals, f32, *eq13).numpy()
    r16 = eq13_rows(phi, goal_parts, has_goals, bf16, *eq13).numpy()
    with th.inference_mode():
        m32 = f32.mastery_from_parts(f32.state_part(phi), goal_parts)
        m16 = bf16.mastery_from_parts(bf16.state_part(phi), goal_parts)
    diff = np.abs(r32 - r16)
    distinct = len(np.unique(raw_all.reshape(len(raw_all), -1), axis=0))
    print(f"\nprecision: {len(phi)} states ({distinct} distinct observations), K = {goal_parts.shape[1]}, "
          f"model {args.model}")
    print(f"  raw r_gc float32: mean {r32.mean():.5f}, std {r32.std():.5f}, range [{r32.min():.5f}, {r32.max():.5f}]")
    print(f"  |r_gc bfloat16 - float32|: max {diff.max():.2e}, mean {diff.mean():.2e} "
          f"(max / std of r_gc: {diff.max() / max(r32.std(), 1e-12):.4f})")
    print(f"  |mastery bfloat16 - float32| over all (state, goal) pairs: max {(m32 - m16).abs().max():.2e}, "
          f"mean {(m32 - m16).abs().mean():.2e}")
    changed = float((m32.argmax(1) != m16.argmax(1)).float().mean())
    print(f"  states whose most-mastered goal changes: {changed:.4f}")
    result: dict = {
        "precision": {"states": len(phi), "r_std": float(r32.std()), "r_diff_max": float(diff.max()),
                      "r_diff_mean": float(diff.mean()), "mastery_diff_max": float((m32 - m16).abs().max()),
                      "argmax_changed": changed},
        "speed": {},
    }

    # speed
    print(f"\nspeed: eq13_rows per call, {args.calls} calls per dtype, alternating, torch threads {args.threads}")
    print(f"  {'states/call':>11} {'float32 ms':>11} {'bfloat16 ms':>12} {'float32/bfloat16':>17}")
    rng = np.random.default_rng(args.seed)
    for n in args.batch_sizes:
        times = {"f32": 0.0, "bf16": 0.0}
        for name, folded in (("f32", f32), ("bf16", bf16)):  # warm up
            eq13_rows(phi[:n], goal_parts[:n], has_goals[:n], folded, *eq13)
        for _ in range(args.calls):
            rows = th.from_numpy(rng.integers(0, len(phi), n))
            p, g, h = phi[rows], goal_parts[rows], has_goals[:n]
            for name, folded in (("f32", f32), ("bf16", bf16)):
                t0 = time.perf_counter()
                eq13_rows(p, g, h, folded, *eq13)
                times[name] += time.perf_counter() - t0
        a, b = (1e3 * times[k] / args.calls for k in ("f32", "bf16"))
        print(f"  {n:>11} {a:>11.3f} {b:>12.3f} {a / b:>16.2f}x")
        result["speed"][n] = (a, b)
    venv.close()
    return result


if __name__ == "__main__":
    main()
