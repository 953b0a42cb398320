"""core.filters.lfilter against scipy.signal.lfilter (the reference it replaces), to 1e-12.

First- and second-order lags, leads, FIR filters (the prewhitening and the AR prefilter), integrators
and double integrators; one- and two-dimensional signals along either axis; initial and final
states; complex signals.  The module itself must not import scipy.signal.
"""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from scipy import signal

from mpm_monitor.core.filters import lfilter

FILTERS = {
    "first order lag": ([0.0, 0.3], [1.0, -0.7]),
    "first order, direct": ([0.25], [1.0, -0.75]),
    "first order with lead": ([0.4, -0.1], [1.0, -0.7]),
    "second order lag": ([0.0, 0.02, 0.015], [1.0, -1.6, 0.64]),
    "second order oscillating": ([0.1, 0.05], [1.0, -1.2, 0.81]),
    "FIR": ([1.0, -0.8, 0.3, -0.05], [1.0]),
    "FIR one tap": ([2.5], [1.0]),
    "long FIR (step-response model)": (np.linspace(0.0, 1.0, 60) ** 2, [1.0]),
    "integrator": ([0.0, 0.5], [1.0, -1.0]),
    "integrator with lag": ([0.0, 0.1, 0.08], [1.0, -1.8, 0.8]),
    "double integrator": ([0.0, 1.0], [1.0, -2.0, 1.0]),
    "a[0] not 1": ([0.6, 0.2], [2.0, -1.4]),
    "longer a than b": ([1.0], [1.0, -0.5, 0.06, -0.001]),
}


def _close(ours, ref):
    ref = np.asarray(ref)
    scale = max(1.0, float(np.max(np.abs(ref)))) if ref.size else 1.0
    np.testing.assert_allclose(ours, ref, rtol=0, atol=1e-12 * scale)


@pytest.mark.parametrize("name", sorted(FILTERS))
def test_one_dimensional_matches_scipy(name):
    b, a = FILTERS[name]
    x = np.random.default_rng(0).normal(size=3000)
    _close(lfilter(b, a, x), signal.lfilter(b, a, x))


@pytest.mark.parametrize("name", sorted(FILTERS))
@pytest.mark.parametrize("axis", [0, 1, -1])
def test_two_dimensional_along_either_axis(name, axis):
    b, a = FILTERS[name]
    x = np.random.default_rng(1).normal(size=(400, 7) if axis == 0 else (7, 400))
    ours = lfilter(b, a, x, axis=axis)
    assert ours.shape == x.shape
    _close(ours, signal.lfilter(b, a, x, axis=axis))


@pytest.mark.parametrize("name", sorted(n for n, (b, a) in FILTERS.items() if max(len(a), len(b)) > 1))
def test_initial_and_final_state_match_scipy(name):
    """Every filter with a state (a one-tap FIR has none)."""
    b, a = FILTERS[name]
    order = max(len(a), len(b)) - 1
    rng = np.random.default_rng(2)
    x = rng.normal(size=500)
    zi = rng.normal(size=order)
    y, zf = lfilter(b, a, x, zi=zi)
    y_ref, zf_ref = signal.lfilter(b, a, x, zi=zi)
    _close(y, y_ref)
    _close(zf, zf_ref)
    # Two halves with the state carried over give the whole record.
    y1, z1 = lfilter(b, a, x[:200], zi=zi)
    y2, _ = lfilter(b, a, x[200:], zi=z1)
    _close(np.concatenate([y1, y2]), y_ref)


@pytest.mark.parametrize("n", [0, 1, 2, 3])
def test_records_shorter_than_the_state(n):
    b, a = [0.1, 0.2, 0.3, 0.4], [1.0, -0.5, 0.2]
    rng = np.random.default_rng(3)
    x, zi = rng.normal(size=n), rng.normal(size=3)
    y, zf = lfilter(b, a, x, zi=zi)
    y_ref, zf_ref = signal.lfilter(b, a, x, zi=zi)
    _close(y, y_ref)
    if n:
        _close(zf, zf_ref)
    else:               # nothing filtered: the state stays (scipy returns uninitialised memory here)
        np.testing.assert_array_equal(zf, zi)
    assert lfilter(b, a, x).shape == (n,)


def test_state_along_an_axis_of_a_matrix():
    b, a = [0.0, 0.2, 0.1], [1.0, -1.1, 0.3]
    rng = np.random.default_rng(4)
    x = rng.normal(size=(5, 300))
    zi = rng.normal(size=(5, 2))
    y, zf = lfilter(b, a, x, axis=1, zi=zi)
    y_ref, zf_ref = signal.lfilter(b, a, x, axis=1, zi=zi)
    _close(y, y_ref)
    _close(zf, zf_ref)
    y0, zf0 = lfilter(b, a, x.T, axis=0, zi=zi.T)
    _close(y0, y_ref.T)
    _close(zf0, zf_ref.T)


def test_first_order_equals_scipy_to_rounding():
    # The forward substitution does scipy's operations in scipy's order for a first-order filter: the
    # same numbers bit for bit where the BLAS computes v - a y as a multiply then an add; where its
    # kernel fuses them (OpenBLAS on AVX-512 processors) each step rounds once instead of twice, and
    # the difference, propagated by the pole, stays at rounding level (4.6e-15 of the peak at 0.9995).
    x = np.random.default_rng(5).normal(size=5000)
    for pole in (0.3, 0.9, 0.9995):
        b, a = [1.0 - pole], [1.0, -pole]
        for num in (b, [0.0, 1.0 - pole]):
            ref = signal.lfilter(num, a, x)
            tol = 64 * np.finfo(float).eps / (1.0 - pole)       # the rounding of each step, amplified by the pole
            assert np.max(np.abs(lfilter(num, a, x) - ref)) <= tol * np.max(np.abs(ref))


def test_fir_is_bit_identical_to_scipy():
    x = np.random.default_rng(6).normal(size=(2000, 3))
    b = [1.0, -0.62, 0.11, 0.02, -0.004]
    assert np.array_equal(lfilter(b, [1.0], x, axis=0), signal.lfilter(b, [1.0], x, axis=0))


def test_complex_signal_and_integer_signal():
    rng = np.random.default_rng(7)
    x = rng.normal(size=200) + 1j * rng.normal(size=200)
    b, a = [0.3, 0.1], [1.0, -0.6]
    _close(lfilter(b, a, x), signal.lfilter(b, a, x))
    xi = np.arange(50)
    _close(lfilter(b, a, xi), signal.lfilter(b, a, xi))


def test_unstable_and_nonfinite_values_propagate_like_scipy():
    x = np.ones(100)
    b, a = [1.0], [1.0, -1.5]
    np.testing.assert_allclose(lfilter(b, a, x), signal.lfilter(b, a, x), rtol=1e-12)
    x[10] = np.nan
    assert np.array_equal(np.isnan(lfilter(b, a, x)), np.isnan(signal.lfilter(b, a, x)))


def test_bad_coefficients_refused():
    with pytest.raises(ValueError, match="a\\[0\\]"):
        lfilter([1.0], [0.0, 1.0], np.ones(3))
    with pytest.raises(ValueError, match="non-empty"):
        lfilter([], [1.0], np.ones(3))


def test_the_module_does_not_import_scipy_signal():
    code = ("import sys; import mpm_monitor.core.filters as f; f.lfilter([1.0], [1.0, -0.5], [1.0, 2.0]); "
            "print('scipy.signal' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"


def test_signals_without_columns_or_samples_leave_the_process_sound():
    """No columns (a row without elements of a column kind) or no samples: empty results, and the
    heap intact (LAPACK's banded solver handed no right-hand side corrupted it; a garbage collection
    then aborted the process), so the check runs in a fresh interpreter."""
    code = (
        "import gc, numpy as np\n"
        "from mpm_monitor.core.filters import lfilter\n"
        "for _ in range(20):\n"
        "    for x in (np.zeros((2200, 0)), np.zeros((0, 3)), np.zeros((2200, 0, 2))):\n"
        "        for a in ([1.0, -0.9], [1.0, -1.8, 0.81]):\n"
        "            y = lfilter([0.0, 0.1], a, x, axis=0)\n"
        "            assert y.shape == x.shape, y.shape\n"
        "            y, zf = lfilter([0.0, 0.1], a, x, axis=0, zi=np.zeros((len(a) - 1,) + x.shape[1:]))\n"
        "            assert y.shape == x.shape and zf.shape == (len(a) - 1,) + x.shape[1:]\n"
        "    junk = [np.ones(10) for _ in range(1000)]\n"
        "    gc.collect()\n"
        "print('sound')\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "sound", (out.returncode, out.stderr[-500:])
