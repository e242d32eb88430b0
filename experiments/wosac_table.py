"""The WOSAC table: export and score several methods on the same scenes.

  python -m experiments.wosac_table --scenarios ../shared/data/womd_real/val.scenario.tfrecord \
      --methods log cv idm-lane simpl-ar pcdiff pcdiff-guided --checkpoint checkpoints/pcdiff-cpu-v11 \
      --out runs/wosac/real_val

For each method: `python -m experiments.wosac --method M --out OUT/M.binproto`
(skipped when that file exists), then `--score` with Waymo's evaluator
(`make wosac-env`; skipped when OUT/M.wosac.json exists), then one markdown
row per method in OUT/table.md; OUT/M.export.json holds the export's CPU and
wall seconds (the whole process, compilation included). `log` is log replay (the logged future, 32
copies): the reference, never a valid submission. `idm` and `idm-lane` are the
same lane-following IDM (WOSAC may not read the logged route); `pcdiff-guided`
is ours with `--guidance objective`. Scoring costs 2-4 CPU-minutes per real
val scene and method, and up to 12.5 GB per worker (docs/WOSAC.md); it resumes
from its journal when run again. --max-scenarios N takes the first N scenes.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time

LEARNED = ("pcdiff", "pcdiff-noprior", "simpl-ar", "pcdiff-guided")
METHODS = ("log", "cv", "idm", "idm-lane") + LEARNED
# table names that are an export method with options (the rest are `--method NAME`)
VARIANTS = {"pcdiff-guided": ["--method", "pcdiff", "--guidance", "objective"]}


def main(argv=None) -> int:
  p = argparse.ArgumentParser(prog="python -m experiments.wosac_table", description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--scenarios", nargs="+", required=True)
  p.add_argument("--methods", nargs="+", default=["log", "cv", "pcdiff"], choices=METHODS)
  p.add_argument("--checkpoint", default=None, help="the learned methods' checkpoint")
  p.add_argument("--out", required=True, help="folder for the submissions, scores and table.md")
  p.add_argument("--max-scenarios", type=int, default=None)
  p.add_argument("--workers", type=int, default=2, help="evaluator processes")
  p.add_argument("--extra", default="", help="more options for the learned methods' export, e.g. '--guidance objective'")
  args = p.parse_args(argv)
  if any(m in LEARNED for m in args.methods) and not args.checkpoint:
    p.error("the learned methods need --checkpoint")
  os.makedirs(args.out, exist_ok=True)
  base = [sys.executable, "-m", "experiments.wosac", "--scenarios", *args.scenarios, "--no-progress"]
  limit = ["--max-scenarios", str(args.max_scenarios)] if args.max_scenarios else []
  from pcdiff_jax import wosac_scoring
  results = {}
  for method in args.methods:
    sub = os.path.join(args.out, f"{method}.binproto")
    if not os.path.exists(sub):
      cmd = base + VARIANTS.get(method, ["--method", method]) + ["--out", sub] + limit
      if method in LEARNED:
        cmd += ["--checkpoint", args.checkpoint] + args.extra.split()
      print("+", " ".join(cmd), flush=True)
      before, t0 = resource.getrusage(resource.RUSAGE_CHILDREN), time.perf_counter()
      if subprocess.call(cmd) != 0:
        print(f"error: the export of {method} failed", file=sys.stderr)
        return 2
      after = resource.getrusage(resource.RUSAGE_CHILDREN)
      cost = {"cpu_seconds": after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime,
              "wall_seconds": time.perf_counter() - t0, "command": " ".join(cmd)}
      with open(os.path.join(args.out, f"{method}.export.json"), "w") as f:
        json.dump(cost, f, indent=1)   # the whole process: start-up and compilation included
    scores = os.path.join(args.out, f"{method}.wosac.json")
    if not os.path.exists(scores):
      cmd = base + ["--score", sub, "--workers", str(args.workers)]
      print("+", " ".join(cmd), flush=True)
      if subprocess.call(cmd) != 0:
        print(f"error: scoring {method} failed", file=sys.stderr)
        return 2
    with open(scores) as f:
      results[method] = json.load(f)
    table = wosac_scoring.compare(results)
    with open(os.path.join(args.out, "table.md"), "w") as f:
      f.write(table)
  print(table)
  return 0


if __name__ == "__main__":
  sys.exit(main())
