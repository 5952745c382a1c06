"""The detector's own Butterworth sections against scipy.signal, and the daemon's imports."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from scipy import signal

from recal.core import sos_filter
from recal.core.detector import DetectorConfig, detect, init_state
from recal.core.sos_filter import SCALAR_MAX_N, butter_sos, sos_zi, sosfilt


@pytest.mark.parametrize("order", [1, 2, 3, 4, 5])
@pytest.mark.parametrize("highpass", [False, True])
@pytest.mark.parametrize(("cutoff_hz", "rate_hz"), [(0.5, 100.0), (0.5, 12.5), (3.0, 50.0)])
def test_design_has_scipys_response(order: int, highpass: bool, cutoff_hz: float,
                                    rate_hz: float) -> None:
    ours = butter_sos(order, cutoff_hz, rate_hz, highpass)
    ref = signal.butter(order, cutoff_hz, "highpass" if highpass else "lowpass", fs=rate_hz,
                        output="sos")
    assert ours.shape == ref.shape and np.all(ours[:, 3] == 1.0)
    f = np.linspace(0.0, rate_hz / 2, 257)
    _, h_ours = signal.sosfreqz(ours, worN=f, fs=rate_hz)
    _, h_ref = signal.sosfreqz(ref, worN=f, fs=rate_hz)
    assert np.max(np.abs(h_ours - h_ref)) < 1e-9


@pytest.mark.parametrize("order", [1, 2, 3, 4])
@pytest.mark.parametrize("highpass", [False, True])
def test_steady_state_is_scipys(order: int, highpass: bool) -> None:
    sos = butter_sos(order, 0.5, 50.0, highpass)
    np.testing.assert_allclose(sos_zi(sos), signal.sosfilt_zi(sos), rtol=1e-9, atol=1e-12)
    y, _ = sosfilt(sos, np.full(200, 0.98), sos_zi(sos) * 0.98)  # steady from the start
    np.testing.assert_allclose(y, 0.0 if highpass else 0.98, atol=1e-12)


@pytest.mark.parametrize("order", [1, 2, 3])
@pytest.mark.parametrize("n", [1, 2, 17, SCALAR_MAX_N, SCALAR_MAX_N + 1, 5000])
def test_scalar_loop_and_compiled_kernel_give_the_same_bits(order: int, n: int) -> None:
    """Same machine, same run: the short-batch loop does the kernel's operations in its order
    (a kernel compiled to fuse multiply-adds would differ in the last bits, and fail here)."""
    rng = np.random.default_rng(order * 1000 + n)
    for highpass in (False, True):
        sos = butter_sos(order, 0.5, 100.0, highpass)
        x, zi = rng.normal(1.0, 0.2, n), rng.normal(0.0, 0.3, (len(sos), 2))
        y_ref, z_ref = signal.sosfilt(sos, x, zi=zi)
        y, z = sos_filter._scalar(sos, x, zi)
        assert np.array_equal(y, y_ref) and np.array_equal(z, z_ref)
        y2, z2 = sosfilt(sos, x, zi)
        assert np.array_equal(y2, y_ref) and np.array_equal(z2, z_ref)


def test_detector_is_the_same_in_any_batching_across_the_kernel_switch() -> None:
    rng = np.random.default_rng(7)
    n = 3 * SCALAR_MAX_N + 11
    raw = rng.normal(0.0, 0.01, (n, 3)) + np.array([0.0, 0.0, 1.0])
    raw[n // 3: n // 2] += rng.normal(0.0, 0.3, (n // 2 - n // 3, 3))  # movement
    cfg = DetectorConfig(rate_hz=100.0)
    _, whole = detect(cfg, init_state(cfg), raw)
    for size in (1, 7, SCALAR_MAX_N, SCALAR_MAX_N + 1):
        state, outs = init_state(cfg), []
        for i in range(0, n, size):
            state, out = detect(cfg, state, raw[i:i + size])
            outs.append(out)
        assert np.array_equal(np.concatenate([o.detector_g for o in outs]), whole.detector_g)
        assert np.array_equal(np.concatenate([o.gate for o in outs]), whole.gate)
    assert whole.gate.any() and not whole.gate.all()


def test_daemon_and_its_detector_do_not_load_scipy_signal() -> None:
    code = ("import sys, numpy as np, recal.cli, recal.daemon.gateway, recal.node.node\n"
            "from recal.core.detector import DetectorConfig, detect, init_state\n"
            "cfg = DetectorConfig(rate_hz=100.0)\n"
            "s = init_state(cfg)\n"
            "for i in range(50):\n"
            "    s, _ = detect(cfg, s, np.array([[0.0, 0.0, 1.0 + 1e-3 * i]]))\n"
            "print(sorted(m for m in sys.modules if m.startswith('scipy')))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120, check=True).stdout
    assert out.strip() == "[]", out


def test_bad_designs_are_refused() -> None:
    for args in ((0, 0.5, 100.0), (2, 0.0, 100.0), (2, 50.0, 100.0)):
        with pytest.raises(ValueError, match="Butterworth"):
            butter_sos(*args, highpass=False)
