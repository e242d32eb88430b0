"""argparse types shared by the CLIs: a user's mistake ends in a usage error
(exit 2) that names the path, not in a traceback from deep inside a run."""
from __future__ import annotations

import argparse
import os


def output_dir(path: str) -> str:
  """A folder to write into: new, or an existing folder (never a file)."""
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
