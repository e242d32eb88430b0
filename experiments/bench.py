"""Benchmarks of the foundation layer; results go to docs/BENCHMARKS.md.

  python -m experiments.bench --scenarios ../shared/data/womd/motion_data_one_example.tfrecord

Measures: TFRecord parse speed (scenarios/s, the record replicated into a
temporary file), closed-loop simulator step time (constant-velocity actor,
64 reactive agents, 80 steps as one lax.scan; per batch size), the time of
the collision/off-road metrics, and the scene encoder's forward pass (64
agents, 256 map pieces; per preset: ms per scene and XLA temp memory).
Compile time is excluded and reported separately.
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
    final = jax.block_until_ready(run(batch, rngs, None))
    compile_s = time.perf_counter() - t0
    times = _time(lambda: run(batch, rngs, None), repeats)
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


def bench_encoder(path: str, presets: list[str], repeats: int) -> list[dict]:
  """Features + encoder forward pass, jitted, on the first record (unbatched)."""
  from pcdiff_jax.config import get_config
  from pcdiff_jax.data import womd
  from pcdiff_jax.model import encoder, features
  from pcdiff_jax.sim import env
  state = env.reset(womd.load(path)[0])
  rows = []
  for name in presets:
    cfg = get_config(name)
    feats = features.scene_features(state, cfg.features)
    params = encoder.init(jax.random.PRNGKey(0), feats, cfg.encoder)
    fwd = jax.jit(lambda p, s: encoder.apply(p, features.scene_features(s, cfg.features), cfg.encoder))
    t0 = time.perf_counter()
    compiled = fwd.lower(params, state).compile()
    compile_s = time.perf_counter() - t0
    jax.block_until_ready(compiled(params, state))
    times = _time(lambda: compiled(params, state), repeats)
    memory = compiled.memory_analysis()
    rows.append({
        "preset": name, "agents": cfg.features.max_agents, "map_pieces": cfg.features.max_polylines,
        "neighbors": cfg.encoder.num_neighbors, "d_model": cfg.encoder.d_model,
        "params": int(sum(np.size(x) for x in jax.tree_util.tree_leaves(params))),
        "compile_s": compile_s, "ms_per_scene": 1000 * float(np.median(times)),
        "ms_per_scene_min": 1000 * float(np.min(times)),
        "temp_mb": (memory.temp_size_in_bytes / 2**20) if memory is not None else None,
    })
  return rows


def main(argv=None) -> int:
  p = argparse.ArgumentParser(prog="python -m experiments.bench", description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--scenarios", required=True, help="a WOMD-format TFRecord (the first record is used)")
  p.add_argument("--parse-copies", type=int, default=200)
  p.add_argument("--batch-sizes", type=int, nargs="+", default=[1, 4, 16])
  p.add_argument("--repeats", type=int, default=5)
  p.add_argument("--encoder-presets", nargs="*", default=["cpu", "paper"],
                 help="config presets for the encoder benchmark (none: skip it)")
  p.add_argument("--json", help="also write the results here")
  args = p.parse_args(argv)
  if not os.path.isfile(args.scenarios):
    p.error(f"--scenarios: file not found: {args.scenarios}")
  results = {"device": str(jax.devices()[0]), "cpu_count": os.cpu_count(),
             "parse": bench_parse(args.scenarios, args.parse_copies),
             "rollout_cv_64_agents": bench_rollout(args.scenarios, args.batch_sizes, args.repeats),
             "encoder_forward": bench_encoder(args.scenarios, args.encoder_presets, args.repeats)}
  print(json.dumps(results, indent=2))
  if args.json:
    with open(args.json, "w") as f:
      json.dump(results, f, indent=2)
  return 0


if __name__ == "__main__":
  raise SystemExit(main())
