"""The run summary's parameter lines (twinwatch.daemon.summary), as an operator reads them."""

from __future__ import annotations

from twinwatch.daemon.summary import _status
from twinwatch.twin.health import FusedHealth, ParameterHealth


def _held_j(rel_std_pct: float) -> ParameterHealth:
    return ParameterHealth(
        value=0.001171, unit="kg m^2", nominal=0.001171, deviation_pct=0.0, status="held",
        fused=FusedHealth(value=0.001171, rel_std_pct=rel_std_pct, low=0.0, high=0.0023),
        held=True, reason="held with Ke (lower priority): held at last trusted value",
        rel_std_pct=None)


def test_a_held_parameters_fused_interval_is_a_plain_percentage() -> None:
    """A fused interval is written as a plain percentage (100, where it read 1e+02); a narrow
    one keeps two digits."""
    assert _status(_held_j(0.0011)).endswith("; fused 0.001171 +- 0.0022 % (2 sigma)")
    assert _status(_held_j(6.2)).endswith("; fused 0.001171 +- 12 % (2 sigma)")
    assert _status(_held_j(49.8)).endswith("; fused 0.001171 +- 100 % (2 sigma)")


def test_a_held_parameter_no_window_determined_says_so_not_a_fused_value() -> None:
    """No window informed J: its fused interval is the fusion's prior (+- 100 %) or wider as
    its level wanders (the README's run: +- 540 %). The line says the windows have not
    determined it, where it read "fused 0.001171 +- 540 %" as if that were a measurement."""
    for rel, shown in ((50.0, "100"), (272.6, "550")):
        line = _status(_held_j(rel))
        assert line.endswith(f"; not determined across the windows either: fused +- {shown} % "
                             "(2 sigma), no narrower than its nameplate prior"), line
        assert "fused 0.001171" not in line
