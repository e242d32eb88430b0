"""Devices and hosts: one `data` mesh axis over every device of every host.

Training is data-parallel (the global batch is split along `data`; parameters
and optimizer state are replicated) and evaluation is scenario-parallel (the
vmapped closed loop's scenario batch is split along `data`). Both use JAX's
own SPMD machinery: a `jax.sharding.Mesh`, `NamedSharding`s given to `jit`,
and `jax.distributed` for several hosts.

  mesh = distributed.data_mesh()              # every device of every host
  step = jax.jit(f, in_shardings=(distributed.replicated(mesh), distributed.batch_sharded(mesh)), ...)
  batch = distributed.shard_batch(local_batch, mesh)   # this host's rows -> one global array

Several hosts: every host runs the same command; `initialize` (called by the
CLIs behind `--coordinator --num-processes --process-id`, or the environment
variables JAX_COORDINATOR_ADDRESS, JAX_NUM_PROCESSES, JAX_PROCESS_ID, or a
cluster JAX detects itself: SLURM, Open MPI, Cloud TPU) connects them before
any device is touched. Each host then feeds its own rows of the global batch
(`host_shard` splits files by process index) and only process 0 writes logs.

Test a mesh on one CPU with fake devices, set before JAX starts its backend:
`XLA_FLAGS=--xla_force_host_platform_device_count=4`.
"""
from __future__ import annotations

import os
from typing import Any, Optional, Sequence

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

DATA_AXIS = "data"

# Environment variables read by `initialize` (JAX reads the first itself).
ENV_COORDINATOR = "JAX_COORDINATOR_ADDRESS"
ENV_NUM_PROCESSES = "JAX_NUM_PROCESSES"
ENV_PROCESS_ID = "JAX_PROCESS_ID"


def _env_int(name: str) -> Optional[int]:
  value = os.environ.get(name)
  if value in (None, ""):
    return None
  try:
    return int(value)
  except ValueError:
    raise ValueError(f"environment variable {name}={value!r} is not an integer") from None


def initialize(coordinator: Optional[str] = None, num_processes: Optional[int] = None,
               process_id: Optional[int] = None, auto: bool = False) -> bool:
  """Connects this process to the others (`jax.distributed.initialize`).

  Arguments left None are read from JAX_COORDINATOR_ADDRESS, JAX_NUM_PROCESSES
  and JAX_PROCESS_ID; with `auto`, JAX detects whatever is still missing from
  its cluster (SLURM, Open MPI, Cloud TPU). Nothing happens (False is
  returned) when neither a coordinator nor a process count is given and
  `auto` is off: the single-host run. Must run before any device is used.
  """
  coordinator = coordinator or os.environ.get(ENV_COORDINATOR) or None
  num_processes = num_processes if num_processes is not None else _env_int(ENV_NUM_PROCESSES)
  process_id = process_id if process_id is not None else _env_int(ENV_PROCESS_ID)
  if coordinator is None and num_processes is None and not auto:
    return False
  if jax.distributed.is_initialized():   # a second CLI call in the same process
    return True
  jax.distributed.initialize(coordinator_address=coordinator, num_processes=num_processes,
                             process_id=process_id)
  return True


def is_primary() -> bool:
  """Whether this process writes logs, tables and figures (process 0)."""
  return jax.process_index() == 0


def data_mesh(num_devices: Optional[int] = None) -> Mesh:
  """A 1-D mesh with axis `data` over the first `num_devices` devices (default:
  every device of every host). Raises ValueError when there are fewer."""
  devices = jax.devices()
  n = len(devices) if num_devices is None else num_devices
  if not 1 <= n <= len(devices):
    raise ValueError(f"{n} device(s) asked for, {len(devices)} available ({devices[0].platform})")
  if n != len(devices) and jax.process_count() > 1:
    raise ValueError(f"with {jax.process_count()} processes the mesh takes every device "
                     f"({len(devices)}), not {n}")
  return Mesh(np.asarray(devices[:n]), (DATA_AXIS,))


def replicated(mesh: Mesh) -> NamedSharding:
  """Every device holds the whole value (parameters, optimizer state, keys)."""
  return NamedSharding(mesh, PartitionSpec())


def batch_sharded(mesh: Mesh) -> NamedSharding:
  """The leading (batch) axis is split along `data`; as a pytree prefix it
  shards every leaf of a batch."""
  return NamedSharding(mesh, PartitionSpec(DATA_AXIS))


def check_divisible(size: int, mesh: Mesh, what: str) -> None:
  """Raises ValueError unless `size` splits evenly over the mesh's devices."""
  n = mesh.devices.size
  if size % n:
    raise ValueError(f"{what} ({size}) must be a multiple of the {n} device(s) it is split over "
                     "(or take fewer devices: --devices)")


def local_batch_size(global_size: int, mesh: Mesh) -> int:
  """Rows of a global batch that this host feeds (the whole batch on one host)."""
  check_divisible(global_size, mesh, "the global batch size")
  return global_size // jax.process_count()


def host_shard(items: Sequence[Any]) -> list:
  """This process's share of `items` (e.g. TFRecord files): every
  process_count-th item from its process index. Raises ValueError when some
  host would get none."""
  n, i = jax.process_count(), jax.process_index()
  if len(items) < n:
    raise ValueError(f"{len(items)} file(s) for {n} processes: each host needs at least one")
  return list(items[i::n])


def replicate(tree: Any, mesh: Mesh) -> Any:
  """Host or single-device values -> global arrays replicated over `mesh`.
  Several processes: every one gets process 0's values (a fresh model, or
  statistics fitted on each host's own data, would otherwise differ)."""
  sharding = replicated(mesh)

  def put(x):
    if isinstance(x, jax.Array) and x.sharding == sharding:
      return x
    if jax.process_count() == 1:
      return jax.device_put(x, sharding)
    from jax.experimental import multihost_utils
    x = np.asarray(multihost_utils.broadcast_one_to_all(np.asarray(x)))
    return jax.make_array_from_callback(x.shape, sharding, lambda index: x[index])
  return jax.tree_util.tree_map(put, tree)


def shard_batch(local: Any, mesh: Mesh) -> Any:
  """This host's rows of a batch (numpy, leading axis) -> global arrays split
  along `data`; the global batch is the hosts' rows in process order."""
  sharding = batch_sharded(mesh)
  return jax.tree_util.tree_map(
      lambda x: jax.make_array_from_process_local_data(sharding, np.asarray(x)), local)


def local_copy(tree: Any) -> Any:
  """Replicated global arrays -> this process's copy on its first device (for
  code that runs on one device per host, e.g. validation)."""
  return jax.tree_util.tree_map(
      lambda x: x.addressable_data(0) if isinstance(x, jax.Array) else x, tree)


def agree(flag: bool) -> bool:
  """Process 0's `flag` on every process (a decision all hosts must take
  together, e.g. stopping on a time budget); `flag` itself on one host."""
  if jax.process_count() == 1:
    return flag
  from jax.experimental import multihost_utils
  return bool(multihost_utils.broadcast_one_to_all(np.asarray(flag)))


def to_host(tree: Any) -> Any:
  """Global arrays (any sharding) -> numpy on every host (an all-gather across
  processes when there are several)."""
  if jax.process_count() == 1:
    return jax.device_get(tree)
  from jax.experimental import multihost_utils
  return multihost_utils.process_allgather(tree, tiled=True)
