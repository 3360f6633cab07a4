"""What does the work in GoCu? PPO_GoCu's defaults against variants that each take one part away.

    python benchmarks/ablations.py run --env GoCu/DoorKey-8x8-v0 --variants predictor_untrained constant_curiosity \\
        --seeds 0 1 2 3 4 5 6 --timesteps 800000 --jobs 2 --out benchmarks/out/ablations/doorkey8x8
    python benchmarks/ablations.py summary --out benchmarks/out/ablations/doorkey8x8 --timesteps 800000 \\
        --defaults benchmarks/results/doorkey8x8_vae_pixel_weighting

The variants (each a ``benchmarks/sample_efficiency.py`` command; everything not named is the defaults):

* ``predictor_trained``: the mastery predictor trained one epoch per update (``predictor_epochs=1``, the defaults);
* ``predictor_untrained``: the mastery predictor never trained (``predictor_epochs=0``): r_gc from its initial weights;
* ``constant_curiosity``: r_gc replaced by its running mean (``--constant-curiosity``, a benchmark-only switch), so
  only the revisit rule, the normalisation and the second value head remain;
* ``vae_untrained``: the VAE never trained (``vae_epochs=0, vae_update_epochs=0``): a fixed random encoder;
* ``revisit_none``: every visit pays r_gc (``revisit_decay="none"``, the paper's rule);
* ``one_value_head``: plain PPO (one value head) on ``GoCuVecEnvWrapper(mode="sum")`` (its default, centred sum) with ``GoCuCallback``.

``run`` executes the (variant, seed) runs, seed-major, ``--jobs`` at a time (one torch thread each), every run stopping once
it reaches a mean return of 0.9 (``--stop-at-threshold``), each resumable from its checkpoints by running the same
command again. ``summary`` prints and writes ``<out>/summary.md``: steps to 0.9 per seed, seeds solved, steps
summed (a seed not solved within ``--timesteps`` counted as ``--timesteps``), beside the defaults' runs (a folder of
``ppo_gocu_seed<S>.csv``), and ``<out>/curves.png``.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import shlex
import subprocess
import sys
import time
from typing import Any, Sequence

HERE = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import sample_efficiency as se  # noqa: E402

#: variant -> the sample_efficiency.py arguments that make it
VARIANTS: dict[str, list[str]] = {
    "predictor_trained": ["--algos", "ppo_gocu", "--curiosity-kwargs", json.dumps({"predictor_epochs": 1})],
    "predictor_untrained": ["--algos", "ppo_gocu", "--curiosity-kwargs", json.dumps({"predictor_epochs": 0})],
    "constant_curiosity": ["--algos", "ppo_gocu", "--constant-curiosity"],
    "vae_untrained": ["--algos", "ppo_gocu", "--curiosity-kwargs", json.dumps({"vae_epochs": 0, "vae_update_epochs": 0})],
    "revisit_none": ["--algos", "ppo_gocu", "--curiosity-kwargs", json.dumps({"revisit_decay": "none"})],
    "one_value_head": ["--algos", "ppo_sum"],
}


def command(variant: str, env: str, seed: int, timesteps: int, out: pathlib.Path) -> list[str]:
    return [
        sys.executable, str(HERE / "sample_efficiency.py"), "--env", env, "--seeds", str(seed), "--timesteps", str(timesteps),
        "--threads", "1", "--checkpoint-freq", "200000", "--stop-at-threshold", "--out", str(out / variant), *VARIANTS[variant],
    ]


def run(args: argparse.Namespace) -> None:
    """Every (variant, seed) run, seed-major (so the variants' partial results pair up), ``--jobs`` at a time."""
    out = pathlib.Path(args.out)
    queue = [(v, s) for s in args.seeds for v in args.variants]
    running: list[tuple[subprocess.Popen, Any]] = []
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    while queue or running:
        while queue and len(running) < args.jobs:
            variant, seed = queue.pop(0)
            cmd = command(variant, args.env, seed, args.timesteps, out)
            (out / variant).mkdir(parents=True, exist_ok=True)
            log = open(out / variant / f"log_seed{seed}.txt", "a")
            log.write(f"$ python benchmarks/sample_efficiency.py {shlex.join(cmd[2:])}\n")
            log.flush()
            print(f"start {variant} seed {seed}", flush=True)
            running.append((subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env), log))
        time.sleep(5)
        for proc, log in list(running):
            if proc.poll() is not None:
                log.close()
                running.remove((proc, log))
                print(f"done ({proc.returncode}): {' '.join(proc.args[-6:])}", flush=True)


def steps_to(rows: Sequence[dict[str, Any]], timesteps: int) -> int | None:
    """Steps to a mean return of 0.9 within ``timesteps`` (None: not reached)."""
    return se.steps_to_threshold([r for r in rows if r["steps"] <= timesteps], 0.9, 100)


def arms(out: pathlib.Path, defaults: pathlib.Path | None) -> dict[str, dict[int, list[dict[str, Any]]]]:
    """arm -> seed -> CSV rows, the defaults first, then the variants in :data:`VARIANTS` order."""
    found: dict[str, dict[int, list[dict[str, Any]]]] = {}
    # a variant folder given as the defaults (``--defaults <out>/predictor_trained``) is read once, as the defaults
    folders = ([("defaults", defaults)] if defaults else []) + [
        (v, out / v) for v in VARIANTS if defaults is None or (out / v).resolve() != defaults.resolve()]
    for name, folder in folders:
        # the defaults' folder may hold plain PPO's runs beside PPO_GoCu's; a variant's folder holds one algorithm's
        for path in sorted(folder.glob("ppo_gocu_seed*.csv" if name == "defaults" else "*_seed*.csv")):
            seed = int(path.stem.rsplit("_seed", 1)[1])
            rows = se.read_csv(path)
            if rows:
                found.setdefault(name, {})[seed] = rows
    return found


def summary(args: argparse.Namespace) -> str:
    out, budget = pathlib.Path(args.out), args.timesteps
    data = arms(out, pathlib.Path(args.defaults) if args.defaults else None)
    seeds = sorted({s for runs in data.values() for s in runs})
    lines = [
        "| arm | " + " | ".join(f"seed {s}" for s in seeds) + " | solved | steps summed | against the defaults |",
        "| --- |" + " --- |" * (len(seeds) + 3),
    ]
    base: dict[int, int] = {}  # the defaults' steps (a miss at the budget) per finished seed
    for name, runs in data.items():
        cells, counted, solved, complete = [], {}, 0, True
        for s in seeds:
            if s not in runs:
                cells.append("-")
                complete = False
                continue
            reached = steps_to(runs[s], budget)
            if reached is None and runs[s][-1]["steps"] < budget:
                cells.append(f"running ({runs[s][-1]['steps']:,})")
                complete = False
                continue
            solved += reached is not None
            counted[s] = budget if reached is None else reached
            cells.append(f"{reached:,}" if reached is not None else "not")
        total = sum(counted.values())
        summed = f"{total:,}" if complete else f"({total:,} so far)"
        if name == "defaults":
            base = counted
        shared = [s for s in counted if s in base]
        ratio = ""
        if name != "defaults" and shared:  # on the seeds both have finished
            ratio = f"{(sum(counted[s] for s in shared) / sum(base[s] for s in shared) - 1) * 100:+.1f}% steps"
            if not complete or len(shared) < len(seeds):
                ratio += " on seed" + ("s " if len(shared) > 1 else " ") + ", ".join(map(str, shared))
        lines.append(f"| {name} | " + " | ".join(cells) + f" | {solved} of {len(counted)} | {summed} | {ratio} |")
    text = "\n".join(
        [
            f"# Ablations: {args.env}, {budget:,} steps",
            "",
            *lines,
            "",
            f"Steps to a mean return of 0.9 over the last 100 episodes (first rollout end; \"not\": not within {budget:,}, "
            "counted as the budget in the sum; against the defaults: on the seeds both have finished). Every run stops once it "
            "reaches 0.9. Defaults: "
            f"`{args.defaults}`. Runs: `python benchmarks/ablations.py run --env {args.env} --timesteps {budget} ...`.",
            f"Machine: {se.machine_line(1)}.",
            "",
        ]
    )
    se.atomic_write_bytes(out / "summary.md", text.encode())
    print(text)
    plot(data, budget, out / "curves.png", args.env)
    return text


def plot(data: dict[str, dict[int, list[dict[str, Any]]]], budget: int, path: pathlib.Path, env: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(data), figsize=(3.2 * len(data), 3.0), sharey=True, squeeze=False)
    for ax, (name, runs) in zip(axes[0], data.items()):
        for seed, rows in sorted(runs.items()):
            rows = [r for r in rows if r["steps"] <= budget]
            ax.plot([r["steps"] / 1e6 for r in rows], [r["mean_return"] for r in rows], lw=1, label=f"seed {seed}")
        ax.axhline(0.9, color="grey", lw=0.5, ls="--")
        ax.set_title(name, fontsize=9)
        ax.set_xlabel("env steps (M)")
        ax.set_xlim(0, budget / 1e6)
    axes[0][0].set_ylabel("mean return, last 100 episodes")
    axes[0][0].legend(fontsize=6)
    fig.suptitle(env, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: Sequence[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("action", choices=("run", "summary"))
    p.add_argument("--env", default="GoCu/DoorKey-8x8-v0")
    p.add_argument("--variants", nargs="+", choices=list(VARIANTS), default=list(VARIANTS))
    p.add_argument("--seeds", nargs="+", type=int, default=list(range(7)))
    p.add_argument("--timesteps", type=int, default=800_000)
    p.add_argument("--jobs", type=int, default=2, help="runs at once (one torch thread each)")
    p.add_argument("--out", required=True)
    p.add_argument("--defaults", default=None, help="folder of the defaults' ppo_gocu_seed<S>.csv runs")
    args = p.parse_args(argv)
    run(args) if args.action == "run" else summary(args)


if __name__ == "__main__":
    main()
