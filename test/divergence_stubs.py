"""For the divergence tests of the plant and MPC nodes: a stub that makes one call of a function return values no
reader takes."""

import numpy as np


def diverging(real, at, bad):
    """``real`` (the plant's measure, the controller's step, a generator's next) with the values of call ``at``
    (0-based) replaced by ``bad`` (``{index: value}``); returns the stub and the list of the values it returned."""
    calls = []

    def stub(*args, **kwargs):
        values = np.array(real(*args, **kwargs), dtype=float)
        if len(calls) == at:
            for i, v in bad.items():
                values[i] = v
        calls.append(values)
        return values

    return stub, calls
