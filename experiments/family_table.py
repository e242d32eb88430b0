"""Collision / off-road rates of finished rollouts per synthetic map family.

  python -m experiments.family_table runs/t4/val50-v4r6-ensA30 runs/t4/val50-idm

Reads each run's scenarios.jsonl (`experiments.rollout --out RUN`) and weights
each scenario's rates by its evaluated agents; the family is the second field
of a synthetic scenario id (`syn-<family>-...`), "womd" for a real one.
"""
from __future__ import annotations

import argparse
import json
import os
import sys


def family_of(scenario_id: str) -> str:
  return scenario_id.split("-")[1] if scenario_id.startswith("syn-") else "womd"


def rates_by_family(path: str) -> dict[str, tuple[float, float, int]]:
  """{family: (collision %, off-road %, evaluated agents)} of one scenarios.jsonl."""
  sums: dict[str, list[float]] = {}
  with open(path) as f:
    for number, line in enumerate(f, 1):
      try:
        row = json.loads(line)
        n = float(row["num_evaluated"])
        coll, off = float(row["collision_rate"]), float(row["offroad_rate"])
        fam = family_of(row["scenario_id"])
      except (ValueError, KeyError, TypeError) as err:
        raise ValueError(f"{path}, line {number}: not a scenario row ({err})") from err
      acc = sums.setdefault(fam, [0.0, 0.0, 0.0])
      acc[0] += n
      acc[1] += coll * n
      acc[2] += off * n
  return {fam: (100 * c / max(n, 1.0), 100 * o / max(n, 1.0), int(n)) for fam, (n, c, o) in sorted(sums.items())}


def main(argv=None) -> int:
  p = argparse.ArgumentParser(prog="python -m experiments.family_table", description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("runs", nargs="+", help="output folders of experiments.rollout")
  args = p.parse_args(argv)
  try:
    tables = {run: rates_by_family(os.path.join(run, "scenarios.jsonl")) for run in args.runs}
  except (OSError, ValueError) as err:
    print(f"error: {err}", file=sys.stderr)
    return 2
  families = sorted({fam for t in tables.values() for fam in t})
  print("| run | " + " | ".join(families) + " |")
  print("|---|" + "---|" * len(families))
  for run, table in tables.items():
    cells = [f"{table[f][0]:.1f} / {table[f][1]:.1f}" if f in table else "-" for f in families]
    print(f"| {run} | " + " | ".join(cells) + " |")
  print("\ncells: collision % / off-road %, weighted by evaluated agents")
  return 0


if __name__ == "__main__":
  sys.exit(main())
