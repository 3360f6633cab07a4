"""Does the embedding phi see what DoorKey is about? The carried key, the key on the floor and the open door,
against one step of the agent, for saved PPO_GoCu models.

    python benchmarks/probes/embedding_phases.py <run>/model_800768.zip [more.zip ...] --layouts 4 --threads 1 \\
        [--refit '{"vae_beta": 0.1}' '{"vae_beta": 0.0, "latent_dim": 32, "fresh": true}' ...]

GoCu pays a state for the goals the predictor thinks cannot be reached from it, and the predictor sees states and
goals only through phi (the VAE's 128-unit layer). What phi does not tell apart, the curiosity cannot pay for
apart. For each DoorKey layout (``env.reset(seed=i)``, i < ``--layouts``) this script renders the agent's 32x32 view
at every cell of the left room it can stand on, facing each of the 4 directions, in four states of the grid:

* ``bare``:      no key anywhere (neither on the floor nor carried), door locked;
* ``floor_key``: the key on its cell, not carried, door locked (as at the start of an episode);
* ``carried``:   the key carried, door locked (differs from ``bare`` only at the agent's own cell, where MiniGrid
  draws the carried object under the agent);
* ``door_open``: the key carried, door open (differs from ``carried`` only where the door is in view),

and measures, over the poses (cell, direction) where the two images differ at all,

* ``carried``:   median ||phi(carried) - phi(bare)||,
* ``floor_key``: median ||phi(floor_key) - phi(bare)||,
* ``door_open``: median ||phi(door_open) - phi(carried)||,

each divided by ``step``: the median ||phi(bare at a cell) - phi(bare at the next cell)|| (right or down, same
direction), i.e. how far one step of the agent moves phi. A ratio near 0 means phi does not see the change: the
states with and without it share their embedding, their mastery and their reward. The same ratios of the images
themselves (phi = the pixels in [0, 1]) are printed first: how large each change is on the screen.

``--refit JSON`` (one or more JSON dicts) also retrains the model's VAE on the model's memory bank, as a VAE update
in training does (de-duplicated, weighted by multiplicity), once per dict, and measures its phi the same way:
``vae_beta`` (beta of eq 8), ``vae_pixel_weighting`` (exponent of the rare-colour weighting), ``vae_epochs``
(default the module's), ``vae_patience`` (default 0: all epochs), ``latent_dim`` and ``fresh`` (start from new
random weights instead of the model's; implied by a ``latent_dim`` other than the model's). The model's own VAE is
left as it was.
"""

from __future__ import annotations

import dataclasses

import argparse
import json
import platform
import sys
import time
from pathlib import Path
from typing import Any, Callable, Sequence

import gymnasium as gym
import numpy as np
import torch as th

import sb3_gocu  # noqa: F401  (registers the GoCu ids)
from sb3_gocu.curiosity.training import Trainer
from sb3_gocu import PPO_GoCu

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "examples"))
import curiosity_map  # noqa: E402  (DoorKey objects, phases, flood fill and rendering of examples/curiosity_map.py)

STATES = ("bare", "floor_key", "carried", "door_open")
CHANGES = {"carried": ("carried", "bare"), "floor_key": ("floor_key", "bare"), "door_open": ("door_open", "carried")}
REFIT_KEYS = {"vae_beta", "vae_pixel_weighting", "vae_epochs", "vae_patience", "latent_dim", "fresh"}


def set_state(base: Any, state: str, objects: tuple) -> None:
    """Put the grid in one of :data:`STATES` (through :func:`curiosity_map.set_phase`)."""
    key, key_pos, door, _ = objects
    phase = {"bare": "key", "floor_key": "no_key", "carried": "key", "door_open": "door_open"}[state]
    curiosity_map.set_phase(base, phase, key, key_pos, door)
    if state == "bare":
        base.carrying = None


def layout_views(env_id: str, seed: int) -> dict[str, dict[tuple[int, int, int], np.ndarray]]:
    """The agent's view at every pose (x, y, direction) of the left room, per state; the key's own cell is left
    out (it cannot be stood on while the key lies there)."""
    env = gym.make(env_id)
    env.reset(seed=seed)
    base = env.unwrapped
    objects = curiosity_map.find_objects(base)
    key_pos, door_x = objects[1], objects[3][0]
    start = tuple(int(v) for v in base.agent_pos)
    set_state(base, "carried", objects)
    reach = curiosity_map.reachable_cells(base, start)
    cells = [(x, y) for y in range(base.height) for x in range(door_x) if reach[y, x] and (x, y) != key_pos]
    views: dict[str, dict[tuple[int, int, int], np.ndarray]] = {}
    for state in STATES:
        set_state(base, state, objects)
        obs = curiosity_map.observations_at(env, cells)
        views[state] = {(x, y, d): obs[i, d] for i, (x, y) in enumerate(cells) for d in range(curiosity_map.DIRECTIONS)}
    env.close()
    return views


def distances(views: dict[str, dict[tuple[int, int, int], np.ndarray]], features: Callable[[np.ndarray], np.ndarray]) -> dict[str, np.ndarray]:
    """Feature distances of each change in :data:`CHANGES` over the poses whose images differ, and of one step
    (``"step"``: bare at (x, y) against bare at (x + 1, y) and (x, y + 1), same direction).

    :param features: (n, H, W, C) uint8 images -> (n, D) features
    """
    poses = list(views["bare"])
    feats = {s: dict(zip(poses, features(np.stack([views[s][p] for p in poses])))) for s in STATES}
    out: dict[str, list[float]] = {name: [] for name in (*CHANGES, "step")}
    for name, (a, b) in CHANGES.items():
        for p in poses:
            if not np.array_equal(views[a][p], views[b][p]):
                out[name].append(float(np.linalg.norm(feats[a][p] - feats[b][p])))
    for x, y, d in poses:
        for nxt in ((x + 1, y, d), (x, y + 1, d)):
            if nxt in feats["bare"]:
                out["step"].append(float(np.linalg.norm(feats["bare"][nxt] - feats["bare"][(x, y, d)])))
    return {k: np.asarray(v) for k, v in out.items()}


def summarise(per_layout: list[dict[str, np.ndarray]]) -> dict[str, float]:
    """Medians over all layouts' poses, and each change's median over the step's median (``<change>/step``)."""
    med = {k: float(np.median(np.concatenate([d[k] for d in per_layout]))) for k in per_layout[0]}
    med.update({f"{k}/step": med[k] / med["step"] for k in CHANGES})
    med["poses"] = float(sum(len(d["step"]) for d in per_layout))
    return med


def pixels(images: np.ndarray) -> np.ndarray:
    return images.reshape(len(images), -1).astype(np.float32) / 255.0


def embedding(module: Any, encoder: th.nn.Module | None = None) -> Callable[[np.ndarray], np.ndarray]:
    """phi of (n, H, W, C) env images through ``encoder`` (default: the module's own)."""

    def features(images: np.ndarray) -> np.ndarray:
        return module.embed(curiosity_map.to_module_layout(images, module.adapter.raw_shape), encoder=encoder).numpy()

    return features


def check_refit(spec: Any) -> None:
    """A ``--refit`` setting is a dict with keys among :data:`REFIT_KEYS` (ValueError otherwise)."""
    if not isinstance(spec, dict):
        raise ValueError(f"--refit takes JSON dicts, got {spec!r}")
    unknown = set(spec) - REFIT_KEYS
    if unknown:
        raise ValueError(f"--refit keys must be among {sorted(REFIT_KEYS)}, got {sorted(unknown)}")


def refit_vae(module: Any, spec: dict[str, Any], seed: int = 0) -> tuple[th.nn.Module, dict[str, Any]]:
    """A VAE retrained on ``module``'s memory bank as a VAE update would (the module's :class:`Trainer`, its
    generators), with the settings of ``spec``; the module's own VAE and optimiser are left as they were.

    :return: the retrained VAE and the fit's record (``epochs_run``, ``time``, ``losses``, ...)
    """
    check_refit(spec)
    latent = int(spec.get("latent_dim", module.vae.mu.out_features))
    fresh = bool(spec.get("fresh", False)) or latent != module.vae.mu.out_features
    with th.random.fork_rng():
        th.manual_seed(seed)
        vae = type(module.vae)(module.adapter.input_shape, embed_dim=module.vae.fc.out_features, latent_dim=latent)
    if not fresh:
        vae.load_state_dict(module.vae.state_dict())
    config = dataclasses.replace(module.config, vae_beta=float(spec.get("vae_beta", module.vae_beta)))
    trainer = Trainer(vae, module.predictor, config, module.adapter, module.device, module.trainer.generator)
    pixel_weighting = float(spec.get("vae_pixel_weighting", module.vae_pixel_weighting))
    job = trainer.vae_job(module.memory.observations[: module.memory.size], module.rng, pixel_weighting, spec.get("vae_epochs"),
                          patience=int(spec.get("vae_patience", 0)))
    if job is None:
        raise ValueError("the model's memory bank is empty: nothing to retrain the VAE on")
    job.threads = None
    fit = trainer.fit_vae(job)
    return vae.eval().requires_grad_(False), dataclasses.asdict(fit)


def measure(model_path: str, env_id: str, layouts: int, refits: Sequence[dict[str, Any]], seed: int = 0) -> dict[str, Any]:
    """The pixel ratios, the model's phi ratios and each refit's, over ``layouts`` layouts."""
    model = PPO_GoCu.load(model_path, device="cpu")
    module = model.curiosity
    if module is None:
        raise ValueError(f"{model_path} has no curiosity module (not a PPO_GoCu model?)")
    views = [layout_views(env_id, i) for i in range(layouts)]
    out: dict[str, Any] = {
        "model": model_path,
        "steps": int(model.num_timesteps),
        "pixels": summarise([distances(v, pixels) for v in views]),
        "phi": summarise([distances(v, embedding(module)) for v in views]),
        "refits": [],
    }
    for spec in refits:
        vae, fit = refit_vae(module, spec, seed)
        row = summarise([distances(v, embedding(module, vae)) for v in views])
        out["refits"].append({"spec": spec, "epochs_run": fit["epochs_run"], "fit_s": fit["time"], **row})
    return out


def row(name: str, r: dict[str, float]) -> str:
    return (f"{name:<44} {r['step']:>7.3f} {r['carried']:>8.3f} {r['carried/step']:>6.3f} {r['floor_key']:>8.3f} "
            f"{r['floor_key/step']:>6.3f} {r['door_open']:>8.3f} {r['door_open/step']:>6.3f}")


def main(argv: Sequence[str] | None = None) -> list[dict[str, Any]]:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("models", nargs="+", help="PPO_GoCu model or checkpoint zips trained on a DoorKey id")
    p.add_argument("--env", default="GoCu/DoorKey-8x8-v0", help="DoorKey id the views are rendered in")
    p.add_argument("--layouts", type=int, default=4, help="layouts: env.reset(seed=0..layouts-1)")
    p.add_argument("--refit", nargs="*", default=[], metavar="JSON", help=f"VAE retraining settings, keys among {sorted(REFIT_KEYS)}")
    p.add_argument("--threads", type=int, default=1, help="torch.set_num_threads")
    p.add_argument("--seed", type=int, default=0, help="torch seed of fresh VAEs")
    p.add_argument("--json", default=None, help="also write the figures to this JSON file")
    args = p.parse_args(argv)
    if args.layouts < 1:
        p.error(f"--layouts must be >= 1, got {args.layouts}")
    try:
        refits = [json.loads(s) for s in args.refit]
    except json.JSONDecodeError as e:
        p.error(f"--refit takes JSON dicts: {e}")
    for spec in refits:
        try:
            check_refit(spec)
        except ValueError as e:
            p.error(str(e))
    th.set_num_threads(args.threads)
    print("command: python benchmarks/probes/embedding_phases.py " + " ".join(sys.argv[1:] if argv is None else argv))
    print(f"machine: {platform.machine()}, {th.get_num_threads()} torch threads, torch {th.__version__}; "
          f"{args.env}, layouts reset(seed=0..{args.layouts - 1})")
    results = []
    for path in args.models:
        t0 = time.perf_counter()
        r = measure(path, args.env, args.layouts, refits, args.seed)
        results.append(r)
        print(f"\n{path} ({r['steps']:,} steps; {int(r['pixels']['poses'])} one-step pairs)")
        print(f"{'median distance (ratio to one step)':<44} {'step':>7} {'carried':>8} {'':>6} {'floor key':>8} {'':>6} {'door':>8} {'':>6}")
        print(row("pixels in [0, 1]", r["pixels"]))
        print(row("phi, the model's VAE", r["phi"]))
        for f in r["refits"]:
            print(row(f"phi, refit {json.dumps(f['spec'])}", f) + f"   ({f['epochs_run']} epochs, {f['fit_s']:.0f} s)")
        print(f"({time.perf_counter() - t0:.0f} s)")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=1)
    return results


if __name__ == "__main__":
    main()
