"""What a run of ``sample_efficiency.py`` writes and what is read back from it: its CSV, its checkpoints, the summary.

Shared by ``sample_efficiency.py`` (which re-exports these names), ``ablations.py`` and the probes.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import pathlib
import platform
import re
import zipfile
from typing import Any, Sequence

import numpy as np
import torch as th

from sb3_gocu.checkpoints import atomic_write

#: a run's CSV columns (their meaning: ``sample_efficiency.py``'s docstring)
COLUMNS = (
    "algo", "seed", "steps", "episodes", "window_episodes", "mean_return", "success_rate", "key_rate", "door_rate",
    "final_distance", "final_success", "max_return", "rooms_mean", "rooms_total",
    "intrinsic_mean", "intrinsic_std", "intrinsic_norm_mean", "goals", "predictor_auc_far", "predictor_auc_goals", "wall_time_s", "fps",
)


def atomic_write_bytes(path: pathlib.Path, data: bytes) -> None:
    """Write ``data`` to ``path`` all at once or not at all (:func:`sb3_gocu.checkpoints.atomic_write`)."""
    atomic_write(path, lambda f: f.write(data))


def csv_bytes(rows: Sequence[dict[str, Any]]) -> bytes:
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=COLUMNS, lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: _fmt(row.get(k)) for k in COLUMNS})
    return buf.getvalue().encode()


def _fmt(v: Any) -> Any:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return ""
    if isinstance(v, float):
        return f"{v:.6g}"
    return v


def read_csv(path: pathlib.Path) -> list[dict[str, Any]]:
    """Rows of a run's CSV with numbers parsed (empty cells -> nan)."""
    rows = []
    with open(path, newline="") as f:
        for raw in csv.DictReader(f):
            row: dict[str, Any] = {}
            for k, v in raw.items():
                if k == "algo":
                    row[k] = v
                elif k in ("seed", "steps", "episodes", "window_episodes"):
                    row[k] = int(float(v)) if v != "" else 0
                else:
                    row[k] = float(v) if v != "" else float("nan")
            rows.append(row)
    return rows


def run_name(algo: str, seed: int) -> str:
    return f"{algo}_seed{seed}"


def model_readable(path: pathlib.Path) -> bool:
    """Whether a model zip exists and every member passes its CRC check."""
    try:
        with zipfile.ZipFile(path) as archive:
            return archive.testzip() is None and "data" in archive.namelist()
    except (OSError, zipfile.BadZipFile, EOFError, ValueError):
        return False


def list_checkpoints(ckpt_dir: pathlib.Path) -> list[tuple[int, pathlib.Path]]:
    """(steps, state file) of a run's checkpoints, oldest first."""
    out = []
    if ckpt_dir.is_dir():
        for f in ckpt_dir.glob("state_*.json"):
            m = re.fullmatch(r"state_(\d+)\.json", f.name)
            if m:
                out.append((int(m.group(1)), f))
    return sorted(out)


# ---------------------------------------------------------------------------------------------- summary
def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo``; else what ``platform`` knows)."""
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or ""


def machine_line(threads: int) -> str:
    cpu = cpu_model()
    return (
        f"{platform.machine()} {cpu}, {os.cpu_count()} CPUs, Python {platform.python_version()}, torch {th.__version__}, "
        f"torch threads {threads}"
    )


def steps_to_threshold(rows: Sequence[dict[str, Any]], threshold: float, min_window: int) -> int | None:
    """First rollout-end step where the windowed mean return is >= threshold (window holding >= min_window episodes)."""
    for r in rows:
        if r["window_episodes"] >= min_window and r["mean_return"] >= threshold:
            return int(r["steps"])
    return None


def wall_time_to_threshold(rows: Sequence[dict[str, Any]], threshold: float, min_window: int) -> float | None:
    """Training wall time (s) at the row of :func:`steps_to_threshold` (None if the run never reached it)."""
    steps = steps_to_threshold(rows, threshold, min_window)
    return None if steps is None else float(next(r["wall_time_s"] for r in rows if int(r["steps"]) == steps))


def best_mean_return(rows: Sequence[dict[str, Any]], min_window: int) -> float:
    """The best windowed mean return of a run (rows whose window holds >= min_window episodes; nan if none does)."""
    means = [r["mean_return"] for r in rows if r["window_episodes"] >= min_window]
    return max(means) if means else float("nan")


def _pm(values: Sequence[float], fmt: str) -> str:
    v = np.asarray(values, dtype=np.float64)
    if len(v) == 0 or np.isnan(v).all():
        return "-"
    return f"{format(v.mean(), fmt)} +- {format(v.std(), fmt)}"


def summarize(
    out: pathlib.Path, threshold: float, min_window: int, order: Sequence[str] = (), atari: bool = False
) -> tuple[str, dict[str, Any]]:
    """Summary table of the CSVs in ``out`` (markdown) and the figures behind it.

    :param order: algorithms in the order their rows come first (the others follow, sorted)
    :param atari: add Table 3's measures: the best windowed mean return, the best episode return and, where the env
        reports rooms (``info["room"]``), the rooms per episode and in total
    """
    runs: dict[str, dict[int, list[dict[str, Any]]]] = {}
    for path in sorted(out.glob("*_seed*.csv")):
        m = re.fullmatch(r"(.+)_seed(\d+)\.csv", path.name)
        if not m:
            continue
        rows = read_csv(path)
        if rows:
            runs.setdefault(m.group(1), {})[int(m.group(2))] = rows
    order = [a for a in order if a in runs] + sorted(a for a in runs if a not in order)
    # Table 2's measure, where the env reports it: the last 100 episodes' final distance and final success
    finals = any(math.isfinite(r[-1].get("final_distance", float("nan"))) for a in runs.values() for r in a.values())
    lines = [
        f"| algo | seeds | final steps | steps to mean return >= {threshold} | wall time to it (min) | final success rate |"
        " final mean return | wall time (min) |"
        + (" final distance | success at the last step |" if finals else "")
        + (" best mean return | best episode return | rooms per episode (last 100) | rooms visited |" if atari else ""),
        "| --- | --- | --- | --- | --- | --- | --- | --- |" + (" --- | --- |" if finals else "") + (" --- | --- | --- | --- |" if atari else ""),
    ]
    figures: dict[str, Any] = {}
    for algo in order:
        seeds = sorted(runs[algo])
        per_seed = {s: runs[algo][s] for s in seeds}
        reached = {s: steps_to_threshold(r, threshold, min_window) for s, r in per_seed.items()}
        hit = [v for v in reached.values() if v is not None]
        minutes = [t / 60 for t in (wall_time_to_threshold(r, threshold, min_window) for r in per_seed.values()) if t is not None]
        final = [r[-1] for r in per_seed.values()]
        if not hit:
            to_thr = "not reached"
        else:
            to_thr = f"{_pm(hit, ',.0f')} ({len(hit)}/{len(seeds)} seeds reached)"
            if len(hit) < len(seeds):
                to_thr += "; " + ", ".join(f"seed {s}: not reached" for s, v in reached.items() if v is None)
        final_steps = sorted({int(r['steps']) for r in final})
        lines.append(
            f"| {algo} | {', '.join(map(str, seeds))} | {', '.join(f'{s:,}' for s in final_steps)} | {to_thr} | {_pm(minutes, '.1f')} | "
            f"{_pm([r['success_rate'] for r in final], '.3f')} | {_pm([r['mean_return'] for r in final], '.3f')} | "
            f"{_pm([r['wall_time_s'] / 60 for r in final], '.1f')} |"
            + (f" {_pm([r.get('final_distance', float('nan')) for r in final], '.3f')} |"
               f" {_pm([r.get('final_success', float('nan')) for r in final], '.3f')} |" if finals else "")
            + (f" {_pm([best_mean_return(r, min_window) for r in per_seed.values()], '.1f')} |"
               f" {_pm([r.get('max_return', float('nan')) for r in final], '.1f')} |"
               f" {_pm([r.get('rooms_mean', float('nan')) for r in final], '.2f')} |"
               f" {_pm([r.get('rooms_total', float('nan')) for r in final], '.1f')} |" if atari else "")
        )
        figures[algo] = {
            "seeds": seeds,
            "steps_to_threshold": reached,
            "final_success_rate": [r["success_rate"] for r in final],
            "final_mean_return": [r["mean_return"] for r in final],
            "final_steps": [int(r["steps"]) for r in final],
            "final_distance": [r.get("final_distance", float("nan")) for r in final],
        }
    return "\n".join(lines), figures


def recorded(out: pathlib.Path) -> tuple[list[str], list[str], str | None]:
    """Commands and machines recorded in the runs' newest checkpoints, and their env id."""
    cmds: list[str] = []
    machines: list[str] = []
    env = None
    for d in sorted((out / "checkpoints").glob("*")):
        ckpts = list_checkpoints(d)
        if not ckpts:
            continue
        try:
            state = json.loads(ckpts[-1][1].read_text())
        except (OSError, ValueError):
            continue
        cmds += [c for c in state.get("commands", []) if c not in cmds]
        if state.get("machine") and state["machine"] not in machines:
            machines.append(state["machine"])
        env = env or state.get("config", {}).get("env")
    return cmds, machines, env
