"""The embedded default dataset: synthetic traffic scenes in the WOMD tf.Example schema.

  python -m experiments.make_data --out data/synth --num-train 2000 --num-val 200 --seed 0
  python -m experiments.make_data --stats data/synth

The first writes DIR/train-XXXXX-of-YYYYY.tfrecord, DIR/val-..., DIR/stats.json
(re-running skips finished shards); the second writes DIR/realism.{md,json},
DIR/realism_hist.png and DIR/examples.png, next to the real WOMD sample.
"""
from __future__ import annotations

import argparse
import json
import os
import sys

from experiments import _args

REAL_SAMPLE = os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data", "womd",
                           "motion_data_one_example.tfrecord")


def parse_args(argv=None) -> argparse.Namespace:
  p = argparse.ArgumentParser(prog="python -m experiments.make_data", description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--out", type=_args.output_dir, help="output folder for the shards")
  p.add_argument("--num-train", type=int, default=1000)
  p.add_argument("--num-val", type=int, default=200)
  p.add_argument("--seed", type=int, default=0)
  p.add_argument("--workers", type=int, default=None, help="processes (default: all cores)")
  p.add_argument("--shard-size", type=int, default=256, help="scenes per TFRecord shard")
  p.add_argument("--max-rg-points", type=int, default=20000,
                 help="roadgraph samples per record, padded (WOMD: 20000)")
  p.add_argument("--families", nargs="+", default=None,
                 help="restrict to these map families (default: all, weighted)")
  p.add_argument("--surface-limit-stretch", type=float, default=1.0,
                 help="widen surface-street speed limits upwards (1: the benchmark's; 2: 10-24 m/s on roads)")
  p.add_argument("--warmup-seconds", type=float, default=1.2,
                 help="traffic simulated before each log starts (1.2: the benchmark's; 30: queues "
                      "at lights and stop signs, as in real scenes)")
  p.add_argument("--stats", metavar="DIR", help="write the realism report for DIR instead")
  p.add_argument("--real", default=REAL_SAMPLE, help="real WOMD record to compare with")
  p.add_argument("--num-scenes", type=int, default=200, help="scenes read for --stats")
  p.add_argument("--metric-scenes", type=int, default=48, help="scenes scored for log collision/off-road")
  args = p.parse_args(argv)
  if not args.stats and not args.out:
    p.error("give --out DIR (generate) or --stats DIR (report)")
  for name in ("num_train", "num_val"):
    if getattr(args, name) < 0:
      p.error(f"--{name.replace('_', '-')} must be >= 0")
  if not 1.0 <= args.surface_limit_stretch <= 3.0:
    p.error("--surface-limit-stretch must be within [1, 3]")
  if not 0.0 <= args.warmup_seconds <= 120.0:
    p.error("--warmup-seconds must be within [0, 120]")
  for name in ("shard_size", "max_rg_points", "num_scenes", "metric_scenes"):
    if getattr(args, name) < 1:
      p.error(f"--{name.replace('_', '-')} must be >= 1")
  if args.workers is not None and args.workers < 1:
    p.error("--workers must be >= 1")
  if args.families:
    from pcdiff_jax.data.synthetic import FAMILIES
    bad = sorted(set(args.families) - set(FAMILIES))
    if bad:
      p.error(f"unknown --families {bad}; choose from {list(FAMILIES)}")
  return args


def _generate(args) -> int:
  from tqdm import tqdm
  from pcdiff_jax.data.synthetic import SyntheticConfig
  from pcdiff_jax.data.synthetic.dataset import write_dataset
  from pcdiff_jax.data.synthetic.scene import DEFAULT_FAMILY_WEIGHTS
  weights = DEFAULT_FAMILY_WEIGHTS
  if args.families:
    weights = tuple((f, w) for f, w in DEFAULT_FAMILY_WEIGHTS if f in args.families)
  cfg = SyntheticConfig(max_rg_points=args.max_rg_points, family_weights=weights,
                        surface_limit_stretch=args.surface_limit_stretch,
                        warmup_steps=round(args.warmup_seconds * 10))
  with tqdm(total=args.num_train + args.num_val, desc="scenes", unit="scene") as bar:
    stats = write_dataset(args.out, args.num_train, args.num_val, args.seed, cfg,
                          shard_size=args.shard_size, workers=args.workers, on_progress=bar.update)
  summary = {k: {f: v for f, v in stats[k].items() if f != "files"} for k in ("train", "val") if k in stats}
  print(json.dumps(summary, indent=2))
  rate = stats.get("scenes_per_second")
  print(f"wrote {args.out}/stats.json" + (f" ({rate:.1f} scenes/s)" if rate else " (all shards existed)"))
  return 0


def _report(args) -> int:
  from experiments.realism_report import write_report
  report = write_report(args.stats, args.real, num_scenes=args.num_scenes,
                        num_metric_scenes=args.metric_scenes)
  with open(os.path.join(args.stats, "realism.md")) as f:
    print(f.read())
  if "real WOMD sample" not in report["summaries"]:
    print(f"note: real sample not found at {args.real}; synthetic figures only", file=sys.stderr)
  print(f"wrote {args.stats}/realism.json, realism.md, realism_hist.png, examples.png")
  return 0


def main(argv=None) -> int:
  args = parse_args(argv)
  try:
    return _report(args) if args.stats else _generate(args)
  except (FileNotFoundError, RuntimeError, ValueError) as err:
    print(f"error: {err}", file=sys.stderr)
    return 2


if __name__ == "__main__":
  sys.exit(main())
