"""Shared pieces of the command-line handlers."""

from __future__ import annotations

import os

from ._checks import positive_float, positive_int

EXIT_OK, EXIT_FAILED, EXIT_BAD_INPUT, EXIT_INTERNAL = 0, 1, 2, 3
#: ``tlsjax calibrate``: a calibration that does not improve the prediction of held-out scans.
EXIT_NOT_IMPROVED = 4


def scanner_args(p, default="hybrid", default_help="hybrid"):
    p.add_argument(
        "--architecture",
        choices=("hybrid", "panoramic"),
        default=default,
        help=f"scanner architecture (default: {default_help})",
    )
    p.add_argument(
        "--unit-length",
        type=positive_float,
        default=1.2,
        metavar="M",
        help="unit length U [m] of the cyclic range terms A3/A4 (default 1.2)",
    )


def available_cpus() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def devices_arg(p):
    p.add_argument(
        "--devices",
        type=positive_int,
        default=available_cpus(),
        metavar="N",
        help="split the CPU into N JAX devices and shard the realisations over them "
        "(default: the CPUs available; results do not depend on it)",
    )


def use_host_devices(n: int) -> None:
    """Ask XLA for ``n`` CPU devices (JAX's public ``jax_num_cpu_devices`` option). The count
    is read when JAX's backend starts, so this must run before the first computation; later
    (tests calling ``main`` in-process) JAX refuses the change and nothing is changed. A batch
    of realisations is sharded over every device (``_simulation._batch``): on a CPU without
    another device, each core then runs its own share."""
    if n <= 1 or "xla_force_host_platform_device_count" in os.environ.get("XLA_FLAGS", ""):
        return
    import jax

    try:
        jax.config.update("jax_num_cpu_devices", int(n))
    except RuntimeError:  # the backend has started: the device count is fixed
        pass
    except AttributeError:  # pragma: no cover - a JAX before the option: its XLA flag
        flag = f"--xla_force_host_platform_device_count={int(n)}"
        os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " " + flag).strip()
