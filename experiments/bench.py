"""Benchmarks of the foundation layer; results go to docs/BENCHMARKS.md.

  python -m experiments.bench --scenarios ../shared/data/womd/motion_data_one_example.tfrecord

Measures: TFRecord parse speed (scenarios/s, the record replicated into a
temporary file), closed-loop simulator step time (constant-velocity actor,
64 reactive agents, 80 steps as one lax.scan; per batch size), and the time
of the collision/off-road metrics. Compile time is excluded and reported
separately.
"""
from __future__ import annotations

import argparse
import json
import os
import tempfile
import time

import jax
import numpy as np


def _time(fn, repeats: int) -> list[float]:
  out = []
  for _ in range(repeats):
    t0 = time.perf_counter()
    jax.block_until_ready(fn())
    out.append(time.perf_counter() - t0)
  return out


def bench_parse(path: str, copies: int) -> dict:
  from pcdiff_jax.data import womd
  state, meta = womd.load(path)
  with tempfile.TemporaryDirectory() as tmp:
    big = os.path.join(tmp, "bench.tfrecord")
    womd.write(big, [(state, f"{meta.scenario_id}-{i}") for i in range(copies)])
    t0 = time.perf_counter()
    n = sum(1 for _ in womd.iterate_numpy(big))
    elapsed = time.perf_counter() - t0
  return {"scenarios": n, "seconds": elapsed, "scenarios_per_s": n / elapsed}


def bench_rollout(path: str, batch_sizes: list[int], repeats: int) -> list[dict]:
  from pcdiff_jax import evaluation
  from pcdiff_jax.data import womd
  state, _ = womd.load(path)
  cfg = evaluation.EvalConfig(method="cv")
  run = evaluation.make_rollout_fn(evaluation.METHODS["cv"](64), cfg)
  score = evaluation.make_score_fn(cfg)
  rows = []
  for b in batch_sizes:
    batch = jax.tree_util.tree_map(lambda a: np.repeat(np.asarray(a)[None], b, 0), state)
    rngs = jax.random.split(jax.random.PRNGKey(0), b)
    t0 = time.perf_counter()
    final = jax.block_until_ready(run(batch, rngs))
    compile_s = time.perf_counter() - t0
    times = _time(lambda: run(batch, rngs), repeats)
    jax.block_until_ready(score(final))
    score_times = _time(lambda: score(final), max(1, repeats // 2))
    rows.append({
        "batch": b, "compile_s": compile_s,
        "ms_per_step": 1000 * float(np.mean(times)) / cfg.num_steps,
        "ms_per_step_std": 1000 * float(np.std(times)) / cfg.num_steps,
        "ms_per_scenario_step": 1000 * float(np.mean(times)) / cfg.num_steps / b,
        "metrics_s_per_scenario": float(np.mean(score_times)) / b,
    })
  return rows


def main(argv=None) -> int:
  p = argparse.ArgumentParser(prog="python -m experiments.bench", description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--scenarios", required=True, help="a WOMD-format TFRecord (the first record is used)")
  p.add_argument("--parse-copies", type=int, default=200)
  p.add_argument("--batch-sizes", type=int, nargs="+", default=[1, 4, 16])
  p.add_argument("--repeats", type=int, default=5)
  p.add_argument("--json", help="also write the results here")
  args = p.parse_args(argv)
  if not os.path.isfile(args.scenarios):
    p.error(f"--scenarios: file not found: {args.scenarios}")
  results = {"device": str(jax.devices()[0]), "cpu_count": os.cpu_count(),
             "parse": bench_parse(args.scenarios, args.parse_copies),
             "rollout_cv_64_agents": bench_rollout(args.scenarios, args.batch_sizes, args.repeats)}
  print(json.dumps(results, indent=2))
  if args.json:
    with open(args.json, "w") as f:
      json.dump(results, f, indent=2)
  return 0


if __name__ == "__main__":
  raise SystemExit(main())
