"""Why a one-value-head learner on the drop-in reward keeps exploring past DoorKey's open door.

    python benchmarks/probes/dropin_episodes.py <run>/checkpoints/ppo_sum_seed0 --steps 450560 --episodes 64 --seed 100

Loads a ``ppo_sum`` checkpoint of ``benchmarks/sample_efficiency.py`` (the PPO model and its wrapper's curiosity
module), plays ``--episodes`` episodes on 16 envs with the stochastic policy, reading each step's r_e and normalised
r_gc from ``infos`` as in training (the module's goals and revisit decay; nothing learned, nothing recorded), and prints:

* episodes, how many opened the door and how many reached the goal; for those that opened it, the steps from the door
  to the episode's end (goal or time limit);
* sigma * r_gc per step over all steps and over the steps after the door opened, and its sum over those steps;
* what a goal-reaching episode forgoes: the discounted sum ``sum_k gamma^k sigma * r_gc`` that the post-door rate
  would pay over the steps it did not take (to the time limit, then SB3's bootstrap of a truncation), beside the
  extrinsic reward it got;
* the value head: V(s) at the step before the goal, against V over the post-door states of episodes that ran to the
  time limit, and the reward for stepping onto the goal.

and, for the centred sum (the wrapper's default: r_gc less its running mean), the post-door rate and the forgone sum
with the mean of all the episodes' steps subtracted.
"""

from __future__ import annotations

import argparse
import pathlib
from typing import Any, Sequence

import numpy as np
import torch as th
from stable_baselines3 import PPO
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.utils import obs_as_tensor

import sb3_gocu  # noqa: F401  (registers the GoCu ids)
from sb3_gocu import GoalCuriosityModule, GoCuVecEnvWrapper

DOOR = 2  # info["task_phase"]: 0 start, 1 key, 2 door open, 3 goal


def play(model: PPO, env: Any, episodes: int, sigma: float) -> list[dict[str, Any]]:
    """Episodes of the model's stochastic policy, each a dict of per-step arrays."""
    n = env.num_envs
    obs = env.reset()
    current: list[dict[str, list]] = [{"r_e": [], "r_i": [], "phase": [], "value": []} for _ in range(n)]
    done_eps: list[dict[str, Any]] = []
    while len(done_eps) < episodes:
        with th.no_grad():
            values = model.policy.predict_values(obs_as_tensor(obs, model.device)).numpy().ravel()
        actions, _ = model.predict(obs, deterministic=False)
        obs, _, dones, infos = env.step(actions)
        for i, info in enumerate(infos):
            ep = current[i]
            ep["value"].append(float(values[i]))  # V(s_t) of the state the action was taken in
            ep["r_e"].append(info["extrinsic_reward"])
            ep["r_i"].append(sigma * info["gocu_reward"])
            ep["phase"].append(int(info.get("task_phase", -1)))
            if dones[i]:
                phase = np.array(ep["phase"])
                opened = int(np.argmax(phase >= DOOR)) + 1 if (phase >= DOOR).any() else None  # first step past the door
                done_eps.append({k: np.array(v) for k, v in ep.items()} | {"truncated": bool(info.get("TimeLimit.truncated")), "opened": opened})
                current[i] = {"r_e": [], "r_i": [], "phase": [], "value": []}
    return done_eps[:episodes]


def summarise(eps: list[dict[str, Any]], gamma: float, max_steps: int, label: str) -> dict[str, float]:
    door = [e for e in eps if e["opened"] is not None]
    goal = [e for e in eps if e["r_e"].sum() > 0]
    after = [e["r_i"][e["opened"]:] for e in door]
    post_rate = float(np.mean(np.concatenate(after))) if after and sum(map(len, after)) else float("nan")
    all_rate = float(np.mean(np.concatenate([e["r_i"] for e in eps])))
    forgone = [post_rate * (1 - gamma ** (max_steps - len(e["r_e"]))) / (1 - gamma) for e in goal]
    pre_goal_v = [e["value"][-1] for e in goal]  # V of the state the goal was stepped onto from
    timeout_post_v = [e["value"][e["opened"]:] for e in door if e["truncated"]]
    out = {
        "episodes": len(eps),
        "door_opened": len(door),
        "goal_reached": len(goal),
        "mean_length": float(np.mean([len(e["r_e"]) for e in eps])),
        "steps_door_to_end": float(np.mean([len(a) for a in after])) if after else float("nan"),
        "steps_door_to_goal": float(np.mean([len(e["r_e"]) - e["opened"] for e in goal])) if goal else float("nan"),
        "sigma_r_gc_per_step": all_rate,
        "sigma_r_gc_per_step_after_door": post_rate,
        "sigma_r_gc_sum_after_door": float(np.mean([a.sum() for a in after])) if after else float("nan"),
        "goal_extrinsic": float(np.mean([e["r_e"].sum() for e in goal])) if goal else float("nan"),
        "goal_forgone_discounted": float(np.mean(forgone)) if forgone else float("nan"),
        "centred_per_step_after_door": post_rate - all_rate,
        "centred_goal_forgone_discounted": float(np.mean([(post_rate - all_rate) * f / post_rate for f in forgone])) if forgone else float("nan"),
        "centred_return_from_start": float(np.mean([np.sum((e["r_i"] - all_rate) * gamma ** np.arange(len(e["r_i"]))) for e in eps])),
        "value_mean": float(np.mean(np.concatenate([e["value"] for e in eps]))),
        "value_before_goal": float(np.mean(pre_goal_v)) if pre_goal_v else float("nan"),
        "value_after_door_timeouts": float(np.mean(np.concatenate(timeout_post_v))) if timeout_post_v else float("nan"),
    }
    print(f"{label}:")
    for k, v in out.items():
        print(f"  {k:32s} {v:.4f}" if isinstance(v, float) else f"  {k:32s} {v}")
    return out


def main(argv: Sequence[str] | None = None) -> dict[str, float]:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("ckpt_dir", help="<run>/checkpoints/ppo_sum_seed<k> of benchmarks/sample_efficiency.py")
    p.add_argument("--steps", type=int, required=True, help="which checkpoint (model_<steps>.zip, curiosity_<steps>.pth)")
    p.add_argument("--env", default="GoCu/DoorKey-8x8-v0")
    p.add_argument("--episodes", type=int, default=64)
    p.add_argument("--seed", type=int, default=100)
    p.add_argument("--sigma", type=float, default=0.25, help="intrinsic_coef of the run")
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args(argv)
    if args.episodes < 1:
        p.error(f"--episodes must be >= 1, got {args.episodes}")
    th.set_num_threads(args.threads)
    ckpt = pathlib.Path(args.ckpt_dir)
    venv = make_vec_env(args.env, n_envs=16, seed=args.seed)
    module = GoalCuriosityModule(venv.observation_space)
    module.load_state_dict(th.load(ckpt / f"curiosity_{args.steps}.pth", weights_only=True))
    env = GoCuVecEnvWrapper(venv, module=module, mode="sum", intrinsic_coef=args.sigma)
    model = PPO.load(ckpt / f"model_{args.steps}.zip", env=env, device="cpu")
    max_steps = venv.get_attr("max_steps")[0]
    print(f"python benchmarks/probes/dropin_episodes.py {args.ckpt_dir} --steps {args.steps} --episodes {args.episodes} --seed {args.seed}")
    print(f"gamma {model.gamma}, sigma {args.sigma}, time limit {max_steps}")
    return summarise(play(model, model.get_env(), args.episodes, args.sigma), model.gamma, max_steps, f"checkpoint {args.steps}")


if __name__ == "__main__":
    main()
