"""The one batch runner of tlsjax: many realisations of one computation as a compiled ``vmap``,
in chunks of a fixed size, sharded over the process's JAX devices along the batch axis, and
over the processes of a multi-process run (``jax.distributed``).

Monte Carlo self-calibration and the AP-set compatibility test both run through it. A chunk of
indices ``k`` is mapped by ``one(k, *constants)``; the constants (seed key, tolerances, AP sets)
are replicated arguments of the compiled function, so changing them never recompiles. Chunk
sizes are rounded up to a multiple of the local device count, so every device gets the same
share.

**Past one machine.** The realisations are cut into *slices* of the per-device batch (the
chunk over the local device count). With ``jax.distributed.initialize(...)`` called first,
process p of P computes the slices ``s = p, p + P, p + 2P, ...`` on its own devices (no
communication while it runs), and the results are gathered to every process at the end
(``multihost_utils.process_allgather``). A slice's results depend only on its indices and the
per-device batch, so a run over several processes equals, bit for bit, one process with the
same per-device batch and seed (tested with two processes on one machine).
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import time

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from .._jit import jit


def device_mesh() -> Mesh:
    """One mesh axis, "batch", over the process's devices (a no-op on one CPU device)."""
    return Mesh(np.array(jax.local_devices()), ("batch",))


def device_key() -> tuple:
    """What a compiled batch function depends on besides its arguments: the devices."""
    return tuple(str(d) for d in jax.local_devices())


#: Working set of one device's share of a compiled call [bytes] when the user gives no chunk
#: size: the Jacobian rows of its realisations. On 2 CPU devices 1,000 Chow-room realisations
#: ran fastest with about 2-5 MB per device and slowed by a quarter or more above 8 MB (4 APs,
#: 225 kB per realisation: 1.51 / 1.25 / 1.23 / 1.59 s with 5 / 10 / 20 / 40 per device; 23 APs,
#: 553 kB: 3.47-3.63 s with 3 / 5 / 10, 5.26 s with 16; measured 2026-11-24 in one process,
#: alternately).
DEVICE_WORKING_SET = 4e6


def round_chunk(chunk_size: int) -> int:
    """``chunk_size`` rounded up to a multiple of the device count."""
    n_dev = jax.local_device_count()
    return int(math.ceil(int(chunk_size) / n_dev) * n_dev)


def auto_chunk(bytes_per_item: float, runs: int) -> int:
    """Items per compiled call: as many per device as fit the device's working set (see
    :func:`device_working_set`), but no more than ``runs`` need; a multiple of the device count."""
    n_dev = jax.local_device_count()
    budget, cap = device_working_set()
    per_device = int(min(max(budget // max(bytes_per_item, 1.0), 1), cap))
    return round_chunk(min(per_device * n_dev, int(runs)))


#: Most members of a chunk on one accelerator: beyond a few thousand the vmapped solve gains
#: nothing and the last chunk's padding costs more.
ACCELERATOR_MAX_ITEMS = 4096


def device_working_set() -> tuple[float, int]:
    """(bytes, most items) of one device's share of a chunk.

    A CPU core runs a chunk's members one after another through its cache, so the share is kept
    near :data:`DEVICE_WORKING_SET`. An accelerator runs them side by side and idles while the
    host launches the next chunk, so its share is as large as its memory allows: an eighth of
    the memory XLA may use (the Jacobian rows are a fraction of a member's buffers), at most
    :data:`ACCELERATOR_MAX_ITEMS` members."""
    d = jax.local_devices()[0]
    if d.platform == "cpu":
        return DEVICE_WORKING_SET, 64
    try:
        limit = float((d.memory_stats() or {}).get("bytes_limit", 0.0))
    except Exception:  # noqa: BLE001 - a backend without memory statistics
        limit = 0.0
    return (limit / 8 if limit > 0 else 1e9), ACCELERATOR_MAX_ITEMS


@dataclasses.dataclass(frozen=True, eq=False)
class Batched:
    """A compiled chunk function ``indices (chunk,) -> pytree of (chunk, ...) arrays``."""

    compiled: object
    chunk: int
    batched: NamedSharding
    replicated: NamedSharding
    compile_s: float


def compile_batched(one, constants, chunk: int) -> Batched:
    """Compile ``vmap(one)`` over a chunk of int64 indices, ahead of time.

    ``constants``: example values (arrays or pytrees of arrays, e.g. the solver options) of the
    replicated arguments.
    """
    mesh = device_mesh()
    batched = NamedSharding(mesh, PartitionSpec("batch"))
    replicated = NamedSharding(mesh, PartitionSpec())
    n_const = len(constants)
    # Each device maps its own share (shard_map): the realisations are independent, so
    # nothing passes between devices. Partitioned by XLA instead (jit with shardings), a
    # vmapped while loop all-reduced its condition over the devices every iteration, and
    # library calls on batched operands (LAPACK) were all-gathered: half a Monte Carlo's time
    # on 2 CPU devices waited in collectives (measured, Chow room).
    fn = jit(
        jax.shard_map(
            jax.vmap(one, in_axes=(0,) + (None,) * n_const),
            mesh=mesh,
            in_specs=(PartitionSpec("batch"),) + (PartitionSpec(),) * n_const,
            out_specs=PartitionSpec("batch"),
            check_vma=False,
        ),
        in_shardings=(batched,) + (replicated,) * n_const,
        out_shardings=batched,
    )
    specs = jax.tree.map(
        lambda c: jax.ShapeDtypeStruct(jnp.shape(c), jnp.result_type(c), sharding=replicated),
        tuple(constants),
    )
    t0 = time.perf_counter()
    compiled = fn.lower(
        jax.ShapeDtypeStruct((chunk,), jnp.int64, sharding=batched), *specs
    ).compile()
    return Batched(compiled, chunk, batched, replicated, time.perf_counter() - t0)


def run_batched(b: Batched, n: int, constants, *, desc: str, progress: bool, indices=None):
    """Run realisations ``0 .. n-1`` (or ``indices``) in chunks, this process's share of the
    slices when there are several processes (module docstring); returns (pytree of (n, ...)
    numpy arrays in that order, on every process, and seconds)."""
    from tqdm.auto import tqdm

    idx = np.arange(n, dtype=np.int64) if indices is None else np.asarray(indices, np.int64)
    n = len(idx)
    size = b.chunk // jax.local_device_count()  # one slice: a device's share of a chunk
    n_slices = -(-n // size)
    procs, me = jax.process_count(), jax.process_index()
    mine = np.arange(me, n_slices, procs)
    # The slices padded with the last index (their results are dropped); a process without a
    # slice computes one padding chunk, so that every process has results of the same shape.
    slices = np.concatenate([idx, np.full(n_slices * size - n, idx[-1])]).reshape(-1, size)
    slots = slices[mine].reshape(-1)
    fill = (-len(slots)) % b.chunk if len(slots) else b.chunk
    slots = np.concatenate([slots, np.full(fill, idx[-1])])
    consts = jax.device_put(tuple(constants), b.replicated)
    parts = []
    t0 = time.perf_counter()
    for c in tqdm(range(len(slots) // b.chunk), desc=desc, unit="chunk", disable=not progress):
        chunk = slots[c * b.chunk : (c + 1) * b.chunk]
        parts.append(
            jax.tree.map(np.asarray, b.compiled(jax.device_put(chunk, b.batched), *consts))
        )
    out = jax.tree.map(lambda *a: np.concatenate(a), *parts)
    if procs > 1:
        out = _gather(out, n_slices, size, procs)
    run_s = time.perf_counter() - t0
    return jax.tree.map(lambda a: a[:n], out), run_s


def _gather(local, n_slices, size, procs):
    """Every process's slices (``p, p + P, ...``), gathered to every process in slice order."""
    from jax.experimental import multihost_utils

    rows = -(-n_slices // procs) * size  # the most any process holds

    def fixed(a):  # every process sends the same shape
        extra = np.zeros((max(rows - len(a), 0),) + a.shape[1:], a.dtype)
        return np.concatenate([a[:rows], extra])

    _wait_for_all()
    every = multihost_utils.process_allgather(jax.tree.map(fixed, local))

    def order(a):  # a: (P, rows, ...)
        out = np.empty((n_slices, size) + a.shape[2:], a.dtype)
        for p in range(procs):
            theirs = np.arange(p, n_slices, procs)
            out[theirs] = a[p, : len(theirs) * size].reshape((len(theirs), size) + a.shape[2:])
        return out.reshape((n_slices * size,) + a.shape[2:])

    return jax.tree.map(order, every)


#: How long a process waits at the gather for the others to finish their share [ms]. The
#: processes of one run differ by their compile and run times (seconds to minutes on a loaded
#: machine), and the CPU collective's own connect timeout (gloo, 30 s) is shorter than that.
GATHER_WAIT_MS = 3_600_000
_BARRIERS = itertools.count()


def _wait_for_all():
    """A barrier of every process, with :data:`GATHER_WAIT_MS` (each call a new barrier id,
    the same sequence on every process)."""
    # JAX has no public barrier with a timeout: multihost_utils.sync_global_devices is itself a
    # collective under gloo's 30 s connect timeout; the coordination client's barrier waits.
    from jax._src import distributed

    client = distributed.global_state.client
    if client is not None:
        client.wait_at_barrier(f"tlsjax_gather_{next(_BARRIERS)}", GATHER_WAIT_MS)
