"""The plants the benchmarks are built on (one home, so no benchmark imports another for a model).

* :func:`random_plant`: a random stable FOPDT plant (gains log-uniform in [0.5, 5] with a random
  sign, time constants 10..80 s, delays 0..8 samples, sample time 1 s), for :mod:`bench.perf` and
  :mod:`bench.memory`;
* :func:`square_model`: an ``n x n`` diagonally dominant FOPDT model (delays 1..7 samples), for
  :mod:`bench.ros_throughput` and :mod:`bench.monitor_load`.
"""

from __future__ import annotations

import numpy as np

from mpm_monitor.core.model import PlantModel


def random_plant(n_outputs: int, n_inputs: int, rng: np.random.Generator) -> PlantModel:
    """A random stable FOPDT plant (see the module docstring)."""
    shape = (n_outputs, n_inputs)
    gain = np.exp(rng.uniform(np.log(0.5), np.log(5.0), shape)) * rng.choice([-1.0, 1.0], shape)
    return PlantModel(sample_time=1.0, inputs=[f"u{j + 1}" for j in range(n_inputs)],
                      outputs=[f"y{i + 1}" for i in range(n_outputs)], gain=gain,
                      time_constant=rng.uniform(10.0, 80.0, shape),
                      delay=rng.integers(0, 9, shape).astype(float), name=f"random {n_outputs}x{n_inputs}")


def square_model(n: int, seed: int = 0) -> PlantModel:
    """An ``n x n`` FOPDT model with diagonal dominance (sample time 1 s, delays 1..7 samples)."""
    rng = np.random.default_rng(seed)
    gain = rng.uniform(0.2, 1.0, (n, n)) + np.eye(n) * n
    tau = rng.uniform(20.0, 60.0, (n, n))
    delay = rng.integers(1, 8, (n, n)).astype(float)
    return PlantModel(sample_time=1.0, inputs=tuple(f"u{k + 1}" for k in range(n)),
                      outputs=tuple(f"y{k + 1}" for k in range(n)), gain=gain, time_constant=tau, delay=delay,
                      name=f"{n}x{n} benchmark model")
