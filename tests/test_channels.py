"""Channel and attack simulators of seeds 000 and 002: formulas and Monte Carlo frequencies."""
from __future__ import annotations

import numpy as np
import pytest

from designer import Gaussian, InputError, UniformBox
from filters.attacks import (
    binary_sensor_channel,
    deception_attack,
    round_robin_received,
    round_robin_schedule,
)


def test_round_robin_formula():
    # gamma_k = mod(k + gamma_ini - 2, N) + 1 written out for N = 4, gamma_ini = 3: 3, 4, 1, 2, 3, ...
    np.testing.assert_array_equal(round_robin_schedule(6, 4, 3) + 1, [3, 4, 1, 2, 3, 4])
    np.testing.assert_array_equal(round_robin_schedule(5, 4) + 1, [1, 2, 3, 4, 1])
    with pytest.raises(InputError, match="gamma_ini"):
        round_robin_schedule(5, 4, 5)


def test_deception_frequency_and_replacement():
    rng = np.random.default_rng(0)
    box = UniformBox([-10.0, -np.pi / 2], [80.0, np.pi / 2])
    y = rng.normal(size=(200, 120, 2))
    out = deception_attack(y, 0.2, box, rng)
    n = out.eta.size
    assert abs(out.eta.mean() - 0.2) < 5 * np.sqrt(0.2 * 0.8 / n)
    np.testing.assert_array_equal(out.y[~out.eta], y[~out.eta])
    np.testing.assert_array_equal(out.y[out.eta], out.xi[out.eta])
    assert np.all((out.xi >= box.lower) & (out.xi <= box.upper))
    with pytest.raises(InputError, match="prob"):
        deception_attack(y, 1.0, box, rng)


def test_round_robin_zero_input_and_hold():
    sched = round_robin_schedule(5, 3)
    ys = np.arange(1.0, 6.0)[:, None] * np.ones((5, 2))
    zi = round_robin_received(ys, sched, 3)
    zoh = round_robin_received(ys, sched, 3, "zero-order-hold")
    for k in range(5):
        assert np.all(zi[k, sched[k]] == ys[k]) and np.all(zoh[k, sched[k]] == ys[k])
        others = [s for s in range(3) if s != sched[k]]
        assert np.all(zi[k, others] == 0)
    np.testing.assert_array_equal(zoh[4, 0], ys[3])  # sensor 0 last sent at k = 3 (0-based)
    np.testing.assert_array_equal(zoh[1, 2], [0, 0])  # not yet sent


def test_binary_channel_logic_and_frequencies():
    rng = np.random.default_rng(1)
    yhat = rng.uniform(0, 1, size=(400, 100, 16))
    out = binary_sensor_channel(yhat, dos_prob=0.1, deception_prob=0.2, flip_prob=0.05,
                                deception=UniformBox([-3.0], [3.0]), threshold=0.3, gain=0.5,
                                channel_noise=Gaussian.zero_mean([[0.01]]), rng=rng)
    n = yhat.size
    for ind, p in ((out.dos, 0.1), (out.deception, 0.2), (out.flip, 0.05)):
        assert abs(ind.mean() - p) < 5 * np.sqrt(p * (1 - p) / n)
    # DoS forces the bit to 0 (T_delta > 0); a clean reading is thresholded; the flip is an XOR.
    assert not out.theta[out.dos].any()
    clean = ~out.dos & ~out.deception
    np.testing.assert_array_equal(out.theta[clean], yhat[clean] > 0.3)
    np.testing.assert_array_equal(out.theta_bar, out.theta ^ out.flip)
    # Deceived readings exceed the threshold with probability P(mu > 0.3) = 2.7 / 6.
    dec = out.deception & ~out.dos
    assert abs(out.theta[dec].mean() - 2.7 / 6) < 5 * np.sqrt(0.45 * 0.55 / dec.sum())
    resid = out.y - 0.5 * out.theta_bar
    assert abs(resid.std() - 0.1) < 0.005
