"""The train step's precision on this machine: ``train_precision="auto"`` times both, bfloat16 where it pays.

bfloat16 products (:attr:`TrainConfig.train_precision`) pay where the hardware multiplies bfloat16 faster and
the step is made of large products, such as the paper's wide network on a CPU with AMX units. Where the
step is bound by the softmax and by narrow attention heads (the ``cpu`` recipe on a CPU), they add
conversions and gain nothing. Rather than guess from the hardware's name, "auto" compiles the step at both
precisions, times a few steps of each on the run's first training batch, and takes bfloat16 only where it is
at least :data:`MARGIN` times as fast. The choice is kept with the compiled programs
(:func:`dit_jax.network.compile_cache.memo`), keyed by the machine, the network and the step's shapes, so a machine
measures each recipe once; a run records the precision it chose in its ``train_config.json``, so resuming
it never measures again.
"""

from __future__ import annotations

import dataclasses
import math
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable

import jax
import numpy as np
import optax
from jax.sharding import Mesh

from dit_jax.network import compile_cache
from dit_jax.training import step as step_lib
from dit_jax.training.config import TrainConfig

#: bfloat16 must give at least this many times float32's pairs per second to be chosen: a step's time moves
#: by several per cent between runs, and float32 keeps the model's own numbers.
MARGIN = 1.15


@dataclasses.dataclass(frozen=True)
class PrecisionChoice:
    """What "auto" chose, and from what.

    Attributes:
      precision: the train step's precision: None (the model's own) or "bfloat16".
      float32_step_s, bfloat16_step_s: median seconds of a step at each precision, as measured.
      cached: the choice was read from the cache, not measured in this process.
    """

    precision: str | None
    float32_step_s: float
    bfloat16_step_s: float
    cached: bool = False

    @property
    def speedup(self) -> float:
        """bfloat16's pairs per second over float32's."""
        return self.float32_step_s / self.bfloat16_step_s

    def describe(self) -> str:
        """One line for the console."""
        chosen = "bfloat16" if self.precision == "bfloat16" else "float32"
        source = "cached measurement" if self.cached else "measured now"
        return (
            f"train precision: {chosen} (a bfloat16 step {self.bfloat16_step_s:.3g} s, float32 "
            f"{self.float32_step_s:.3g} s: {self.speedup:.2f}x; bfloat16 needs {MARGIN}x; {source})"
        )


def decide(float32_step_s: float, bfloat16_step_s: float, margin: float = MARGIN) -> str | None:
    """The precision to train at, from the two steps' times: "bfloat16" where it gives at least ``margin``
    times float32's pairs per second, else None (the model's own)."""
    return "bfloat16" if float32_step_s >= margin * bfloat16_step_s else None


def cpu_model() -> str:
    """The CPU's model name as ``lscpu`` gives it (from /proc/cpuinfo), else the platform's processor."""
    try:
        with open("/proc/cpuinfo") as f:
            return next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        return platform.processor() or platform.machine()


def machine() -> tuple[str, ...]:
    """What a step's speed depends on besides the program: the backend, its devices, the CPU and XLA's flags."""
    devices = jax.devices()
    return (
        jax.default_backend(),
        devices[0].device_kind,
        str(len(devices)),
        cpu_model(),
        str(os.cpu_count()),
        os.environ.get("XLA_FLAGS", ""),
    )


def time_steps(
    config: TrainConfig, optimizer: optax.GradientTransformation, mesh: Mesh, batch: dict, steps: int
) -> float:
    """Median seconds of ``steps`` train steps of ``config`` on ``batch`` (after one that compiles), from fresh
    parameters. ``batch``: a training batch on the host (``src``, ``tgt``: (B, N, 3); ``R``: (B, 3, 3); ``t``:
    (B, 3))."""
    step = step_lib.make_train_step(config, optimizer, mesh)
    state = step_lib.replicate(step_lib.init_state(config, optimizer), mesh)
    batch = step_lib.shard_batch(batch, mesh)
    times = []
    for _ in range(steps + 1):
        start = time.perf_counter()
        state, out = step(state, batch)
        out["loss"].block_until_ready()
        times.append(time.perf_counter() - start)
    return statistics.median(times[1:])


def choose(
    config: TrainConfig,
    optimizer: optax.GradientTransformation,
    mesh: Mesh,
    batch: dict,
    *,
    steps: int = 3,
    timer: Callable[..., float] | None = None,
) -> PrecisionChoice:
    """Measures (or reads from the cache) the step of ``config`` on ``batch`` (see :func:`time_steps`) at both
    precisions and chooses by :func:`decide`. ``config.train_precision`` is ignored; ``timer`` times one
    candidate, with :func:`time_steps`'s arguments (by default :func:`time_steps` itself).

    In a multi-process run every process measures (a step spans all of them, so none may skip it on a cache
    hit of its own) and takes process 0's choice, so all compile the same step."""
    shapes = tuple(sorted((name, np.shape(value)) for name, value in batch.items()))
    parts = ("train_precision", machine(), repr(sorted(config.model.to_dict().items())), shapes)
    parts += (config.train_iters, config.differentiable, config.correspondence_weight > 0)
    measured = []
    timer = timer or time_steps

    def measure():
        seconds = [timer(dataclasses.replace(config, train_precision=None), optimizer, mesh, batch, steps)]
        try:
            seconds.append(
                timer(dataclasses.replace(config, train_precision="bfloat16"), optimizer, mesh, batch, steps)
            )
        except Exception as error:  # a backend that cannot compile or run it: float32, and the run goes on
            print(f"train precision: bfloat16 failed here ({type(error).__name__}: {error}); float32", file=sys.stderr)
            seconds.append(math.inf)
        measured.append(True)
        return seconds

    if jax.process_count() == 1:
        float32_s, bfloat16_s = compile_cache.memo("train-precision", parts, measure)
        chosen = decide(float32_s, bfloat16_s)
    else:
        from jax.experimental import multihost_utils

        float32_s, bfloat16_s = measure()
        flag = multihost_utils.broadcast_one_to_all(np.int32(decide(float32_s, bfloat16_s) == "bfloat16"))
        chosen = "bfloat16" if int(flag) else None
    return PrecisionChoice(chosen, float(float32_s), float(bfloat16_s), cached=not measured)
