"""The shipped model: one call to load it, one to export a training run like it.

  models, cfg = pcdiff_jax.pretrained()   # both stages + latent statistics + config
  encoder_params, cfg = pcdiff_jax.pretrained(stage="encoder")   # stage 1 (the proposal prior)
  simpl_ar_params, cfg = pcdiff_jax.pretrained(stage="simpl-ar")  # the SIMPL-AR baseline's encoder

`checkpoints/<name>/` (committed, see its MODEL_CARD.md) has the layout of a
training workdir (`encoder/checkpoints/<step>`, `diffusion/checkpoints/<step>`),
so every `--checkpoint` option takes it as it is. `export` writes such a folder
from a training workdir with the optimizer state left out (a third of the size).
"""
from __future__ import annotations

import os
import shutil
from typing import Optional

DEFAULT_NAME = "pcdiff-cpu-v11"
_STAGES = ("encoder", "diffusion")
_OPTIONAL_STAGES = ("simpl_ar",)   # encoder_stage.SIMPL_AR_DIR: copied when the workdir has it
STAGES = ("encoder", "diffusion", "simpl-ar")


def checkpoint_dir(name: str = DEFAULT_NAME) -> str:
  """The folder of a shipped model: `$PCDIFF_CHECKPOINTS/<name>` when that
  variable is set, else `<repository>/checkpoints/<name>` (a clone, an editable
  install), else the copy an installed wheel carries, `pcdiff_jax/checkpoints/<name>`
  (setup.py puts the default model there, and only that one)."""
  root = os.environ.get("PCDIFF_CHECKPOINTS")
  if root is not None:
    return os.path.join(root, name)
  package = os.path.dirname(os.path.abspath(__file__))
  in_repository = os.path.join(os.path.dirname(package), "checkpoints", name)
  in_wheel = os.path.join(package, "checkpoints", name)
  return in_wheel if not os.path.isdir(in_repository) and os.path.isdir(in_wheel) else in_repository


def pretrained(name: str = DEFAULT_NAME, stage: str = "diffusion", path: Optional[str] = None):
  """(models, cfg) of a shipped model (`planner.Models`, `config.Config`);
  stage="encoder" returns (encoder parameters, cfg) instead, stage="simpl-ar"
  those the SIMPL-AR baseline runs with (its own fine-tuned encoder when the
  folder has one, else stage 1's). `path`: a folder with the same layout (e.g.
  an exported or a training workdir). cfg runs the map crop anchored on the
  agents (`config.RUN_MAP_ANCHOR`, as the evaluation does); `read_config`
  gives the one it was trained with."""
  from pcdiff_jax.training import diffusion_stage, encoder_stage
  folder = path or checkpoint_dir(name)
  if not os.path.isdir(folder):
    raise FileNotFoundError(f"no shipped model at {folder} (set PCDIFF_CHECKPOINTS or pass path=; an "
                            f"installed wheel carries only {DEFAULT_NAME})")
  if stage not in STAGES:
    raise ValueError(f"stage must be one of {STAGES}, got {stage!r}")
  load = {"encoder": encoder_stage.load, "simpl-ar": encoder_stage.load_simpl_ar}.get(stage, diffusion_stage.load)
  params, cfg = load(folder)
  return params, run_config(cfg)


def run_config(cfg):
  """A trained model's Config as it runs: its map crop anchored on the agents."""
  import dataclasses
  from pcdiff_jax.config import RUN_MAP_ANCHOR
  return dataclasses.replace(cfg, features=dataclasses.replace(cfg.features, map_anchor=RUN_MAP_ANCHOR))


def read_config(path: str, stage: str = "diffusion"):
  """The Config a model folder was trained with (no parameters loaded)."""
  from pcdiff_jax import config as config_lib
  from pcdiff_jax.training import trainer
  ckpt = trainer.Checkpointer(os.path.join(path, stage), read_only=True)
  try:
    return config_lib.from_dict(ckpt.read_config())
  finally:
    ckpt.close()


def export(workdir: str, out: str, simpl_ar_from: Optional[str] = None) -> dict[str, int]:
  """Copies the latest checkpoint of each stage of a training WORKDIR into OUT
  (same layout) with parameters, frozen extras and config only, and the
  SIMPL-AR encoder (simpl_ar/) when the workdir has one. `simpl_ar_from`: a
  model folder whose SIMPL-AR encoder OUT's baseline keeps instead (when
  WORKDIR's encoder was refit for ours only, as v11's). Returns the step of
  each stage. Refuses to overwrite an existing OUT."""
  from pcdiff_jax.training import encoder_stage, trainer
  if os.path.exists(out):
    raise FileExistsError(f"{out} exists; remove it or choose another --out")
  sources = {stage: os.path.join(workdir, stage) for stage in _STAGES}
  sources.update({s: os.path.join(workdir, s) for s in _OPTIONAL_STAGES if os.path.isdir(os.path.join(workdir, s))})
  if simpl_ar_from is not None:
    if not os.path.isdir(os.path.join(simpl_ar_from, encoder_stage.STAGE_DIR)):
      raise FileNotFoundError(f"--simpl-ar-from {simpl_ar_from}: not a model folder (no encoder/)")
    sources[encoder_stage.SIMPL_AR_DIR] = os.path.join(simpl_ar_from, encoder_stage.simpl_ar_dir(simpl_ar_from))
  steps = {}
  tmp = out.rstrip("/") + ".tmp"
  shutil.rmtree(tmp, ignore_errors=True)
  try:
    for stage, source in sources.items():
      src = trainer.Checkpointer(source, read_only=True)
      try:
        step, config, raw = src.latest_step(), src.read_config(), src.restore_raw()
      finally:
        src.close()
      slim = {"step": raw["step"], "params": raw["params"], "rng": raw["rng"]}
      if raw.get("extra"):
        slim["extra"] = raw["extra"]
      dst = trainer.Checkpointer(os.path.join(tmp, stage), keep=1)
      try:
        dst.save_raw(step, slim, config)
      finally:
        dst.close()
      steps[stage] = int(step)
    os.replace(tmp, out)
  finally:
    shutil.rmtree(tmp, ignore_errors=True)
  return steps
