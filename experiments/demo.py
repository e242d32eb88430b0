"""The main job on the built-in data, end to end (README quickstart: `make demo`).

  python -m experiments.demo --out runs/demo

1. generates synthetic scenes in the WOMD tf.Example schema (OUT/data),
2. trains stage 1 (scene encoder) and stage 2 (PCA latent + denoiser) with
   the `demo` preset (OUT/model),
3. rolls out ours, SIMPL-AR, IDM and constant velocity in closed loop on
   the val scenes, 80 steps at 10 Hz (OUT/eval/METHOD: metrics, GIFs),
4. prints the metrics table and writes it to OUT/table.md,
5. runs ours in closed loop on the real WOMD sample when it is there
   (`--real`, default ../shared/data/womd/...; OUT/eval/real-pcdiff).

Every step resumes: re-running skips finished shards, continues training from
the last checkpoint and re-evaluates. The demo preset is sized to finish in
about a quarter of an hour on 2 CPU cores; its numbers show the pipeline
working, not the paper's quality (docs/RESULTS.md has the longer runs).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

from experiments import make_data, rollout, train

METHODS = ("pcdiff", "simpl-ar", "idm", "cv")
LABELS = {"pcdiff": "ours (prior, 5 DDIM steps)", "simpl-ar": "SIMPL-AR", "idm": "IDM",
          "cv": "constant velocity"}


def parse_args(argv=None) -> argparse.Namespace:
  p = argparse.ArgumentParser(prog="python -m experiments.demo", description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--out", default="runs/demo", help="output folder")
  p.add_argument("--config", default="demo", help="config preset of both stages")
  p.add_argument("--num-train", type=int, default=400, help="synthetic training scenes")
  p.add_argument("--num-val", type=int, default=24, help="synthetic val scenes (the closed-loop set)")
  p.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
  p.add_argument("--batch-size", type=int, default=4, help="scenarios per jitted closed-loop call")
  p.add_argument("--real", default=make_data.REAL_SAMPLE,
                 help="a real WOMD record to run ours on at the end (skipped when absent)")
  p.add_argument("--no-progress", action="store_true")
  args = p.parse_args(argv)
  if args.num_train < 8 or args.num_val < 1:
    p.error("--num-train must be >= 8 and --num-val >= 1")
  return args


def _run(name: str, main, argv: list[str]) -> None:
  print(f"\n== {name}: python -m experiments.{main.__module__.split('.')[-1]} {' '.join(argv)}", flush=True)
  t0 = time.perf_counter()
  code = main(argv)
  if code:
    raise SystemExit(f"demo: step '{name}' failed (exit {code})")
  print(f"== {name}: done in {time.perf_counter() - t0:.0f} s", flush=True)


def table(out: str, methods) -> str:
  """Markdown table of OUT/eval/METHOD/metrics.json (missing runs are skipped)."""
  rows = ["| method | collision (%) | off-road (%) | realism (W1) | minADE (m) | ms / replan |",
          "|---|---|---|---|---|---|"]
  for m in methods:
    path = os.path.join(out, "eval", m, "metrics.json")
    if not os.path.exists(path):
      continue
    with open(path) as f:
      r = json.load(f)
    rows.append(f"| {LABELS[m]} | {100 * r['collision_rate']['mean']:.1f} | "
                f"{100 * r['offroad_rate']['mean']:.1f} | {r['realism']['mean']:.2f} | "
                f"{r['min_ade']['mean']:.2f} | {r['runtime_ms_per_replan']['mean']:.1f} |")
  return "\n".join(rows) + "\n"


def main(argv=None) -> int:
  args = parse_args(argv)
  t0 = time.perf_counter()
  data, model = os.path.join(args.out, "data"), os.path.join(args.out, "model")
  quiet = ["--no-progress"] if args.no_progress else []
  _run("scenes", make_data.main, ["--out", data, "--num-train", str(args.num_train),
                                  "--num-val", str(args.num_val), "--seed", "0", "--shard-size", "100"])
  _run("training", train.main, ["--stage", "all", "--config", args.config, "--workdir", model,
                                "--data", os.path.join(data, "train-*")] + quiet)
  from pcdiff_jax.config import get_config
  max_agents = get_config(args.config).metrics.max_reactive_agents
  for method in args.methods:
    argv = ["--scenarios", os.path.join(data, "val-*"), "--method", method,
            "--out", os.path.join(args.out, "eval", method), "--batch-size", str(args.batch_size),
            "--max-agents", str(max_agents), "--gifs", "2"]
    if method in ("pcdiff", "simpl-ar"):
      argv += ["--checkpoint", model, "--ddim-steps", "5"]
    _run(f"closed loop: {method}", rollout.main, argv + quiet)
  if "pcdiff" in args.methods and os.path.exists(args.real):
    _run("closed loop on the real WOMD sample: pcdiff", rollout.main, [
        "--scenarios", args.real, "--method", "pcdiff", "--checkpoint", model,
        "--out", os.path.join(args.out, "eval", "real-pcdiff"), "--max-agents", str(max_agents),
        "--gifs", "1"] + quiet)
  text = table(args.out, args.methods)
  minutes = (time.perf_counter() - t0) / 60
  header = (f"# Demo: {args.num_val} synthetic val scenes, 80 closed-loop steps at 10 Hz, up to "
            f"{max_agents} reactive agents, the SDC replays its log\n\n")
  with open(os.path.join(args.out, "table.md"), "w") as f:
    f.write(header + text + f"\nTotal time {minutes:.1f} min.\n")
  print("\n" + header + text)
  print(f"demo finished in {minutes:.1f} min; table: {args.out}/table.md; GIFs: {args.out}/eval/*/gifs/")
  return 0


if __name__ == "__main__":
  sys.exit(main())
