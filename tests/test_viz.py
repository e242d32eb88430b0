"""Rendering smoke tests on the real WOMD example (skipped when it is absent)."""
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from matplotlib.colors import to_rgb
from PIL import Image

from pcdiff_jax import viz

RECORD = Path(__file__).resolve().parents[2] / "shared/data/womd/motion_data_one_example.tfrecord"


@pytest.fixture(scope="module")
def state():
  if not RECORD.exists():
    pytest.skip(f"WOMD example record not found at {RECORD}")
  from pcdiff_jax.data import womd
  from pcdiff_jax.sim import env
  state, _ = womd.load(str(RECORD))
  return env.reset(state)   # a loaded state has only t = 0 simulated (Waymax's loader)


def _with_map_features(state):
  """Writes a crosswalk, a speed bump and a stop sign next to the SDC into padded roadgraph slots."""
  rg = jax.tree_util.tree_map(np.array, state.roadgraph_points)
  sdc = int(np.argmax(np.asarray(state.object_metadata.is_sdc)))
  cx, cy = float(state.log_trajectory.x[sdc, 10]), float(state.log_trajectory.y[sdc, 10])
  s = np.arange(0, 1, 0.05)
  crosswalk = np.concatenate([np.stack([cx + 8 * s, cy - 4 + 0 * s], -1),
                              np.stack([cx + 8 + 0 * s, cy - 4 + 3 * s], -1),
                              np.stack([cx + 8 - 8 * s, cy - 1 + 0 * s], -1),
                              np.stack([cx + 0 * s, cy - 1 - 3 * s], -1)])
  bump = np.stack([cx - 6 + 4 * s, cy + 5 + 0 * s], -1)
  feats = [(crosswalk, 18), (bump, 19), (np.array([[cx - 3, cy - 3]]), 17)]
  i = np.flatnonzero(~rg.valid)[0]
  for k, (xy, kind) in enumerate(feats):
    n = len(xy)
    rg.x[i:i + n], rg.y[i:i + n] = xy[:, 0], xy[:, 1]
    rg.types[i:i + n], rg.ids[i:i + n], rg.valid[i:i + n] = kind, 10_000 + k, True
    i += n
  return state.replace(roadgraph_points=rg)


def test_scene_png(state, tmp_path):
  path = viz.render_scene_png(state, tmp_path / "scene.png", timestep=10)
  img = Image.open(path)
  assert img.format == "PNG" and img.size == (800, 800)
  rgb = np.asarray(img.convert("RGB")).astype(int)
  assert len(np.unique(rgb.reshape(-1, 3), axis=0)) > 30
  # The view is centred on the SDC, so its red box fills part of the centre.
  sdc = np.array(to_rgb(viz.SDC_COLOR)) * 255
  centre = rgb[300:500, 300:500]
  assert (np.abs(centre - sdc).max(-1) < 20).sum() > 50


def test_rollout_gif(state, tmp_path):
  path = viz.render_rollout_gif(state, tmp_path / "roll.gif", start=10, stop=15)
  img = Image.open(path)
  assert img.format == "GIF" and img.n_frames == 6 and img.size == (480, 480)
  assert img.info["loop"] == 0 and img.info["duration"] == 100


def test_map_features_and_grid(state, tmp_path):
  plain = viz.render_scene_png(state, tmp_path / "plain.png", timestep=10, view_radius=20.0)
  extra = viz.render_scene_png(_with_map_features(state), tmp_path / "extra.png", timestep=10,
                               view_radius=20.0)
  diff = np.asarray(Image.open(plain).convert("RGB")) != np.asarray(Image.open(extra).convert("RGB"))
  assert diff.any(-1).sum() > 500  # crosswalk, speed bump and stop sign were drawn
  roles = np.asarray(state.object_metadata.is_modeled)
  path = viz.render_grid_png([state, state, state], tmp_path / "grid.png", ncols=2,
                             titles=["a", "b", "c"], timestep=jnp.asarray(12), roles=roles,
                             trajectory="log")
  assert Image.open(path).size == (800, 800)


def test_rejects_batched_state(state):
  batched = jax.tree_util.tree_map(lambda x: x[None], state)
  with pytest.raises(ValueError, match="unbatched"):
    viz.render_scene_png(batched, "/dev/null")
