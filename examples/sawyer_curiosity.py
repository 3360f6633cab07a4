"""Where is a trained PPO_GoCu agent curious on a Sawyer task? r_gc along an expert's episode and a random one.

    MUJOCO_GL=egl python examples/sawyer_curiosity.py --model model.zip --env GoCu/VisualSawyerPusher-v1 --seed 0 --out out/

The Sawyer tasks have no grid to map (``examples/curiosity_map.py`` is DoorKey's), so this draws the curiosity along
two episodes from the same seed (``env.reset(seed=--seed)``, which draws the goal, so both have the same one): one of
the task's scripted policy (``env.unwrapped.task.expert_action``, read from the simulator's state), which solves it,
and one of a random policy. Each frame is scored against a fixed set of K goals drawn once from the model's goal
buffer, as in ``curiosity_map.py``:

* raw r_gc of eq 13, ``(alpha - h(m_1..m_K)) / delta`` (before the normalisation of eq 14);
* max mastery, ``max_k m(phi(s), phi(g_k))``.

Files written to ``--out``: ``sawyer_curiosity.png`` (8 of the expert's frames above their VAE reconstructions, and
both episodes' r_gc and ``info["distance"]`` per step) and ``sawyer_curiosity.npz`` (the arrays). If r_gc does not
rise where the expert does what the task asks (hooks the handle, moves the puck), the curiosity gives the agent no
reason to go there; if the reconstructions lose the object, the VAE cannot tell those frames apart.
"""

from __future__ import annotations

import argparse
import pathlib
import sys
from typing import Any

import gymnasium as gym
import matplotlib
import numpy as np
import torch as th

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

import sb3_gocu  # noqa: E402,F401  (registers the environments)
from sb3_gocu import PPO_GoCu  # noqa: E402

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from curiosity_map import sample_goals, score, to_module_layout  # noqa: E402


def episode(env: gym.Env, policy: str, seed: int, max_steps: int | None = None) -> dict[str, np.ndarray]:
    """One episode of ``policy`` ("expert" or "random") from ``env.reset(seed=seed)``: frames (n, H, W, C), distances,
    successes."""
    base = env.unwrapped
    obs, info = env.reset(seed=seed)
    env.action_space.seed(seed)
    frames, distances, successes = [obs], [info["distance"]], [False]
    done, t = False, 0
    while not done and (max_steps is None or t < max_steps):
        action = base.task.expert_action(base) if policy == "expert" else env.action_space.sample()
        obs, _, terminated, truncated, info = env.step(np.clip(action, -1, 1).astype(np.float32))
        frames.append(obs)
        distances.append(info["distance"])
        successes.append(info["is_success"])
        done, t = terminated or truncated, t + 1
    return {"frames": np.stack(frames), "distance": np.array(distances), "success": np.array(successes)}


@th.inference_mode()
def sawyer_curiosity(model: PPO_GoCu, env_id: str, seed: int = 0, max_steps: int | None = None) -> dict[str, Any]:
    """Both episodes, scored: ``{policy: {frames, distance, success, r_gc, max_mastery}}``, the goals, and the
    expert's 8 frames with their VAE reconstructions (``shown``, ``recon``, (8, H, W, C) in [0, 1])."""
    module = model.curiosity
    if module is None:
        raise ValueError("the model has no curiosity module (curiosity=False)")
    goals = sample_goals(module, None, seed)
    env = gym.make(env_id)
    out: dict[str, Any] = {"goals": goals}
    try:
        for policy in ("expert", "random"):
            ep = episode(env, policy, seed, max_steps)
            ep["r_gc"], ep["max_mastery"] = score(module, to_module_layout(ep["frames"], module.adapter.raw_shape), goals)
            out[policy] = ep
    finally:
        env.close()
    frames = out["expert"]["frames"]
    idx = np.linspace(0, len(frames) - 1, 8).round().astype(int)
    x = module.adapter.to_tensor(to_module_layout(frames[idx], module.adapter.raw_shape), module.device)
    recon = module.vae.reconstruct(x).cpu().numpy()
    out["shown_steps"], out["shown"] = idx, frames[idx] / 255.0
    out["recon"] = np.clip(recon.transpose(0, 2, 3, 1), 0, 1)  # the ConvVAE's output is (n, C, H, W)
    return out


def draw(result: dict[str, Any], title: str, path: pathlib.Path) -> None:
    fig = plt.figure(figsize=(11, 6), dpi=110)
    grid = fig.add_gridspec(3, 8, height_ratios=[1, 1, 2.2])
    for i, step in enumerate(result["shown_steps"]):
        for row, imgs, label in ((0, result["shown"], "expert frame"), (1, result["recon"], "VAE reconstruction")):
            ax = fig.add_subplot(grid[row, i])
            ax.imshow(imgs[i], interpolation="nearest")
            ax.set_xticks([]), ax.set_yticks([])
            ax.set_title(f"step {step}" if row == 0 else "", fontsize=7)
            if i == 0:
                ax.set_ylabel(label, fontsize=7)
    ax = fig.add_subplot(grid[2, :])
    twin = ax.twinx()
    for policy, colour in (("expert", "tab:blue"), ("random", "tab:grey")):
        ep = result[policy]
        ax.plot(ep["r_gc"], color=colour, lw=1, label=f"r_gc, {policy}")
        twin.plot(ep["distance"], color=colour, lw=1, ls="--", label=f"distance, {policy}")
        hit = np.flatnonzero(ep["success"])
        if len(hit):
            ax.axvline(hit[0], color=colour, lw=0.8, ls=":")
    ax.set_xlabel("step of the episode (dotted: first success)")
    ax.set_ylabel("raw r_gc (eq 13)")
    twin.set_ylabel('info["distance"] (dashed)')
    ax.legend(loc="upper left", fontsize=7)
    twin.legend(loc="upper right", fontsize=7)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model", required=True, help="a PPO_GoCu model or checkpoint zip trained on --env")
    p.add_argument("--env", default="GoCu/VisualSawyerDoorHook-v1")
    p.add_argument("--seed", type=int, default=0, help="the episodes' goal (env.reset(seed=...), the same for both) and the goals drawn")
    p.add_argument("--max-steps", type=int, default=None, help="stop each episode after this many steps (default: its length)")
    p.add_argument("--out", default="sawyer_curiosity", help="output folder")
    args = p.parse_args(argv)
    model = PPO_GoCu.load(args.model, device="cpu")
    result = sawyer_curiosity(model, args.env, args.seed, args.max_steps)
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    title = f"{args.env}, {pathlib.Path(args.model).name} at {model.num_timesteps:,} steps, seed {args.seed}"
    draw(result, title, out / "sawyer_curiosity.png")
    np.savez_compressed(out / "sawyer_curiosity.npz", goals=result["goals"], shown_steps=result["shown_steps"],
                        **{f"{pol}_{k}": v for pol in ("expert", "random") for k, v in result[pol].items()})
    for policy in ("expert", "random"):
        ep = result[policy]
        first = np.flatnonzero(ep["success"])
        n = len(ep["r_gc"])
        print(f"{policy}: {n - 1} steps, first success {first[0] if len(first) else 'none'}, final distance {ep['distance'][-1]:.3f}; "
              f"raw r_gc mean {ep['r_gc'].mean():.4f} (first half {ep['r_gc'][: n // 2].mean():.4f}, second half "
              f"{ep['r_gc'][n // 2 :].mean():.4f}), max mastery mean {ep['max_mastery'].mean():.3f}")
    print(f"wrote {out / 'sawyer_curiosity.png'} and {out / 'sawyer_curiosity.npz'}")
    return result


if __name__ == "__main__":
    main()
