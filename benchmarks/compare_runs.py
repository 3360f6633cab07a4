"""Whether two per-run CSVs of ``sample_efficiency.py`` agree row for row (all but the wall-time columns).

    python benchmarks/compare_runs.py benchmarks/results/doorkey8x8_vae_patience1/variants/ppo_gocu_seed0_uninterrupted_to_497k.csv \
        <dir>/ppo_gocu_seed0.csv

A rerun of a recorded seed with the same settings should give the same rows exactly (the seed alone decides a
run): this checks it over the rows both files hold, as printed to the CSV's precision. Exit status 1 if a row
differs.
"""

from __future__ import annotations

import argparse
import csv
import sys

COLUMNS = ("steps", "episodes", "window_episodes", "mean_return", "success_rate", "key_rate", "door_rate",
           "intrinsic_mean", "intrinsic_std", "intrinsic_norm_mean", "goals")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("a")
    parser.add_argument("b")
    args = parser.parse_args(argv)
    with open(args.a, newline="") as fa, open(args.b, newline="") as fb:
        a, b = list(csv.DictReader(fa)), list(csv.DictReader(fb))
    n = min(len(a), len(b))
    if n == 0:
        sys.exit("no rows to compare")
    differing = [i for i in range(n) if any(a[i].get(c) != b[i].get(c) for c in COLUMNS)]
    print(f"rows compared: {n} (to {a[n - 1]['steps']} steps); rows differing: {len(differing)}")
    if differing:
        i = differing[0]
        print(f"first at {a[i]['steps']} steps: " + ", ".join(f"{c} {a[i][c]} vs {b[i][c]}" for c in COLUMNS if a[i][c] != b[i][c]))
        sys.exit(1)


if __name__ == "__main__":
    main()
