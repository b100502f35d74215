"""The ring buffer's block path (``RingBuffer.extend``, issue 35 item 4: a real-time replay's
rows due together taken at once) does exactly what ``append`` does sample by sample: the same
windows (stamps, values, jitter, index), the same counters by reason and cause, on streams with
gaps, jitter, stamps going back, repeated stamps, exact duplicates, NaN and drifting clocks."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from twinwatch.daemon.ringbuffer import RingBuffer

CH = ("a", "b", "c")


def _stream(seed: int, n: int = 3000) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.01 + rng.uniform(0, 0.002, n)
    v = rng.normal(size=(n, len(CH)))
    for _ in range(6):  # gaps: samples missing
        k = int(rng.integers(50, n - 50))
        t[k:] += 0.01 * int(rng.integers(1, 4))
    for _ in range(4):  # jitter beyond tolerance
        t[int(rng.integers(1, n))] += 0.0045
    for _ in range(3):  # a stamp going back
        k = int(rng.integers(1, n))
        t[k] = t[k - 1] - 0.02
    for _ in range(4):  # NaN and inf values
        v[int(rng.integers(0, n)), int(rng.integers(0, len(CH)))] = rng.choice([np.nan, np.inf])
    for _ in range(4):  # exact duplicates (a logger's retry) and repeated stamps
        k = int(rng.integers(1, n))
        t[k] = t[k - 1]
        if rng.random() < 0.5:
            v[k] = v[k - 1]
    k = int(rng.integers(500, n - 600))  # a clock drifting off the period for a while
    t[k:k + 500] += np.arange(500) * 0.0004
    t[k + 500:] += 0.2
    return t, v


def _state(rb: RingBuffer, windows: list[Any]) -> tuple[Any, ...]:
    return (dict(rb.lost), dict(rb.discarded), dict(rb.causes), rb.duplicates, rb.samples,
            rb.bad_samples, rb.windows, rb.pending, rb._sums, rb._lo, rb._hi, rb._last_t,
            rb._last_row, [(w.index, w.t.tolist(), {c: x.tolist() for c, x in w.channels.items()},
                            None if w.stamp_jitter is None else w.stamp_jitter.tolist())
                           for w in windows])


def _by_samples(t: np.ndarray, v: np.ndarray, requests: dict[int, int]) -> tuple[Any, ...]:
    rb = RingBuffer(CH, window=50, sample_period=0.01)
    out = []
    for i in range(len(t)):
        if i in requests:
            rb.request_window(requests[i])
        w = rb.append(float(t[i]), dict(zip(CH, v[i].tolist(), strict=True)))
        if w is not None:
            out.append(w)
    return _state(rb, out)


def _by_blocks(t: np.ndarray, v: np.ndarray, requests: dict[int, int], seed: int
               ) -> tuple[tuple[Any, ...], int]:
    rng = np.random.default_rng(seed)
    rb = RingBuffer(CH, window=50, sample_period=0.01)
    out = []
    i = 0
    taken = 0
    while i < len(t):
        size = int(rng.integers(1, 40))
        # a request falls between blocks here, as between reads in the acquisition
        due = [k for k in requests if i <= k < i + size]
        if due and due[0] == i:
            rb.request_window(requests[i])
            due = due[1:]
        if due:
            size = due[0] - i
        m, w = rb.extend(t[i:i + size], v[i:i + size])
        taken += m
        if m == 0:
            w = rb.append(float(t[i]), dict(zip(CH, v[i].tolist(), strict=True)))
            m = 1
        if w is not None:
            out.append(w)
        i += m
    return _state(rb, out), taken


@pytest.mark.parametrize("seed", range(8))
def test_blocks_give_the_windows_and_counters_of_samples(seed: int) -> None:
    t, v = _stream(seed)
    requests = {0: 73, 1700: 40, 2400: 61}  # a staggered first window, an adaptive one
    expected = _by_samples(t, v, requests)
    got, taken = _by_blocks(t, v, requests, seed)
    assert got == expected
    assert expected[6] >= 20  # windows were made
    assert sum(expected[2].values()) >= 5  # and abandoned, for several causes
    assert taken > 0.9 * len(t)  # most samples took the block path


def test_a_block_stops_at_the_window_it_completes() -> None:
    rb = RingBuffer(CH, window=10, sample_period=0.01)
    t = np.arange(25) * 0.01
    v = np.ones((25, 3))
    m, w = rb.extend(t, v)
    assert m == 10 and w is not None and w.index == 0
    m, w = rb.extend(t[10:], v[10:])
    assert m == 10 and w is not None and w.t[0] == pytest.approx(0.1)
    assert rb.needed == 10 and rb.pending == 0


def _csv(path: Any, seconds: float) -> None:
    """A recording of the five DC-motor channels with what loggers write wrong: a row without
    a time, a NaN value, an exact duplicate row, a stamp going back, a gap, jitter."""
    rng = np.random.default_rng(3)
    n = int(seconds / 0.01)
    t = np.arange(n) * 0.01 + rng.uniform(0, 0.001, n)
    v = rng.normal(size=(n, 5))
    t[250:] += 0.03  # a gap
    t[300] += 0.0046  # jitter beyond tolerance
    rows = [f"{t[i]:.7f}," + ",".join(repr(x) for x in v[i].tolist()) for i in range(n)]
    rows[150] = "," + rows[150].split(",", 1)[1]  # no time stamp
    rows[340] = rows[340].rsplit(",", 1)[0] + ",nan"
    rows.insert(380, rows[379])  # a logger's retry
    rows[420] = f"{t[410]:.7f}," + rows[420].split(",", 1)[1]  # back
    path.write_text("t,Va,ia,omega,Tload,setpoint\n" + "\n".join(rows) + "\n")


def _acquire(path: Any, realtime: bool, blocks: bool, monkeypatch: pytest.MonkeyPatch
             ) -> tuple[Any, ...]:
    from pathlib import Path

    from twinwatch.config.loader import default_config
    from twinwatch.daemon.acquisition import Acquisition
    from twinwatch.drivers.base import Driver
    from twinwatch.drivers.file import FileDriver, FileDriverConfig
    from twinwatch.twin.models import create_model

    taken = [0]
    with monkeypatch.context() as mp:
        if not blocks:
            mp.setattr(FileDriver, "read_block", Driver.read_block)
        extend = RingBuffer.extend

        def counted(self: RingBuffer, *a: Any, **k: Any) -> Any:
            m, w = extend(self, *a, **k)
            taken[0] += m
            return m, w
        mp.setattr(RingBuffer, "extend", counted)
        cfg = default_config()
        driver = FileDriverConfig(type="file", path=path, time_column="t", sample_period=0.01,
                                  realtime=realtime, columns={
                                      c: {"column": c}
                                      for c in ("Va", "ia", "omega", "Tload", "setpoint")})
        cfg = cfg.model_copy(update={"driver": driver})
        model = create_model(cfg.machine.model, cfg.machine.options)
        acq = Acquisition(cfg, model, own_driver=True)
        acq.stagger("press-1")
        acq.open(None, base_dir=Path.cwd(), wait=False)
        windows: list[Any] = []
        lost: list[int] = []
        try:
            acq.run(None, lambda w, block: windows.append(w), lost.append)
            stats = acq.driver.stats.as_dict() if acq.driver is not None else {}
        finally:
            acq.release()
    assert (taken[0] > 0.8 * acq.ring.samples) if blocks else taken[0] == 0
    return _state(acq.ring, windows) + (sum(lost), stats)


@pytest.mark.parametrize("realtime", [False, True])
def test_a_recording_read_in_blocks_gives_what_it_gives_sample_by_sample(
        tmp_path: Any, monkeypatch: pytest.MonkeyPatch, realtime: bool) -> None:
    """The file driver's rows due together go to the ring buffer as blocks: the same windows
    (the first one staggered), the same abandoned windows, drivers' and ring's counters."""
    path = tmp_path / "rec.csv"
    _csv(path, 12.0 if not realtime else 7.5)
    by_samples = _acquire(path, realtime, False, monkeypatch)
    by_blocks = _acquire(path, realtime, True, monkeypatch)
    assert by_blocks == by_samples
    assert by_samples[6] >= 1 and by_samples[-2] >= 3  # windows made, and abandoned
