"""argparse types shared by the CLIs: a user's mistake ends in a usage error
(exit 2) that names the path, not in a traceback from deep inside a run."""
from __future__ import annotations

import argparse
import os
from typing import Optional

from pcdiff_jax.config import RUN_MAP_ANCHOR


def policy_item(text: str) -> tuple[str, object]:
  """'field=value' -> (field, value); a comma-separated value is a tuple."""
  name, sep, value = text.partition("=")
  if not sep or not name:
    raise argparse.ArgumentTypeError(f"expected FIELD=VALUE, got {text!r}")
  return name, tuple(value.split(",")) if "," in value else value


def add_policy_flags(p: argparse.ArgumentParser) -> None:
  """The diffusion policy's options: three common flags, a JSON file and
  generic FIELD=VALUE items (`policy_config` merges them)."""
  from pcdiff_jax.policy import PolicyConfig
  p.add_argument("--ddim-steps", type=int, default=None,
                 help=f"pcdiff: DDIM steps of a cold plan (policy field ddim_steps, default {PolicyConfig.ddim_steps})")
  p.add_argument("--replan-every", type=int, default=None,
                 help="pcdiff: steps between plans (policy field replan_every; default 2: plans at 5 Hz)")
  p.add_argument("--warm-start", action=argparse.BooleanOptionalAction, default=None,
                 help="pcdiff: start each replan from the previous plan (the default) or from the "
                      "proposal prior (policy field warm_start)")
  p.add_argument("--policy-file", default=None, metavar="FILE.json",
                 help="pcdiff: a JSON object of policy fields, e.g. {\"select_samples\": 4, \"jerk_limit\": [1.5, 5]}")
  p.add_argument("--policy", nargs="+", default=[], metavar="FIELD=VALUE", type=policy_item,
                 help="pcdiff: set policy fields (over --policy-file and the flags above), e.g. --policy "
                      "max_curvature=0.3 jerk_limit=1.5,5 (tuples comma-separated); the fields are listed below")


def add_map_flags(p: argparse.ArgumentParser, pieces: Optional[int] = None, why: str = "") -> None:
  """A learned model's map crop at evaluation time (`EvalConfig.map_pieces`, `.map_anchor`);
  pieces: the default crop (None: the model's)."""
  default = "the model's, 256" if pieces is None else f"{pieces}, or the model's if fewer{why}"
  p.add_argument("--map-pieces", type=int, default=pieces, metavar="N",
                 help=f"learned methods: at most this many map pieces for the encoder (default: {default}); "
                      "fewer is faster")
  p.add_argument("--map-anchor", default=RUN_MAP_ANCHOR, choices=("sdc", "agents"),
                 help="learned methods: keep the pieces nearest any modelled agent (default) or nearest the "
                      "SDC (as the model was trained)")


def add_start_flags(p: argparse.ArgumentParser) -> None:
  """Where a simulated method starts (`EvalConfig.fit_start_velocity`)."""
  p.add_argument("--start-velocity", default="positions", choices=("positions", "tracked"),
                 help="simulated methods: start an object whose tracked velocity is more than 2 m/s off its "
                      "last 0.5 s of positions at the positions' velocity (default), or at the tracked one")


def start_options(args: argparse.Namespace) -> dict:
  """{fit_start_velocity} for EvalConfig from --start-velocity."""
  return {"fit_start_velocity": args.start_velocity == "positions"}


def map_crop(p: argparse.ArgumentParser, args: argparse.Namespace) -> dict:
  """{map_pieces, map_anchor} for EvalConfig; a usage error (exit 2) for a bad count."""
  if args.map_pieces is not None and args.map_pieces < 1:
    p.error("--map-pieces must be >= 1")
  return {"map_pieces": args.map_pieces, "map_anchor": args.map_anchor}


def policy_fields_epilog() -> str:
  """A --help epilog: every policy field with its default."""
  import dataclasses
  import textwrap
  from pcdiff_jax.policy import PolicyConfig
  show = lambda v: ",".join(map(str, v)) if isinstance(v, tuple) else str(v)   # as --policy takes it
  fields = [f"{f.name}={show(getattr(PolicyConfig(), f.name))}" for f in dataclasses.fields(PolicyConfig)
            if f.name != "guidance"]
  return ("policy fields (--policy FIELD=VALUE, --policy-file; pcdiff_jax/policy/config.py says what each does):\n  "
          + textwrap.fill(" ".join(fields), 96, subsequent_indent="  "))


def policy_config(p: argparse.ArgumentParser, args: argparse.Namespace):
  """PolicyConfig's defaults, then --policy-file, then --ddim-steps / --replan-every /
  --warm-start where given, then --policy; a usage error (exit 2) names a bad field."""
  import json
  from pcdiff_jax.config import get_config
  from pcdiff_jax.policy import PolicyConfig, validate, with_overrides
  pcfg = PolicyConfig()
  if args.policy_file is not None:
    try:
      with open(args.policy_file) as f:
        fields = json.load(f)
    except (OSError, ValueError) as err:
      p.error(f"--policy-file {args.policy_file}: {err}")
    if not isinstance(fields, dict):
      p.error(f"--policy-file {args.policy_file}: expected a JSON object of policy fields")
    try:
      pcfg = with_overrides(pcfg, fields.items())
    except (ValueError, TypeError) as err:
      p.error(f"--policy-file {args.policy_file}: {err}")
  flags = {"ddim_steps": args.ddim_steps, "replan_every": args.replan_every, "warm_start": args.warm_start}
  try:
    pcfg = with_overrides(pcfg, [(k, v) for k, v in flags.items() if v is not None])
    pcfg = with_overrides(pcfg, args.policy)
    validate(get_config("cpu"), pcfg)   # the presets share the ranges checked here; the actor checks again
  except (ValueError, TypeError) as err:
    p.error(f"--policy: {err}")
  return pcfg


def shipped_model_above(path: str):
  """The shipped model folder (one with a MODEL_CARD.md) that `path` is or lies in, else None."""
  folder = os.path.abspath(path)
  while True:
    if os.path.isfile(os.path.join(folder, "MODEL_CARD.md")):
      return folder
    parent = os.path.dirname(folder)
    if parent == folder:
      return None
    folder = parent


def output_dir(path: str) -> str:
  """A folder to write into: new, or an existing folder (never a file, never inside a shipped
  model, which every command only reads)."""
  shipped = shipped_model_above(path)
  if shipped is not None:
    raise argparse.ArgumentTypeError(f"{path} is inside the shipped model {shipped} (it has a MODEL_CARD.md), "
                                     "which is read-only: write to a new folder, e.g. under runs/")
  if os.path.exists(path) and not os.path.isdir(path):
    raise argparse.ArgumentTypeError(f"{path} exists and is a file, not a folder: give a folder path")
  parent = os.path.dirname(os.path.abspath(path))
  while not os.path.exists(parent):
    parent = os.path.dirname(parent)
  if not os.path.isdir(parent):
    raise argparse.ArgumentTypeError(f"{path}: {parent} is a file, so no folder can be made below it")
  return path


def output_file(path: str) -> str:
  """A file to write: never an existing folder."""
  if os.path.isdir(path):
    raise argparse.ArgumentTypeError(f"{path} is a folder: give a file path")
  output_dir(os.path.dirname(path) or ".")
  return path


def setup_logging() -> None:
  """INFO from our own modules; the libraries' start-up chatter (absl, orbax's
  per-save notices, jax's "no TPU backend" probe, TensorFlow's C++ banner) only
  from WARNING up."""
  import logging
  os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "2")   # before TensorFlow is first imported
  logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
  for noisy in ("absl", "orbax", "jax._src.xla_bridge"):
    logging.getLogger(noisy).setLevel(logging.WARNING)


def add_device_flags(parser: argparse.ArgumentParser, hosts: bool = True) -> None:
  """--devices, and with `hosts` the multi-host flags (`pcdiff_jax.distributed`)."""
  g = parser.add_argument_group("devices and hosts")
  g.add_argument("--devices", type=int, default=None,
                 help="use the first N devices (default: every device); the batch is split over them")
  if not hosts:
    return
  g.add_argument("--coordinator", default=None,
                 help="several hosts: HOST:PORT of process 0 (default: $JAX_COORDINATOR_ADDRESS)")
  g.add_argument("--num-processes", type=int, default=None,
                 help="several hosts: how many processes (default: $JAX_NUM_PROCESSES)")
  g.add_argument("--process-id", type=int, default=None,
                 help="several hosts: this process's index (default: $JAX_PROCESS_ID)")
  g.add_argument("--distributed", action="store_true",
                 help="several hosts: let JAX detect the rest from its cluster (SLURM, Open MPI, Cloud TPU)")


def check_device_flags(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
  """Usage errors (exit 2) for values that can never work; the device count is
  checked later, once the devices are known."""
  if args.devices is not None and args.devices < 1:
    parser.error("--devices must be >= 1")
  num, pid = getattr(args, "num_processes", None), getattr(args, "process_id", None)
  if num is not None and num < 1:
    parser.error("--num-processes must be >= 1")
  if pid is not None and (pid < 0 or (num is not None and pid >= num)):
    parser.error("--process-id must be in [0, --num-processes)")


def device_mesh(args: argparse.Namespace):
  """Connects the hosts (when asked) and returns the `data` mesh over
  --devices, or None for a single device (the one-device code path).
  Raises ValueError when more devices are asked for than there are."""
  import jax

  from pcdiff_jax import distributed
  if hasattr(args, "coordinator"):   # the flags, else the environment variables, when set
    distributed.initialize(args.coordinator, args.num_processes, args.process_id, auto=args.distributed)
  n = jax.device_count() if args.devices is None else args.devices
  if n == 1 and jax.process_count() == 1:
    return None
  return distributed.data_mesh(args.devices)
