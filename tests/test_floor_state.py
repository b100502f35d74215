"""The interval's floor survives a restart (issue 23 item 5): its state is saved with the twin
and read back, so the published intervals, and the trends and RUL weighed by them, are those of
an uninterrupted run (tests/test_prognostics_resume.py runs the whole daemon)."""

from __future__ import annotations

import json

import numpy as np

from twinwatch.twin.estimation.floor import FloorState, StructuralFloor


def test_the_floor_state_round_trips_through_json_by_parameter_name() -> None:
    floor = StructuralFloor(3)
    floor.observe([0, 1], np.log([6.5, 0.0014, 0.038]), {0: 1e-4, 1: 2e-3}, t=1.0)
    floor.observe([0, 1], np.log([6.51, 0.00139, 0.038]), {0: 1e-4, 1: 2e-3}, t=3.0)
    names = ["Ra", "D", "Ke"]
    saved = json.loads(json.dumps(floor.state.as_dict(names)))
    assert saved["Ke"] is None
    back = FloorState.from_dict(saved, names)
    assert back.last == floor.state.last
    np.testing.assert_array_equal(back.excess, floor.state.excess)
    np.testing.assert_array_equal(back.pairs, floor.state.pairs)
    restored = StructuralFloor(3)
    restored.state = back
    np.testing.assert_array_equal(restored.tau(), floor.tau())
    assert floor.tau()[0] > 0  # a 0.15 % step against 0.01 % errors: a floor
    # another configuration's parameters: the names it knows, the others fresh
    other = FloorState.from_dict(saved, ["D", "J"])
    assert other.last[0] == floor.state.last[1] and other.last[1] is None
    assert other.pairs.tolist() == [1.0, 0.0]
