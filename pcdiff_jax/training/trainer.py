"""A small, stage-agnostic training loop: AdamW, orbax checkpoints, scalars, resume.

`fit` drives any stage given a pure `loss_fn(params, batch, rng) -> (loss,
metrics)`, a `batch_at(step)` that is a pure function of the step (so a
resumed run sees the same batches) and an `evaluate(params) -> metrics`.

Files under the work directory:
  checkpoints/<step>/{state,config}: orbax; the full Config is saved with every
    checkpoint and a resumed run must use the same one (a clear error names
    the fields that differ).
  tb/: TensorBoard event files (tf.summary); metrics.jsonl: the same scalars,
    one JSON line per log (train/... and val/...).
Interrupts (Ctrl-C, SIGTERM) save a checkpoint at the last finished step
before exiting; a hard kill loses at most `checkpoint_every` steps.
"""
from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import time
from typing import Any, Callable, Optional

import jax
import jax.numpy as jnp
import numpy as np
import optax
import orbax.checkpoint as ocp
from flax import struct
from jax.sharding import Mesh

from pcdiff_jax import distributed
from pcdiff_jax import config as config_lib
from pcdiff_jax.config import TrainConfig
from pcdiff_jax.sim.datatypes import Array

log = logging.getLogger(__name__)


@struct.dataclass
class TrainState:
  step: Array        # () int32, optimizer steps taken
  params: Any
  opt_state: Any
  rng: Array         # (2,) uint32 raw key data (checkpoint-friendly)
  extra: Any         # frozen arrays saved with the checkpoint (e.g. latent statistics)


def learning_rate_schedule(cfg: TrainConfig) -> optax.Schedule:
  warmup = max(min(cfg.warmup_steps, cfg.total_steps - 1), 0)
  return optax.warmup_cosine_decay_schedule(
      init_value=0.0, peak_value=cfg.learning_rate, warmup_steps=warmup,
      decay_steps=max(cfg.total_steps, warmup + 1),
      end_value=cfg.learning_rate * cfg.final_lr_fraction)


def make_optimizer(cfg: TrainConfig) -> optax.GradientTransformation:
  return optax.chain(optax.clip_by_global_norm(cfg.grad_clip),
                     optax.adamw(learning_rate_schedule(cfg), weight_decay=cfg.weight_decay))


def create_state(params: Any, tx: optax.GradientTransformation, seed: int,
                 extra: Any = None) -> TrainState:
  return TrainState(step=jnp.zeros((), jnp.int32), params=params, opt_state=tx.init(params),
                    rng=jax.random.key_data(jax.random.key(seed)),
                    extra={} if extra is None else extra)


LossFn = Callable[..., tuple[Array, dict]]


def make_train_step(loss_fn: LossFn, tx: optax.GradientTransformation, with_extra: bool = False,
                    mesh: Optional[Mesh] = None):
  """jit((state, batch) -> (state, metrics)); metrics gain grad_norm.

  loss_fn(params, batch, rng) -> (loss, metrics), or with_extra
  loss_fn(params, extra, batch, rng) where `extra` is the state's frozen part.
  With a `mesh` (`pcdiff_jax.distributed.data_mesh`) the step is data-parallel:
  the batch is split along its `data` axis, the state and the metrics are
  replicated, and the loss (a mean over the global batch) is the one device's
  up to the order of float sums: XLA inserts the gradient all-reduce.
  """
  def train_step(state: TrainState, batch: Any):
    key = jax.random.fold_in(jax.random.wrap_key_data(state.rng), state.step)
    fn = (lambda p: loss_fn(p, state.extra, batch, key)) if with_extra else \
        (lambda p: loss_fn(p, batch, key))
    (_, metrics), grads = jax.value_and_grad(fn, has_aux=True)(state.params)
    updates, opt_state = tx.update(grads, state.opt_state, state.params)
    params = optax.apply_updates(state.params, updates)
    metrics = dict(metrics, grad_norm=optax.global_norm(grads))
    return state.replace(step=state.step + 1, params=params, opt_state=opt_state), metrics
  if mesh is None:
    return jax.jit(train_step, donate_argnums=0)
  rep = distributed.replicated(mesh)
  return jax.jit(train_step, in_shardings=(rep, distributed.batch_sharded(mesh)),
                 out_shardings=(rep, rep), donate_argnums=0)


def count_params(params: Any) -> int:
  return int(sum(np.prod(x.shape) for x in jax.tree_util.tree_leaves(params)))


# ----------------------------------------------------------------------------
# Checkpoints.


class CheckpointMismatch(ValueError):
  pass


# Fields a resumed run may change: they do not alter what was learned so far
# (a longer run stretches the cosine decay from the resumed step on).
RESUMABLE_FIELDS = frozenset({"total_steps", "log_every", "eval_every", "checkpoint_every",
                              "eval_batch_size", "keep_checkpoints"})


def _diff(a: Any, b: Any, prefix: str = "") -> list[str]:
  if isinstance(a, dict) and isinstance(b, dict):
    out = []
    for k in sorted(set(a) | set(b)):
      if k in RESUMABLE_FIELDS:
        continue
      out += _diff(a.get(k), b.get(k), f"{prefix}{k}.")
    return out
  if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
    a, b = list(a), list(b)
  return [] if a == b else [f"{prefix[:-1]}: saved {a!r}, now {b!r}"]


def _with_defaults(saved: dict) -> dict:
  """A saved Config dict with the fields added since it was saved at their
  defaults (so a run saved before a new option resumes when it is off)."""
  try:
    return config_lib.to_dict(config_lib.from_dict(saved))
  except (ValueError, TypeError):   # not a whole Config (or a field since removed): compare as saved
    return saved


class _DropReadOnlyNotice(logging.Filter):
  """orbax warns "Given directory is read only" each time a model is loaded
  read-only, which is what loading is, and "Metadata file does not exist" when
  a step's metadata is read: those messages only, not warnings."""

  def filter(self, record: logging.LogRecord) -> bool:
    msg = str(record.msg)
    return not (msg.startswith("Given directory is read only") or msg.startswith("Metadata file does not exist"))


@contextlib.contextmanager
def _quiet_orbax_notices():
  quiet = _DropReadOnlyNotice()
  logging.getLogger("absl").addFilter(quiet)
  try:
    yield
  finally:
    logging.getLogger("absl").removeFilter(quiet)


class Checkpointer:
  """orbax CheckpointManager holding {state, config} under WORKDIR/checkpoints."""

  def __init__(self, workdir: str, keep: int = 2, read_only: bool = False):
    self.directory = os.path.abspath(os.path.join(workdir, "checkpoints"))
    if read_only and not os.path.isdir(self.directory):
      raise FileNotFoundError(f"no checkpoint in {self.directory}")
    with _quiet_orbax_notices():
      self.manager = ocp.CheckpointManager(
          self.directory, item_names=("state", "config"),
          options=ocp.CheckpointManagerOptions(
              max_to_keep=None if read_only else keep, save_interval_steps=0 if read_only else 1,
              create=not read_only, read_only=read_only, enable_async_checkpointing=False))

  def latest_step(self) -> Optional[int]:
    return self.manager.latest_step()

  def save(self, state: TrainState, config: dict) -> None:
    step = int(state.step)
    if step in self.manager.all_steps():
      return
    self.manager.save(step, args=ocp.args.Composite(
        state=ocp.args.StandardSave(state), config=ocp.args.JsonSave(config)))
    self.manager.wait_until_finished()

  def save_raw(self, step: int, tree: Any, config: dict) -> None:
    """Saves any pytree of arrays (e.g. a TrainState without its optimizer
    state, `pretrained.export`) as step `step`; `restore_raw` reads it back."""
    self.manager.save(step, args=ocp.args.Composite(
        state=ocp.args.StandardSave(tree), config=ocp.args.JsonSave(config)))
    self.manager.wait_until_finished()

  def read_config(self, step: Optional[int] = None) -> dict:
    step = self.latest_step() if step is None else step
    if step is None:
      raise FileNotFoundError(f"no checkpoint in {self.directory}")
    return self.manager.restore(step, args=ocp.args.Composite(config=ocp.args.JsonRestore()))["config"]

  def restore(self, like: TrainState, step: Optional[int] = None) -> TrainState:
    step = self.latest_step() if step is None else step
    if step is None:
      raise FileNotFoundError(f"no checkpoint in {self.directory}")
    abstract = jax.tree_util.tree_map(ocp.utils.to_shape_dtype_struct, like)
    try:
      out = self.manager.restore(step, args=ocp.args.Composite(state=ocp.args.StandardRestore(abstract)))
    except (ValueError, KeyError, TypeError) as err:
      raise CheckpointMismatch(
          f"checkpoint {self.directory}/{step} does not match this model: {err}") from err
    return out["state"]

  def restore_raw(self, step: Optional[int] = None) -> dict:
    """The saved TrainState as nested dicts of arrays (no template needed): for
    loading parameters into inference code whatever the optimizer was."""
    step = self.latest_step() if step is None else step
    if step is None:
      raise FileNotFoundError(f"no checkpoint in {self.directory}")
    out = self.manager.restore(step, args=ocp.args.Composite(
        state=ocp.args.StandardRestore(self._abstract_on_this_device(step))))
    return out["state"]

  def _abstract_on_this_device(self, step: int) -> Any:
    """The saved tree's shapes and dtypes on this process's first device.
    Without a target orbax restores each array onto the device it was saved
    from, which fails across machines ("Topology mismatch": a model saved on a
    CPU, read on a GPU)."""
    path = os.path.join(self.directory, str(step), "state")
    with _quiet_orbax_notices(), ocp.StandardCheckpointer() as reader:
      meta = reader.metadata(path)
    tree = getattr(meta, "item_metadata", meta)
    tree = getattr(tree, "tree", tree)
    device = jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
    return jax.tree_util.tree_map(
        lambda m: jax.ShapeDtypeStruct(m.shape, m.dtype, sharding=device) if hasattr(m, "shape") else m,
        tree)

  def restore_or_keep(self, state: TrainState, config: dict,
                      compare: Optional[tuple[str, ...]] = None) -> TrainState:
    """Resumes from the latest checkpoint when there is one, else returns `state`.

    Raises CheckpointMismatch when the saved config differs from `config` in
    the top-level sections `compare` (default: all).
    """
    if self.latest_step() is None:
      return state
    saved = _with_defaults(self.read_config())
    if compare is not None:
      saved = {k: saved.get(k) for k in compare}
      config = {k: config.get(k) for k in compare}
    diff = _diff(saved, config)
    if diff:
      raise CheckpointMismatch(
          f"{self.directory} holds a run with another config ({'; '.join(diff[:6])}); "
          "use a new --workdir or the same config")
    return self.restore(state)

  def close(self) -> None:
    self.manager.close()


# ----------------------------------------------------------------------------
# Scalars.


class ScalarLog:
  """TensorBoard event files (tf.summary) and a metrics.jsonl beside them."""

  def __init__(self, workdir: str):
    os.makedirs(workdir, exist_ok=True)
    self._jsonl = open(os.path.join(workdir, "metrics.jsonl"), "a")
    try:
      from pcdiff_jax.data import womd
      womd.quiet_tensorflow_env()
      import tensorflow as tf
      from tensorflow.core.framework import summary_pb2
    except ImportError:  # event files are a convenience; jsonl always works
      self._tf = self._writer = None
      return
    self._tf = tf
    self._writer = tf.summary.create_file_writer(os.path.join(workdir, "tb"))
    # What tensorboard's own scalar summary writes; tf.summary.scalar itself
    # needs the tensorboard package, which is not a dependency.
    self._meta = summary_pb2.SummaryMetadata(
        plugin_data=summary_pb2.SummaryMetadata.PluginData(plugin_name="scalars"))

  def write(self, step: int, scalars: dict) -> None:
    scalars = {k: float(v) for k, v in scalars.items()}
    self._jsonl.write(json.dumps({"step": step, "time": time.time(), **scalars}) + "\n")
    self._jsonl.flush()
    if self._writer is not None:
      with self._writer.as_default():
        for k, v in scalars.items():
          self._tf.summary.write(k, self._tf.constant(v, self._tf.float32), step=step,
                                 metadata=self._meta)
      self._writer.flush()

  def close(self) -> None:
    self._jsonl.close()
    if self._writer is not None:
      self._writer.close()


class _NoScalars:
  """ScalarLog's stand-in on hosts other than process 0."""

  def write(self, step: int, scalars: dict) -> None:
    pass

  def close(self) -> None:
    pass


@contextlib.contextmanager
def _sigterm_as_interrupt():
  previous = signal.getsignal(signal.SIGTERM)

  def handler(signum, frame):
    raise KeyboardInterrupt(f"signal {signum}")
  try:
    signal.signal(signal.SIGTERM, handler)
  except ValueError:  # not the main thread
    previous = None
  try:
    yield
  finally:
    if previous is not None:
      signal.signal(signal.SIGTERM, previous)


# ----------------------------------------------------------------------------
# The loop.


def fit(state: TrainState, train_step: Callable, batch_at: Callable[[int], Any],
        evaluate: Optional[Callable[[Any], dict]], cfg: TrainConfig, workdir: str, config: dict,
        desc: str = "train", max_minutes: Optional[float] = None, progress: bool = True,
        schedule: Optional[optax.Schedule] = None,
        compare: Optional[tuple[str, ...]] = None,
        evaluate_state: bool = False, mesh: Optional[Mesh] = None) -> tuple[TrainState, dict]:
  """Trains until `cfg.total_steps` (or `max_minutes`), resuming from `workdir`.

  `compare`: the config sections a resumed run must match (default: all).
  `evaluate` gets the parameters, or the whole TrainState if `evaluate_state`.
  `mesh`: data-parallel training (`train_step` from `make_train_step(...,
  mesh=mesh)`): the state is replicated over the mesh, `batch_at(step)` gives
  this host's rows of the global batch, validation runs on one device per host
  and only process 0 writes scalars. A checkpoint holds whole arrays, so a run
  resumes on any device count.

  Returns the final state and the last validation metrics ({} if none ran).
  """
  from tqdm.auto import tqdm
  ckpt = Checkpointer(workdir, cfg.keep_checkpoints)
  if mesh is not None:   # the restore target: orbax reads each array straight onto the mesh
    state = distributed.replicate(state, mesh)
  state = ckpt.restore_or_keep(state, config, compare)
  # Host numpy leaves (restored or frozen) -> arrays committed to one device
  # (or replicated over the mesh), like the step's outputs, so the first and
  # later steps compile once.
  state = (jax.device_put(state, jax.devices()[0]) if mesh is None
           else distributed.replicate(state, mesh))
  primary = distributed.is_primary()
  progress = progress and primary
  start = int(state.step)
  if start:
    log.info("resumed %s from step %d (%s)", desc, start, ckpt.directory)
  scalars = ScalarLog(workdir) if primary else _NoScalars()
  last_eval: dict = {}
  t0 = time.time()

  def run_eval(step):
    nonlocal last_eval
    if evaluate is None or not primary:
      return
    here = state if mesh is None else distributed.local_copy(state)
    last_eval = evaluate(here if evaluate_state else here.params)
    scalars.write(step, {f"val/{k}": v for k, v in last_eval.items()})
    tqdm.write(f"[{desc}] step {step} val " + " ".join(f"{k}={v:.4g}" for k, v in last_eval.items()))

  bar = tqdm(total=cfg.total_steps, initial=start, desc=desc, unit="step", disable=not progress,
             dynamic_ncols=True)
  pending: list[dict] = []
  window_start, window_steps = time.time(), 0
  try:
    with _sigterm_as_interrupt():
      for step in range(start, cfg.total_steps):
        batch = batch_at(step)
        if mesh is not None:
          batch = distributed.shard_batch(batch, mesh)
        state, metrics = train_step(state, batch)
        pending.append(metrics)
        window_steps += 1
        done = step + 1
        bar.update(1)
        if done % cfg.log_every == 0 or done == cfg.total_steps:
          means = {k: float(np.mean([float(m[k]) for m in pending])) for k in pending[0]}
          rate = window_steps / max(time.time() - window_start, 1e-9)
          extra = {"steps_per_s": rate}
          if schedule is not None:
            extra["lr"] = float(schedule(done))
          scalars.write(done, {**{f"train/{k}": v for k, v in means.items()}, **extra})
          bar.set_postfix(loss=f"{means['loss']:.3f}", it_s=f"{rate:.2f}")
          pending, window_start, window_steps = [], time.time(), 0
        if done % cfg.checkpoint_every == 0:
          ckpt.save(state, config)
        if done % cfg.eval_every == 0 and done != cfg.total_steps:
          run_eval(done)
        if max_minutes is not None and distributed.agree(time.time() - t0 > 60 * max_minutes):
          tqdm.write(f"[{desc}] time budget of {max_minutes} min reached at step {done}")
          break
  except KeyboardInterrupt:
    bar.close()
    ckpt.save(state, config)
    if primary:
      tqdm.write(f"[{desc}] interrupted: saved step {int(state.step)} in {ckpt.directory}")
    scalars.close()
    ckpt.close()
    raise
  bar.close()
  ckpt.save(state, config)
  run_eval(int(state.step))
  scalars.close()
  ckpt.close()
  return state, last_eval
