"""Sharded, parallel, resumable writing of the synthetic dataset.

Scene i of a split is `generate_scene(seed, i, stream=split_code)`, so the
bytes of a shard depend only on (seed, split, shard range, config), not on
how many processes wrote it. A finished shard is never rewritten: rerunning
after an interruption writes only the missing shards.
"""
from __future__ import annotations

import concurrent.futures as futures
import dataclasses
import json
import multiprocessing
import os
import time
from typing import Callable, Optional

import numpy as np

from pcdiff_jax.data.synthetic.scene import SyntheticConfig, generate_scene

SPLITS = {"train": 0, "val": 1}


@dataclasses.dataclass(frozen=True)
class Shard:
  split: str
  index: int
  count: int
  start: int                     # first scene index
  size: int                      # scenes in this shard

  def name(self) -> str:
    return f"{self.split}-{self.index:05d}-of-{self.count:05d}.tfrecord"


def plan_shards(split: str, num_scenes: int, shard_size: int) -> list[Shard]:
  count = max(1, -(-num_scenes // shard_size))
  return [Shard(split, k, count, k * shard_size, min(shard_size, num_scenes - k * shard_size))
          for k in range(count) if num_scenes > 0]


def _meta_path(out_dir: str, shard: Shard) -> str:
  return os.path.join(out_dir, "shards", shard.name() + ".json")


def write_shard(out_dir: str, shard: Shard, seed: int, cfg: SyntheticConfig) -> list[dict]:
  """Generates and writes one shard (tmp file + rename); returns per-scene info."""
  from pcdiff_jax.data import womd
  infos = []

  def scenes():
    for i in range(shard.start, shard.start + shard.size):
      t0 = time.perf_counter()
      scene = generate_scene(seed, i, cfg, stream=SPLITS[shard.split])
      infos.append(dict(scene.info, scenario_id=scene.scenario_id, seconds=time.perf_counter() - t0))
      yield scene.state, scene.scenario_id

  womd.write(os.path.join(out_dir, shard.name()), scenes())
  with open(_meta_path(out_dir, shard) + ".tmp", "w") as f:
    json.dump(infos, f)
  os.replace(_meta_path(out_dir, shard) + ".tmp", _meta_path(out_dir, shard))
  return infos


def _done(out_dir: str, shard: Shard) -> bool:
  return os.path.exists(os.path.join(out_dir, shard.name())) and os.path.exists(_meta_path(out_dir, shard))


def write_dataset(out_dir: str, num_train: int, num_val: int, seed: int, cfg: SyntheticConfig = SyntheticConfig(),
                  shard_size: int = 256, workers: Optional[int] = None,
                  on_progress: Optional[Callable[[int], None]] = None) -> dict:
  """Writes `out_dir/{train,val}-XXXXX-of-YYYYY.tfrecord` and `out_dir/stats.json`; returns the stats."""
  os.makedirs(os.path.join(out_dir, "shards"), exist_ok=True)
  workers = workers or os.cpu_count() or 1
  shards = plan_shards("train", num_train, shard_size) + plan_shards("val", num_val, shard_size)
  todo = [s for s in shards if not _done(out_dir, s)]
  reused = len(shards) - len(todo)
  t0 = time.perf_counter()
  if on_progress:
    on_progress(sum(s.size for s in shards if s not in todo))
  if workers == 1 or len(todo) <= 1:
    for shard in todo:
      write_shard(out_dir, shard, seed, cfg)
      if on_progress:
        on_progress(shard.size)
  else:
    # spawn, not fork: the parent may already run JAX/TensorFlow threads.
    ctx = multiprocessing.get_context("spawn")
    with futures.ProcessPoolExecutor(max_workers=workers, mp_context=ctx) as pool:
      jobs = {pool.submit(write_shard, out_dir, s, seed, cfg): s for s in todo}
      for job in futures.as_completed(jobs):
        job.result()
        if on_progress:
          on_progress(jobs[job].size)
  elapsed = time.perf_counter() - t0
  stats = dataset_stats(out_dir, shards)
  stats.update(seed=seed, config=dataclasses.asdict(cfg), workers=workers, shard_size=shard_size,
               shards_reused=reused, seconds=elapsed,
               scenes_per_second=(sum(s.size for s in todo) / elapsed) if elapsed > 0 and todo else None)
  with open(os.path.join(out_dir, "stats.json"), "w") as f:
    json.dump(stats, f, indent=2)
  return stats


def dataset_stats(out_dir: str, shards: list[Shard]) -> dict:
  """Counts from the per-shard sidecars: scenes, families, objects, redraws, log overlaps."""
  out = {}
  for split in SPLITS:
    infos = []
    for s in shards:
      if s.split == split:
        with open(_meta_path(out_dir, s)) as f:
          infos += json.load(f)
    if not infos:
      continue
    objects = np.array([i["num_objects"] for i in infos])
    attempts = np.array([i["attempts"] for i in infos])
    families: dict[str, int] = {}
    for i in infos:
      families[i["family"]] = families.get(i["family"], 0) + 1
    out[split] = {
        "num_scenes": len(infos),
        "files": sorted({s.name() for s in shards if s.split == split}),
        "scene_types": dict(sorted(families.items())),
        "objects_per_scene": {"mean": float(objects.mean()), "min": int(objects.min()), "max": int(objects.max())},
        "draws_per_scene": float(attempts.mean()),
        "scenes_redrawn": int((attempts > 1).sum()),
        "scenes_with_log_overlap": int(sum(i["log_overlaps"] > 0 for i in infos)),
        "generation_seconds_per_scene": float(np.mean([i["seconds"] for i in infos])),
    }
  return out
