"""Learning curves from the CSVs of ``benchmarks/sample_efficiency.py``: PPO and PPO_GoCu on one figure.

    python benchmarks/plot_curves.py benchmarks/out/doorkey8                      # -> benchmarks/out/doorkey8/curves.png
    python benchmarks/plot_curves.py benchmarks/out/doorkey8 --band std --metric success_rate --out sr.png
    python benchmarks/plot_curves.py benchmarks/out/doorkey16 --per-seed      # runs of different lengths
    python benchmarks/plot_curves.py runs/gocu runs/ppo --out curves.png       # the runs of several folders
    python benchmarks/plot_curves.py random=runs/random late=runs/late --seeds 0 1 2   # folders as named arms

x = env steps, y = mean extrinsic return of the last 100 episodes (``--metric`` picks another CSV column). For
each algo: the mean over seeds and a band (``--band minmax``: min to max over seeds, the default; ``std``:
mean +- std). Seeds are put on a common step grid by linear interpolation; at a step that some seed has not
reached yet (a run still going), only the seeds that reached it count, so the tail of a curve may rest on
fewer seeds (the legend gives the number of seeds); with ``--per-seed`` each seed's own curve is drawn too and
the mean and band stop where the shortest run stops, and labels that would overlap are moved apart (a thin line
joins a moved label to its curve's end). Rows before a run's first finished episode are skipped. Several folders
can be drawn on one figure (runs of one env made on different days or machines); a seed of one algo in two of them
is refused. ``NAME=FOLDER`` draws a folder's runs as the arm ``NAME`` (an experiment whose arms differ in a setting:
every run of the folder, whatever its algo, is that arm); ``--seeds`` keeps only those seeds.
"""

from __future__ import annotations

import argparse
import csv
import json
import pathlib
import re
from typing import Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

LABELS = {"ppo": "PPO", "ppo_gocu": "PPO + GoCu"}
COLORS = {"ppo": "tab:blue", "ppo_gocu": "tab:red"}
YLABELS = {
    "mean_return": "mean extrinsic return (last 100 episodes)",
    "success_rate": "success rate (last 100 episodes)",
    "intrinsic_mean": "mean raw intrinsic reward r_gc",
}


Runs = dict[str, dict[int, tuple[np.ndarray, np.ndarray]]]


def load_runs(directory: pathlib.Path, metric: str) -> Runs:
    """{algo: {seed: (steps, values)}} of the ``<algo>_seed<seed>.csv`` files in ``directory``."""
    runs: Runs = {}
    for path in sorted(directory.glob("*_seed*.csv")):
        m = re.fullmatch(r"(.+)_seed(\d+)\.csv", path.name)
        if not m:
            continue
        steps, values = [], []
        with open(path, newline="") as f:
            for row in csv.DictReader(f):
                if row.get(metric, "") in ("", "nan"):
                    continue
                steps.append(float(row["steps"]))
                values.append(float(row[metric]))
        if steps:
            runs.setdefault(m.group(1), {})[int(m.group(2))] = (np.asarray(steps), np.asarray(values))
    return runs


def load_folders(directories: Sequence[pathlib.Path], metric: str, names: Sequence[str | None] = (),
                 seeds: Sequence[int] | None = None) -> Runs:
    """:func:`load_runs` of each folder, merged; a seed of one algo in two folders raises ``ValueError``.

    :param names: per folder, the arm its runs are drawn as (None: their algo)
    :param seeds: keep only these seeds (None: all)
    """
    runs: Runs = {}
    where: dict[tuple[str, int], pathlib.Path] = {}
    for directory, name in zip(directories, [*names, *[None] * (len(directories) - len(names))]):
        for algo, by_seed in load_runs(directory, metric).items():
            algo = name or algo
            for seed, curve in by_seed.items():
                if seeds is not None and seed not in seeds:
                    continue
                if (algo, seed) in where:
                    raise ValueError(f"{algo} seed {seed} is in both {where[algo, seed]} and {directory}: pass one of them")
                where[algo, seed] = directory
                runs.setdefault(algo, {})[seed] = curve
    return runs


def spread_labels(points: Sequence[tuple[float, float]], width: float, height: float) -> list[float]:
    """Heights for labels anchored at ``points`` (x, y in axes fractions; a label spans x to x + ``width`` and y
    +- ``height`` / 2) such that no two overlap and all stay inside the axes: labels that would overlap are
    stacked ``height`` apart, in the order of their anchors' y, centred on their anchors' mean (moved in as a whole
    where the stack would leave the axes). Returns the labels' y, in the order of ``points``."""
    if width <= 0 or height <= 0:
        raise ValueError(f"width and height must be > 0, got {width} and {height}")
    order = sorted(range(len(points)), key=lambda j: (points[j][1], points[j][0]))
    clusters = [[i] for i in order]
    ys = [0.0] * len(points)
    while True:
        for members in clusters:
            members.sort(key=lambda j: (points[j][1], points[j][0]))
            n = len(members)
            low = float(np.mean([points[j][1] for j in members])) - (n - 1) * height / 2
            top = 1 - height / 2 - (n - 1) * height  # the lowest label's highest place
            low = max(min(low, top), height / 2)  # inside the axes; a stack taller than them starts at the bottom
            for k, j in enumerate(members):
                ys[j] = low + k * height
        clash = next(((a, b) for a in range(len(clusters)) for b in range(a + 1, len(clusters))
                      if any(abs(points[i][0] - points[j][0]) < width and abs(ys[i] - ys[j]) < height - 1e-12
                             for i in clusters[a] for j in clusters[b])), None)
        if clash is None:
            return ys
        a, b = clash
        clusters[a] += clusters.pop(b)


def aggregate(seed_curves: Sequence[tuple[np.ndarray, np.ndarray]], band: str, n_points: int = 400) -> tuple[np.ndarray, ...]:
    """Common grid x, mean, band low, band high, and the number of seeds at each x."""
    start = min(s[0] for s, _ in seed_curves)
    stop = max(s[-1] for s, _ in seed_curves)
    grid = np.unique(np.concatenate([s for s, _ in seed_curves]))
    if len(grid) > n_points:
        grid = np.linspace(start, stop, n_points)
    ys = np.full((len(seed_curves), len(grid)), np.nan)
    for i, (s, v) in enumerate(seed_curves):
        inside = (grid >= s[0]) & (grid <= s[-1])
        ys[i, inside] = np.interp(grid[inside], s, v)
    count = np.isfinite(ys).sum(0)
    keep = count > 0
    grid, ys, count = grid[keep], ys[:, keep], count[keep]
    with np.errstate(all="ignore"):
        mean = np.nanmean(ys, 0)
        if band == "std":
            sd = np.nanstd(ys, 0)
            lo, hi = mean - sd, mean + sd
        else:
            lo, hi = np.nanmin(ys, 0), np.nanmax(ys, 0)
    return grid, mean, lo, hi, count


def env_name(directory: pathlib.Path) -> str | None:
    """The env id of a ``sample_efficiency.py`` folder: from its checkpoints' state, else its summary's heading."""
    for state in sorted((directory / "checkpoints").glob("*/state_*.json")):
        try:
            return json.loads(state.read_text())["config"]["env"]
        except (OSError, ValueError, KeyError):
            continue
    summary = directory / "summary.md"  # a results folder keeps the summary, not the checkpoints
    if summary.is_file():
        # the heading sample_efficiency.py's write_summary gives it; an env id ends in -v<version>
        m = re.match(r"# Sample efficiency: (\S+-v\d+)\s*$", summary.read_text().split("\n", 1)[0])
        if m:
            return m.group(1)
    return None


def mean_curve(seed_curves: Sequence[tuple[np.ndarray, np.ndarray]], band: str, all_seeds: bool = False) -> tuple[np.ndarray, ...]:
    """x, mean, band low, band high over the seeds; ``all_seeds``: only where every seed has data (a run stopped
    early, e.g. once solved, does not pull the mean towards the runs still going)."""
    x, mean, lo, hi, count = aggregate(seed_curves, band)
    if all_seeds:
        full = count == len(seed_curves)
        x, mean, lo, hi = x[full], mean[full], lo[full], hi[full]
    return x, mean, lo, hi


def plot(directory: str | pathlib.Path | Sequence[str | pathlib.Path], out: str | pathlib.Path | None = None, metric: str = "mean_return",
         band: str = "minmax", title: str | None = None, threshold: float | None = 0.9, per_seed: bool = False,
         seeds: Sequence[int] | None = None) -> pathlib.Path:
    """Draw the curves of the runs in ``directory`` (one folder or several; ``NAME=FOLDER``: the folder's runs as the
    arm ``NAME``) and save a PNG; ``per_seed``: also each seed's own curve (thin, labelled at its end), with the mean
    and band drawn only where every seed has data; ``seeds``: only these seeds.
    :return: the PNG's path (default: ``curves.png`` in the first folder)"""
    given = [directory] if isinstance(directory, (str, pathlib.Path)) else list(directory)
    if not given:
        raise ValueError("directory: give at least one folder")
    names = [str(d).split("=", 1)[0] if "=" in str(d) else None for d in given]
    folders = [pathlib.Path(str(d).split("=", 1)[1] if "=" in str(d) else d) for d in given]
    try:
        runs = load_folders(folders, metric, names, seeds)
    except ValueError as e:
        raise SystemExit(str(e)) from None
    if not runs:
        raise SystemExit(f"no <algo>_seed<seed>.csv with a '{metric}' column in {', '.join(map(str, folders))}")
    envs = {env for env in map(env_name, folders) if env is not None}
    if len(envs) > 1:
        raise SystemExit(f"the folders hold runs of different envs ({', '.join(sorted(envs))}): plot them apart")
    out = pathlib.Path(out) if out is not None else folders[0] / ("curves.png" if metric == "mean_return" else f"curves_{metric}.png")
    fig, ax = plt.subplots(figsize=(7, 4.5), dpi=120)
    order = [a for a in LABELS if a in runs] + sorted(a for a in runs if a not in LABELS)
    ends: list[tuple[str, float, float, str]] = []  # per seed: label, end x, end y, colour
    for algo in order:
        seeds = sorted(runs[algo])
        x, mean, lo, hi = mean_curve([runs[algo][s] for s in seeds], band, all_seeds=per_seed)
        color = COLORS.get(algo)
        label = f"{LABELS.get(algo, algo)} ({len(seeds)} seed{'s' if len(seeds) > 1 else ''})"
        (line,) = ax.plot(x, mean, color=color, lw=1.8, label=label)
        ax.fill_between(x, lo, hi, color=line.get_color(), alpha=0.2, lw=0)
        if per_seed:
            for seed in seeds:
                sx, sy = runs[algo][seed]
                ax.plot(sx, sy, color=line.get_color(), lw=0.7, alpha=0.7)
                ends.append((f"seed {seed}", float(sx[-1]), float(sy[-1]), line.get_color()))
    if threshold is not None and metric == "mean_return":
        ax.axhline(threshold, color="grey", ls=":", lw=1)
    ax.set_xlabel("environment steps")
    ax.set_ylabel(YLABELS.get(metric, metric))
    what = f"mean over seeds, band = {'min-max' if band == 'minmax' else '+- std'}"
    if per_seed:
        what = f"thin: each seed; thick: {what}, where every seed ran"
    # per seed, the longer caption goes on a line of its own (one line would be cut at the figure's edge)
    sep = "\n" if per_seed else ": "
    ax.set_title(title or f"{next(iter(envs), None) or folders[0].name}{sep}{what}", fontsize=10 if per_seed else None)
    ax.ticklabel_format(axis="x", style="sci", scilimits=(0, 0))
    ax.grid(alpha=0.3)
    ax.legend(loc="center right" if per_seed else "upper left")
    if per_seed:
        ax.margins(x=0.1)  # room for the seed labels
        ax.autoscale_view()
        (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
        anchors = [((ex - x0) / (x1 - x0), (ey - y0) / (y1 - y0)) for _, ex, ey, _ in ends]
        # a 7-point label "seed N" is about 0.07 of the axes wide and 0.035 high at this figure size
        heights = spread_labels(anchors, width=0.08, height=0.04)
        for (text, ex, ey, color), (ax_x, ax_y), y in zip(ends, anchors, heights):
            moved = abs(y - ax_y) > 1e-9
            ax.annotate(text, (ex, ey), xytext=(ax_x + 0.005, y), textcoords="axes fraction", fontsize=7, color=color,
                        va="center", arrowprops=dict(arrowstyle="-", color=color, lw=0.5, alpha=0.7) if moved else None)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    plt.close(fig)
    return out


def main(argv: Sequence[str] | None = None) -> pathlib.Path:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("directory", nargs="+", help="the --out dir of sample_efficiency.py (several: their runs on one figure)")
    p.add_argument("--out", default=None, help="PNG path (default <first directory>/curves.png)")
    p.add_argument("--metric", default="mean_return", help="CSV column on the y axis (mean_return, success_rate, intrinsic_mean, ...)")
    p.add_argument("--band", choices=["minmax", "std"], default="minmax")
    p.add_argument("--title", default=None)
    p.add_argument("--threshold", default="0.9", type=lambda v: None if v.lower() == "none" else float(v),
                   help="dotted line at this return (the success threshold of the DoorKey runs; 'none': no line, as on Atari)")
    p.add_argument("--per-seed", action="store_true", help="also draw each seed's curve; mean and band only where every seed ran")
    p.add_argument("--seeds", nargs="+", type=int, default=None, help="only these seeds (default: all)")
    args = p.parse_args(argv)
    path = plot(args.directory, args.out, args.metric, args.band, args.title, args.threshold, per_seed=args.per_seed,
                seeds=args.seeds)
    print(f"wrote {path}")
    return path


if __name__ == "__main__":
    main()
