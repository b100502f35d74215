"""``twinwatch tail``: one line per health message (:func:`health_line`) and the printer that
orders the lines, the alarm events and the notes (:class:`Tail`).
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

from twinwatch.watch.fleet import Delivery, Gap
from twinwatch.watch.render import deviation_text, gap_line, value_text
from twinwatch.watch.session import health_view
from twinwatch.watch.view import number, problem_counters

if TYPE_CHECKING:
    from twinwatch.twin.health import HealthView


def health_line(doc: HealthView | Mapping[str, Any], *, wall: float | None = None) -> str:
    """One line for ``twinwatch tail``: when it arrived, machine, window and its plant time,
    each parameter the window concerns (value, deviation from nominal, ``=`` held, ``~``
    fused), the fit, the model check and the raised alarms. ``doc``: the health message's
    typed view (:func:`~twinwatch.twin.health.read_health`), or decoded.

    Example::

        10:15:31 dc-motor-sim #540 [1080.00-1081.99 s] Ra 5.82987 -10.31 % D 0.00143 +0.02 %
        ... nRMSE 1.6e-05 check ok  ALARM Ra (run 20261122T101530Z-3f9a2c)
    """
    doc = health_view(doc)
    stamp = time.strftime("%H:%M:%S", time.localtime(time.time() if wall is None else wall))
    parts = [stamp, str("?" if doc.machine is None else doc.machine),
             f"#{'?' if doc.window is None else doc.window}"]
    t0, t1 = number(doc.t_start), number(doc.t_end)
    if t0 is not None and t1 is not None:
        parts.append(f"[{t0:.2f}-{t1:.2f} s]")
    parts += _parameter_words(doc) + _fit_words(doc) + _alarm_words(doc)
    n = len(doc.terms or [])
    if n:
        parts.append(f"+{n} term{'s' if n > 1 else ''}")
    problems = problem_counters(doc)
    if problems:
        parts.append("losses " + ", ".join(f"{k} {v}" for k, v in problems.items()))
    if doc.run:
        parts.append(f"(run {doc.run})")
    return " ".join(parts)


def _parameter_words(doc: HealthView) -> list[str]:
    """:func:`health_line`'s parameters: ``Ra 5.82987 -10.31 %`` each (``Ra=`` held, ``Ra~``
    fused), the tied and fixed ones left out."""
    marks = {"held": "=", "fused": "~"}
    return [f"{name}{marks.get(str(p.status), ' ')}{value_text(number(p.value))} "
            f"{deviation_text(number(p.deviation_pct))}"
            for name, p in (doc.parameters or {}).items() if p.status not in ("tied", "fixed")]


def _fit_words(doc: HealthView) -> list[str]:
    """:func:`health_line`'s fit: ``nRMSE 1.6e-05``, ``check ok`` / ``check FAILED`` (none
    without a model check), ``untrusted``."""
    nrmse, check = number(doc.nrmse), doc.model_check
    passed = check.passed if check is not None else None
    words = [f"nRMSE {nrmse:.1e}" if nrmse is not None else "nRMSE n/a"]
    if passed is not None:
        words.append("check ok" if passed else "check FAILED")
    if doc.trusted is False:
        words.append("untrusted")
    return words


def _alarm_words(doc: HealthView) -> list[str]:
    """:func:`health_line`'s raised alarms, alarms first: `` ALARM Ra``, `` WARNING D, J``."""
    raised = [(k, a.level) for k, a in (doc.alarms or {}).items()
              if a.level in ("warning", "alarm")]
    words = []
    for lvl in ("alarm", "warning"):
        names = [k for k, v in raised if v == lvl]
        if names:
            words.append(f" {lvl.upper()} {', '.join(names)}")
    return words


class Tail:
    """``twinwatch tail`` (its ``--help``): each window printed once; a window got from the
    history after a gap comes when it is got, marked ``[from the history]`` in text.

    Give its :meth:`on_health`, :meth:`on_alarm`, :meth:`on_token` and :meth:`on_gap` to the
    :class:`FleetWatcher` (:func:`watching`), then :meth:`run`.

    Args:
        emit: where a line goes (stdout).
        as_json: each health message as one line of JSON, exactly as published (no alarm
            events).
        note: where the machine's appearing and going are said (stderr), or None.
    """

    def __init__(self, emit: Callable[[str], None], *, as_json: bool = False,
                 note: Callable[[str], None] | None = None) -> None:
        self.emit = emit
        self.as_json = as_json
        self.note = note
        self._lines: deque[tuple[bool, str]] = deque()
        self._cond = threading.Condition()
        self._tokens = 0

    def _put(self, is_health: bool, line: str) -> None:
        with self._cond:
            self._lines.append((is_health, line))
            self._cond.notify()

    def on_health(self, machine: str, doc: HealthView, text: str,
                  delivery: Delivery = "live") -> None:
        if self.as_json:
            self._put(True, text)
        else:
            mark = "  [from the history]" if delivery == "history" else ""
            self._put(True, health_line(doc) + mark)

    def on_gap(self, gap: Gap) -> None:
        if self.note is not None:
            self.note(gap_line(gap))

    def on_alarm(self, machine: str, event: dict[str, Any]) -> None:
        if not self.as_json:
            self._put(False, f"{time.strftime('%H:%M:%S')} {event.get('message', event)}")

    def on_token(self, machine: str, present: bool) -> None:
        self._tokens += present
        if self.note is not None:
            self.note(f"{machine}: " + ("on the network" if present else
                                        "gone (its daemon stopped, or the link was lost)"))

    def run(self, count: int | None = None, stop: threading.Event | None = None,
            waiting: str | None = None) -> int:
        """Print until ``count`` health messages or ``stop``.

        Args:
            waiting: said aside once if no machine has appeared within 1 s (what is awaited).

        Returns:
            The number of health messages printed.
        """
        printed = 0
        t0 = time.monotonic()
        said_waiting = waiting is None
        while (count is None or printed < count) and not (stop is not None and stop.is_set()):
            with self._cond:
                if not self._lines:
                    self._cond.wait(0.2)
                batch = list(self._lines)
                self._lines.clear()
            for is_health, line in batch:
                if is_health and count is not None and printed >= count:
                    break
                self.emit(line)
                printed += is_health
            if not said_waiting and not self._tokens and time.monotonic() - t0 > 1.0:
                said_waiting = True
                if self.note is not None:
                    self.note(f"waiting for {waiting} (not on the network yet)")
        return printed
