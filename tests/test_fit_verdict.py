"""The ring verdict (`ring_verdict`) on given values, errors and correlations: which
fits are degenerate, which are valid with a caveat. No fit, no compile."""

import numpy as np
import pytest

from jaxlens._fit.result import ring_verdict

NAMES = ("distance", "fov", "sigma", "brightness", "floor", "ring_flux")


def _verdict(ring_seen: float, *, floor: float = 0.0, free=NAMES):
    values = dict(distance=40.0, fov=1.57, sigma=0.04, brightness=0.8, floor=floor,
                  ring_flux=1.0)  # fmt: skip
    errors = dict(distance=0.22, fov=0.003, sigma=0.001, brightness=0.01, floor=0.001,
                  ring_flux=1.0 / ring_seen)  # fmt: skip
    corr = np.eye(len(free))
    corr[0, 1] = corr[1, 0] = 0.9
    return ring_verdict(free, values, errors, corr, shadow_seen=False)


@pytest.mark.parametrize(
    ("seen", "degenerate", "caveat"),
    [(1.6, True, False), (4.9, True, False), (6.2, False, True), (10.5, False, False)],
)
def test_a_faint_relativistic_ring_is_a_caveat_above_5_errors_and_degenerate_below(
    seen, degenerate, caveat
):
    # The fit benchmark's D = 40, FOV 90 deg ring (sigma free, no floor) is seen at
    # 3.8-6.1 errors over noise draws (pulls up to 2.2 below 5, 1.4 above); D = 17 at
    # 0.7-3.1 (pulls up to 3.7).
    deg, note, vif, cav = _verdict(seen)
    assert deg is degenerate and bool(note) is degenerate and bool(cav) is caveat
    assert vif == pytest.approx(1.0 / (1.0 - 0.81))
    if degenerate:
        assert "faint, sub-pixel feature" in note and "star_sigma" in note
    if caveat:
        assert f"seen at {seen:.2g} standard errors" in cav and "allows for that" in cav


def test_a_seen_edge_or_a_given_sigma_needs_no_ring():
    # A floor seen above 5 errors shows the shadow's edge: no caveat, whatever the ring.
    assert _verdict(1.6, floor=0.05)[0::3] == (False, "")
    free = tuple(n for n in NAMES if n != "sigma")
    assert _verdict(1.6, free=free)[0::3] == (False, "")
