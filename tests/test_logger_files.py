"""Files as data loggers write them (issue 23 item 4): a logger's retried row, a stamp written
twice with other values, two captures one after the other.

The ring buffer's rules on a synthetic stream, then ``twinwatch run`` on CSV recordings of the
simulated DC motor (harness/sources.py) written as a logger would: every 97th row twice,
and two captures concatenated (the clock starts over at the seam).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from harness.daemon import db_rows, with_driver
from harness.sources import FILE_DRIVER, plant_csv
from twinwatch.daemon.ringbuffer import RingBuffer

from .helpers.cli import cli

CH = ("a", "b")


def _feed(rb: RingBuffer, rows: list[tuple[float, dict[str, float]]]) -> list:
    return [w for t, v in rows if (w := rb.append(t, v)) is not None]


def _rows(n: int, t0: float = 0.0, v0: int = 0) -> list[tuple[float, dict[str, float]]]:
    return [(t0 + k * 0.01, {"a": float(v0 + k), "b": 2.0 * (v0 + k)}) for k in range(n)]


def test_an_exact_duplicate_is_dropped_and_counted_the_window_goes_on(caplog):
    clean = _rows(100)
    logged = []
    for k, row in enumerate(clean):
        logged.append(row)
        if k % 7 == 6:
            logged.append(row)  # the logger's retry
    rb = RingBuffer(CH, window=10, sample_period=0.01)
    wins = _feed(rb, logged)
    ref = _feed(RingBuffer(CH, window=10, sample_period=0.01), clean)
    assert len(wins) == len(ref) == 10
    for w, r in zip(wins, ref, strict=True):
        np.testing.assert_array_equal(w.t, r.t)
        np.testing.assert_array_equal(w["a"], r["a"])
    assert rb.duplicates == 14 and sum(rb.discarded.values()) == 0
    assert sum(rb.lost.values()) == 14 and "exact duplicate" in next(iter(rb.lost))
    assert sum("exact duplicate" in r.message for r in caplog.records) == 1  # logged once


def test_a_stamp_repeated_with_other_values_abandons_only_its_window():
    rows = _rows(100)
    t, v = rows[45]
    rows.insert(46, (t, {"a": -1.0, "b": -1.0}))  # same stamp, other values
    rb = RingBuffer(CH, window=10, sample_period=0.01)
    wins = _feed(rb, rows)
    # window 4 (samples 40..49) holds the conflict: abandoned; every other window is whole
    assert [int(w["a"][0]) for w in wins] == [0, 10, 20, 30, 46, 56, 66, 76, 86]
    assert all(np.all(w["a"] >= 0) and np.all(np.diff(w.t) > 0) for w in wins)
    assert rb.causes["time_back"] == 1 and sum(rb.discarded.values()) == 1
    assert rb.duplicates == 0


def test_a_clock_that_starts_over_costs_at_most_the_window_at_the_seam():
    rb = RingBuffer(CH, window=10, sample_period=0.01)
    wins = _feed(rb, _rows(95) + _rows(100, v0=1000))
    assert len(wins) == 9 + 10  # the 5 samples of the partial window at the seam only
    assert sum(rb.discarded.values()) == 1 and rb.discarded["time stamp jumped backwards"] == 1
    rb = RingBuffer(CH, window=10, sample_period=0.01)
    assert len(_feed(rb, _rows(100) + _rows(100, v0=1000))) == 20  # on a window's end: none
    assert sum(rb.discarded.values()) == 0


NOISE = {"noise": {"ia": 1.0, "omega": 1.0}}


def _run(tmp: Path, rows: list[str], header: str) -> tuple[int, list[dict], str]:
    data = tmp / "logger.csv"
    data.write_text("\n".join([header, *rows]) + "\n")
    cfg = with_driver(tmp, FILE_DRIVER.format(path=data))
    r = cli("run", str(cfg), "--no-progress")
    return r.exit_code, db_rows(tmp / "state.sqlite"), r.output


def test_a_logger_csv_with_every_97th_row_written_twice_loses_no_window(tmp_path):
    """Before: 0 of 30 windows, 5977 of 6061 samples dropped as 'time stamp jumped backwards
    or repeated'."""
    header, *rows = plant_csv(tmp_path / "plant.csv", 60.0, plant=NOISE).read_text().splitlines()
    logged = [r for k, row in enumerate(rows) for r in ((row, row) if k % 97 == 96 else (row,))]
    assert len(logged) == 6000 + 61
    code, stored, out = _run(tmp_path, logged, header)
    assert code == 0, out
    assert len(stored) == 30, out
    c = stored[-1]["counters"]
    assert c["windows_abandoned"] == 0 and c["samples_lost"] == 61, c
    assert "61 exact duplicates dropped" in out, out
    ras = [h["parameters"]["Ra"]["value"] for h in stored]
    assert all(math.isfinite(x) and abs(x / 6.5 - 1) < 0.05 for x in ras), ras  # nominal


@pytest.mark.parametrize("seam", [0.0, 1.3])
def test_two_captures_concatenated_lose_at_most_the_window_at_the_seam(tmp_path, seam):
    """Two 30 s captures (the second with its own noise), the second's clock from 0 again;
    ``seam``: how far into a window the first one ends."""
    header, *first = plant_csv(tmp_path / "a.csv", 30.0 + seam, plant=NOISE
                               ).read_text().splitlines()
    _, *second = plant_csv(tmp_path / "b.csv", 30.0, seed=1, plant=NOISE
                           ).read_text().splitlines()
    code, stored, out = _run(tmp_path, first + second, header)
    assert code == 0, out
    c = stored[-1]["counters"]
    assert len(stored) == 30, out
    assert c["windows_abandoned"] == (1 if seam else 0), c


def test_a_realtime_replay_is_paced_after_the_clock_starts_over(tmp_path):
    """Two 0.1 s captures at 20 ms, the second's clock from 0 again: replayed in real time,
    the second is paced from the seam (about 0.16 s in all), not delivered at once (0.08 s)."""
    import time

    from twinwatch.drivers.base import EndOfStream
    from twinwatch.drivers.file import FileDriver, FileDriverConfig

    capture = [f"{k * 20},{k}.0" for k in range(5)]
    data = tmp_path / "two.csv"
    data.write_text("\n".join(["time_ms,u", *capture, *capture]) + "\n")
    config = FileDriverConfig.model_validate({
        "type": "file", "path": str(data), "time_column": "time_ms", "time_scale": 1e-3,
        "sample_period": 0.02, "realtime": True, "columns": {"Va": {"column": "u"}}})
    n = 0
    with FileDriver(config) as driver:
        start = time.monotonic()
        with pytest.raises(EndOfStream):
            while True:
                n += driver.read(1.0) is not None
        elapsed = time.monotonic() - start
    assert n == 10
    assert elapsed >= 0.159, elapsed
