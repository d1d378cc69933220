"""Issue #43 item 6: the rolling shutter's (readout, reference row) start on a flat valley.

Hand-made costs stand in for :meth:`RollingShutter.fit_start`'s truncated squared error: the data
measure the exposure time of one band of rows (row fraction 0.8, the floor at the image's bottom)
precisely and the readout itself only weakly, so readout x (0.8 - reference row) is fixed and the
two trade along a valley.
"""
from __future__ import annotations

import pytest

from synth.sensor.effects.rolling_shutter import CONVENTION_CHI2, fit_row_times

DT = 1.0 / 30.0
R_TRUE = 0.018          # s, the first row stamped (reference row 0)
X_BAND = 0.8            # the row fraction whose exposure time the data measure
T_BAND = X_BAND * R_TRUE


def valley(r_weak: float, s_weak: float, s_band: float = 2e-4):
    """chi-square cost: the band's time to s_band seconds, the readout to s_weak seconds about a
    noisy reading r_weak."""
    def cost(readout: float, ref: float) -> float:
        t = (X_BAND - ref) * readout
        return ((t - T_BAND) / s_band) ** 2 + ((readout - r_weak) / s_weak) ** 2
    return cost


def test_flat_valley_takes_the_conventional_reference_row():
    # the weak readout reading 0.030 (1.5 sigma of 0.008 s off): the free minimum sits at readout
    # ~0.030, reference row ~0.32 (cost 0), the first-row convention at readout 0.018 costs
    # (0.012 / 0.008)^2 = 2.25 < 3.84: the convention is kept, as the data do not ask for more
    R, rho = fit_row_times(valley(0.030, 0.008), 0.0, DT)
    assert rho == 0.0
    assert R == pytest.approx(R_TRUE, rel=0.02)


def test_a_clear_free_reference_row_is_kept():
    # the readout well measured at 0.030 (0.001 s): the convention costs (0.012 / 0.001)^2 = 144,
    # far above the test's threshold: the free reference row 0.8 - T_BAND / 0.030 = 0.32 stays
    assert (0.012 / 0.001) ** 2 > CONVENTION_CHI2
    R, rho = fit_row_times(valley(0.030, 0.001), 0.0, DT)
    assert R == pytest.approx(0.030, rel=0.02)
    assert rho == pytest.approx(X_BAND - T_BAND / 0.030, abs=0.02)


@pytest.mark.parametrize("ref", [0.5, 1.0])
def test_other_conventions(ref):
    # a centre- or last-row stamp with a weak readout reading beside the truth
    t_band = (X_BAND - ref) * R_TRUE

    def cost(readout, r):
        return (((X_BAND - r) * readout - t_band) / 2e-4) ** 2 + ((readout - 0.024) / 0.008) ** 2
    R, rho = fit_row_times(cost, 0.0, DT)
    assert rho == ref
    assert R == pytest.approx(R_TRUE, rel=0.03)
