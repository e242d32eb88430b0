"""The main job on the built-in data, end to end (README quickstart: `make demo`).

  python -m experiments.demo --out runs/demo            # the shipped model (checkpoints/)
  python -m experiments.demo --out runs/demo --train    # train the `demo` preset from scratch first

1. generates synthetic val scenes in the WOMD tf.Example schema (OUT/data;
   with --train, training scenes too),
2. loads the shipped model (`pcdiff_jax.pretrained`, checkpoints/ and its
   MODEL_CARD.md) or, with --train, trains stage 1 (scene encoder) and
   stage 2 (PCA latent + denoiser) with --config (OUT/model),
3. rolls out ours, SIMPL-AR, IDM and constant velocity in closed loop on
   the val scenes, --num-steps (80) steps at 10 Hz (OUT/eval/METHOD: metrics, GIFs),
4. prints the metrics table and writes it to OUT/table.md,
5. rolls out log replay, ours and the baselines on the first --num-real real
   WOMD val scenes when they are there (`--real-scenes`, default
   ../shared/data/womd_real/val.scenario.tfrecord; OUT/eval/real/METHOD, with
   GIFs) and prints their table (OUT/table.md),
6. runs ours in closed loop on the real WOMD sample when it is there
   (`--real`, default ../shared/data/womd/...; OUT/eval/real-pcdiff).

Every step resumes: re-running skips finished shards, continues training from
the last checkpoint and re-evaluates. The `demo` preset of --train is sized to
train in minutes on 2 CPU cores; its numbers show the pipeline working, not
the model's quality (docs/RESULTS.md has the longer runs).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

from experiments import _args, make_data, rollout, train
from pcdiff_jax import shipped
from pcdiff_jax.config import get_config

METHODS = ("pcdiff", "simpl-ar", "idm", "cv")
REAL_VAL = os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data", "womd_real",
                        "val.scenario.tfrecord")
LABELS = {"log": "log replay (the recorded drivers)", "pcdiff": ("ours (prior, 5 DDIM steps, then warm-started; "
                     "8 samples, the least colliding and off-road kept)"),
          "simpl-ar": "SIMPL-AR", "idm": "IDM", "cv": "constant velocity"}


def parse_args(argv=None) -> argparse.Namespace:
  p = argparse.ArgumentParser(prog="python -m experiments.demo", description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--out", default="runs/demo", type=_args.output_dir, help="output folder")
  p.add_argument("--checkpoint", default=None,
                 help="trained model folder (default: the shipped model, checkpoints/" + shipped.DEFAULT_NAME + ")")
  p.add_argument("--train", action="store_true",
                 help="train both stages from scratch with --config instead of loading a model")
  p.add_argument("--config", default="demo", help="config preset of both stages (with --train)")
  p.add_argument("--max-agents", type=int, default=None,
                 help="reactive agents nearest the SDC (default: the model config's)")
  p.add_argument("--warm-start", action=argparse.BooleanOptionalAction, default=True,
                 help="ours: warm-started (amortised) replanning (default) or cold plans (--no-warm-start)")
  p.add_argument("--num-train", type=int, default=400, help="synthetic training scenes")
  p.add_argument("--num-val", type=int, default=16, help="synthetic val scenes (the closed-loop set)")
  p.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
  p.add_argument("--batch-size", type=int, default=4, help="scenarios per jitted closed-loop call")
  p.add_argument("--num-steps", type=int, default=80, help="closed-loop steps at 10 Hz (80: WOMD's 8 s)")
  p.add_argument("--real", default=make_data.REAL_SAMPLE,
                 help="a real WOMD record to run ours on at the end (skipped when absent)")
  p.add_argument("--real-scenes", default=REAL_VAL,
                 help="real WOMD scenes to roll every method out on too (skipped when absent)")
  p.add_argument("--num-real", type=int, default=3, help="how many of --real-scenes (0: none)")
  p.add_argument("--no-progress", action="store_true")
  args = p.parse_args(argv)
  if args.num_real < 0:
    p.error("--num-real must be >= 0")
  if args.num_train < 8 or args.num_val < 1:
    p.error("--num-train must be >= 8 and --num-val >= 1")
  if args.train and args.checkpoint:
    p.error("--train and --checkpoint exclude each other")
  if args.max_agents is not None and args.max_agents < 1:
    p.error("--max-agents must be >= 1")
  if not 1 <= args.num_steps <= 80:
    p.error("--num-steps must be in [1, 80] (WOMD has 80 future steps)")
  return args


def _run(name: str, main, argv: list[str]) -> None:
  print(f"\n== {name}: python -m experiments.{main.__module__.split('.')[-1]} {' '.join(argv)}", flush=True)
  t0 = time.perf_counter()
  code = main(argv)
  if code:
    raise SystemExit(f"demo: step '{name}' failed (exit {code})")
  print(f"== {name}: done in {time.perf_counter() - t0:.0f} s", flush=True)


def table(out: str, methods, folder: str = "eval") -> str:
  """Markdown table of OUT/FOLDER/METHOD/metrics.json (missing runs are skipped)."""
  rows = ["| method | collision (%) | off-road (%) | realism (W1) | minADE (m) | still moved (%) | ms / replan |",
          "|---|---|---|---|---|---|---|"]
  for m in methods:
    path = os.path.join(out, folder, m, "metrics.json")
    if not os.path.exists(path):
      continue
    with open(path) as f:
      r = json.load(f)
    rows.append(f"| {LABELS[m]} | {100 * r['collision_rate']['mean']:.1f} | "
                f"{100 * r['offroad_rate']['mean']:.1f} | {r['realism']['mean']:.2f} | "
                f"{r['min_ade']['mean']:.2f} | {100 * r['still_moved_rate']['mean']:.1f} | "
                f"{r['runtime_ms_per_replan']['mean']:.1f} |")
  return "\n".join(rows) + "\n"


def main(argv=None) -> int:
  args = parse_args(argv)
  t0 = time.perf_counter()
  data = os.path.join(args.out, "data")
  model = os.path.join(args.out, "model") if args.train else (args.checkpoint or shipped.checkpoint_dir())
  if not args.train and not os.path.isdir(model):
    print(f"demo: no trained model at {model}; pass --checkpoint DIR or --train", file=sys.stderr)
    return 2
  quiet = ["--no-progress"] if args.no_progress else []
  num_train = args.num_train if args.train else 0
  _run("scenes", make_data.main, ["--out", data, "--num-train", str(num_train),
                                  "--num-val", str(args.num_val), "--seed", "0", "--shard-size", "100"])
  if args.train:
    _run("training", train.main, ["--stage", "all", "--config", args.config, "--workdir", model,
                                  "--data", os.path.join(data, "train-*")] + quiet)
    model_cfg = get_config(args.config)
  else:
    model_cfg = shipped.read_config(model)
    print(f"\n== model: {model} (see its MODEL_CARD.md)", flush=True)
  max_agents = args.max_agents or model_cfg.metrics.max_reactive_agents
  for method in args.methods:
    argv = ["--scenarios", os.path.join(data, "val-*"), "--method", method,
            "--out", os.path.join(args.out, "eval", method), "--batch-size", str(args.batch_size),
            "--max-agents", str(max_agents), "--gifs", "1", "--num-steps", str(args.num_steps)]
    if method in ("pcdiff", "simpl-ar"):
      argv += ["--checkpoint", model, "--ddim-steps", "5"]
    if method == "pcdiff" and not args.warm_start:
      argv += ["--no-warm-start"]
    _run(f"closed loop: {method}", rollout.main, argv + quiet)
  real_methods = ["log"] + list(args.methods)
  real = args.num_real > 0 and os.path.exists(args.real_scenes)
  for method in real_methods if real else ():
    argv = ["--scenarios", args.real_scenes, "--max-scenarios", str(args.num_real), "--method", method,
            "--out", os.path.join(args.out, "eval", "real", method), "--batch-size", str(args.batch_size),
            "--max-agents", str(max_agents), "--gifs", str(args.num_real), "--num-steps", str(args.num_steps)]
    if method in ("pcdiff", "simpl-ar"):
      argv += ["--checkpoint", model]
    _run(f"closed loop on real WOMD val scenes: {method}", rollout.main, argv + quiet)
  if "pcdiff" in args.methods and os.path.exists(args.real):
    _run("closed loop on the real WOMD sample: pcdiff", rollout.main, [
        "--scenarios", args.real, "--method", "pcdiff", "--checkpoint", model,
        "--out", os.path.join(args.out, "eval", "real-pcdiff"), "--max-agents", str(max_agents),
        "--gifs", "1", "--num-steps", str(args.num_steps)] + ([] if args.warm_start else ["--no-warm-start"]) + quiet)
  text = table(args.out, args.methods)
  minutes = (time.perf_counter() - t0) / 60
  header = (f"# Demo: {args.num_val} synthetic val scenes, {args.num_steps} closed-loop steps at 10 Hz, up to "
            f"{max_agents} reactive agents, the SDC replays its log\n\n")
  if real:
    header_real = (f"\n# The first {args.num_real} real WOMD val scenes ({args.real_scenes}), the same "
                   "setting, log replay first\n\n")
    text += header_real + table(args.out, real_methods, os.path.join("eval", "real"))
  with open(os.path.join(args.out, "table.md"), "w") as f:
    f.write(header + text + f"\nTotal time {minutes:.1f} min.\n")
  print("\n" + header + text)
  print(f"demo finished in {minutes:.1f} min; table: {args.out}/table.md; GIFs: {args.out}/eval/*/gifs/")
  return 0


if __name__ == "__main__":
  sys.exit(main())
