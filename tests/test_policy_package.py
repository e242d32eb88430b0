"""The policy package's closed-loop outputs, pinned bit for bit on CPU.

tests/data/policy_rollouts.npz holds short closed-loop rollouts (and one stateless `policy.step`).
It was first recorded with the single-module policy the package replaced (commit e1ec5d4), which
the package matched bit for bit; it was re-recorded when the jerk limit's reference became
the policy's own executed acceleration (the log's trend over a second at the first step) and the
kinematic speed the velocity along the heading, when the encoder's attention applied its key and
value projections once per receiver instead of per edge (float rounding), and when the tests'
XLA settings (conftest.py) replaced XLA's defaults for it (CHANGELOG.md). Record it with
`PYTHONPATH=.:tests python tests/test_policy_package.py`, and only for a change meant to move
the numbers.
"""
from __future__ import annotations

import os
import pathlib
import platform
import sys

import jax
import numpy as np
import pytest

from conftest import build_tiny_models, make_scene
from pcdiff_jax import policy
from pcdiff_jax.config import get_config
from pcdiff_jax.model import guidance as guidance_lib
from pcdiff_jax.sim import env

CFG = get_config("tiny")
REFERENCE = pathlib.Path(__file__).parent / "data" / "policy_rollouts.npz"
NUM_STEPS = 5
# name -> PolicyConfig: the defaults, the new gates on the executed action, and the other branches
# of planning (track execution, consistent noise, top-1 prior centre, cold plans, guidance).
SETTINGS = {
    # The defaults the reference was recorded with (the still gate, the curvature bound and the
    # follow bound came on by default after it; "gates" covers the first two, tests/test_policy.py
    # the follow bound). Every setting but "track" plans at every step, the default then, and
    # none spares the map term (`select_map_spare`, a default added after the recording).
    "defaults": policy.PolicyConfig(still_gate=(0.0, 0.0), max_curvature=0.0, follow=(0.0, 0.0), replan_every=1,
                                 select_map_spare=(0.0, 0.0)),
    "gates": policy.PolicyConfig(still_gate=(2.0, 2.0), max_curvature=0.05, select_held_still=False,
                                 follow=(0.0, 0.0), replan_every=1, select_map_spare=(0.0, 0.0)),
    # The selection scoring held agents standing still (the default after "gates" was recorded).
    "held_still": policy.PolicyConfig(still_gate=(2.0, 2.0), max_curvature=0.05, follow=(0.0, 0.0),
                                      replan_every=1, select_map_spare=(0.0, 0.0)),
    "track": policy.PolicyConfig(execute="track", consistent_noise=True, prior_centre="top1",
                                 replan_every=2, select_samples=2, jerk_limit=(1.0, 0.0),
                                 still_gate=(0.0, 0.0), max_curvature=0.0, follow=(0.0, 0.0),
                                 select_map_spare=(0.0, 0.0)),
    "cold_guided": policy.PolicyConfig(warm_start=False, select_samples=1, ddim_steps=2,
                                       temporal_ensemble=(0.0, 0.0), stop_hold=False,
                                       still_gate=(0.0, 0.0), max_curvature=0.0, follow=(0.0, 0.0),
                                       replan_every=1, guidance=guidance_lib.GuidanceConfig(mode="objective")),
}


def _scene():
  # Object 2 is stopped (the still gate's case) and object 3 crawls.
  return env.reset(make_scene(num_steps=91, speeds=(10.0, 8.0, 0.0, 0.3)))


def _outputs(models) -> dict[str, np.ndarray]:
  """{name: array} for every setting: the rollout's executed actions (T, O, 2), their valid mask
  (T, O, 1) and the simulated poses and speeds (O, 91) at its end; and one stateless step."""
  state, out = _scene(), {}
  for name, pol in SETTINGS.items():
    run = jax.jit(lambda s, r, m, pol=pol: env.rollout(s, policy.actor(CFG, pol), NUM_STEPS, r, params=m))
    res = jax.device_get(run(state, jax.random.key(3), models))
    traj = res.final_state.sim_trajectory
    out[f"{name}/action"] = np.asarray(res.actions.data)
    out[f"{name}/valid"] = np.asarray(res.actions.valid)
    out[f"{name}/controlled"] = np.asarray(res.is_controlled)
    for field in ("x", "y", "yaw", "vel_x", "vel_y"):
      out[f"{name}/{field}"] = np.asarray(getattr(traj, field))
  step = jax.jit(lambda s, r, m: policy.step(s, m, CFG, r, SETTINGS["gates"]))
  action, controlled = jax.device_get(step(state, jax.random.key(4), models))
  out["step/action"], out["step/valid"] = np.asarray(action.data), np.asarray(action.valid)
  out["step/controlled"] = np.asarray(controlled)
  return out


def machine() -> str:
  """What decides the CPU program's last bits: the jax and jaxlib versions, the CPU (XLA tunes
  its code for the host's model, so two models with the same vector units still round apart),
  its vector units and the XLA flags (conftest.py's, unless XLA_DEFAULTS_ENV is set)."""
  from importlib import metadata
  flags, cpu = set(), {}
  if pathlib.Path("/proc/cpuinfo").exists():
    for line in pathlib.Path("/proc/cpuinfo").read_text().splitlines():
      key, _, value = (part.strip() for part in line.partition(":"))
      if key in ("vendor_id", "cpu family", "model"):
        cpu.setdefault(key, value)
      if key == "flags":
        flags = set(value.split()) & {"avx", "avx2", "fma", "avx512f", "avx512_bf16", "amx_tile"}
        break
  model = " ".join(f"{k}={v}" for k, v in sorted(cpu.items()))
  return (f"jax {metadata.version('jax')} jaxlib {metadata.version('jaxlib')} {platform.machine()} {model} "
          f"{' '.join(sorted(flags))} XLA_FLAGS={' '.join(sorted(os.environ.get('XLA_FLAGS', '').split()))}")


@pytest.mark.skipif(jax.default_backend() != "cpu", reason="the reference was recorded on CPU")
def test_rollouts_match_the_recorded_policy(tiny_models):
  """Bit for bit where jax, jaxlib, the CPU's vector units and the XLA flags are those of the
  recording; elsewhere XLA may compile other instructions (FMA, vector widths), so to 1e-3
  (float32 rounding over 5 steps)."""
  if not REFERENCE.exists():
    pytest.skip(f"{REFERENCE} not recorded: run this file's __main__")
  reference = dict(np.load(REFERENCE))
  recorded_on = str(reference.pop("machine"))
  got, ran_on = _outputs(tiny_models), machine()
  assert sorted(got) == sorted(reference)
  for key, want in reference.items():
    if recorded_on == ran_on:
      np.testing.assert_array_equal(got[key], want, err_msg=key)
    else:
      # A CPU with other vector units (e.g. avx512_bf16) rounds otherwise, and 5 closed-loop
      # steps amplify it: 2e-4 on one of 40 actions there; guidance's gradient steps amplify it
      # more: 4e-3 on one of 40 guided actions on an AMD EPYC against an Intel recording.
      tol = 1e-2 if "guided" in key else 1e-3
      np.testing.assert_allclose(got[key], want, rtol=tol, atol=tol, err_msg=f"{key} (recorded on {recorded_on})")


if __name__ == "__main__":   # record REFERENCE with conftest.py's XLA flags (importing it sets them)
  REFERENCE.parent.mkdir(exist_ok=True)
  np.savez_compressed(REFERENCE, machine=np.asarray(machine()), **_outputs(build_tiny_models()))
  print(f"wrote {REFERENCE} ({REFERENCE.stat().st_size} bytes)")
