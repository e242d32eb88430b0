"""Export a training run as a shipped model (parameters and config, no optimizer state).

  python -m experiments.export --workdir runs/v3 --out checkpoints/pcdiff-cpu-v3

OUT has a training workdir's layout (encoder/, diffusion/), so `--checkpoint OUT`
works everywhere and `pcdiff_jax.pretrained(path=OUT)` loads it.
"""
from __future__ import annotations

import argparse
import sys

from experiments import _args
from pcdiff_jax import shipped


def main(argv=None) -> int:
  p = argparse.ArgumentParser(prog="python -m experiments.export", description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--workdir", required=True, help="training workdir with encoder/ and diffusion/")
  p.add_argument("--out", required=True, type=_args.output_dir, help="new folder for the exported model")
  p.add_argument("--simpl-ar-from", default=None, metavar="FOLDER",
                 help="keep the SIMPL-AR baseline's encoder of this model folder (its simpl_ar/ or encoder/)")
  args = p.parse_args(argv)
  try:
    steps = shipped.export(args.workdir, args.out, simpl_ar_from=args.simpl_ar_from)
  except (FileNotFoundError, FileExistsError, ValueError) as err:
    print(f"error: {err}", file=sys.stderr)
    return 2
  print(f"wrote {args.out}: " + ", ".join(f"{k} step {v}" for k, v in steps.items()))
  return 0


if __name__ == "__main__":
  sys.exit(main())
