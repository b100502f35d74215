"""A daemon's outputs: the sinks it opens, adopts from a reload, hands to the pipeline and closes.

:class:`Outputs` opens the configured outputs through the sink registry
(:data:`twinwatch.sinks.SINKS`) and knows none by name: their roles decide which open and the
order of writing (the gate first), their ``open_order`` the order of opening. It answers a
reload's :meth:`Outputs.handover`, adopts what a running daemon hands over, wires the outputs
to the :class:`~twinwatch.daemon.pipeline.WindowPipeline`, and keeps the accounting of every
output, open or closed.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Collection, Container, Mapping
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Literal

from twinwatch.sinks import SINKS, sink_class
from twinwatch.sinks.base import AlarmBands, Gate, Outbox, Role, SharedResources, Sink, SinkContext

if TYPE_CHECKING:
    from twinwatch.config.schema import OutputTable, TwinwatchConfig
    from twinwatch.daemon.pipeline import WindowPipeline
    from twinwatch.drivers.base import Driver
    from twinwatch.twin.health import HealthView
    from twinwatch.twin.model import TwinModel

logger = logging.getLogger(__name__.rsplit(".", 1)[0] + ".runner")

__all__ = ["Outputs", "close_logged", "sink_context"]


class Outputs:
    """One daemon's outputs (registry name -> open sink), in the order each window is written.

    Args:
        pipeline: the window pipeline the outputs are written by (:meth:`wire`).
        roles: which roles open (``gate``, ``publisher``, ``recorder``).
        run: returns the daemon's run id.
        base_dir, work_dir, shared: the outputs' context (:func:`sink_context`).

    Attributes:
        sinks: registry name -> the open output, in writing order (the gate first).
        closed: the outputs :meth:`close` closed; adopted: those a running daemon handed over.
    """

    def __init__(self, config: TwinwatchConfig, model: TwinModel, *, machine: str,
                 pipeline: WindowPipeline, roles: Mapping[Role, bool], run: Callable[[], str],
                 base_dir: Path, work_dir: Path, shared: SharedResources | None) -> None:
        self.config = config
        self.model = model
        self.machine = machine
        self.pipeline = pipeline
        self.roles = dict(roles)
        self._run = run
        self.base_dir = base_dir
        self.work_dir = work_dir
        self.shared = shared
        self.sinks: dict[str, Sink] = {}
        self.closed: dict[str, Sink] = {}
        self.adopted: set[str] = set()

    # -- opening ----------------------------------------------------------------------------
    def open(self, reuse: dict[str, Sink], skip: Collection[str] = ()) -> set[str]:
        """Open the enabled outputs whose role is wanted, adopting the ``reuse``d ones that
        fit, in their ``open_order`` (every exclusive resource before any file is touched: a
        second twinwatch in the same directory fails without harming the first). The outputs
        in ``skip`` are not opened (yet).

        Returns:
            The names of the adopted outputs.

        Raises:
            ValueError: ``reuse`` names an output the registry does not know.
            twinwatch.errors.SinkError: an output cannot open.
        """
        for name in reuse:
            if name not in SINKS:
                raise ValueError(f"unknown output {name!r}; the outputs are "
                                 f"{', '.join(SINKS.names())}")
        tables = [t for t in self.config.output_tables() if t.config.enabled]
        classes = {t.name: sink_class(t.name) for t in tables}
        wanted = [t for t in tables if self.roles[classes[t.name].role]]
        context = self._sink_context(has_gate=any(classes[t.name].role == "gate"
                                                  for t in wanted))
        adopted = self._adopt(wanted, reuse)
        for t in sorted(wanted, key=lambda t: classes[t.name].open_order):
            if t.name not in self.sinks and t.name not in skip:
                self.sinks[t.name] = classes[t.name].open(t.name, t.config, context)
        order = [t.name for t in wanted]
        self.sinks = dict(sorted(self.sinks.items(), key=lambda kv: (
            not isinstance(kv[1], Gate), order.index(kv[0]))))
        return adopted

    def _adopt(self, wanted: list[OutputTable], reuse: dict[str, Sink]) -> set[str]:
        """Adopt the handed-over outputs whose table and context are unchanged (bound to this
        daemon by :meth:`wire`); one that does not fit is left to the daemon that handed it
        over. Returns the adopted names."""
        context = self.context(self.config, self.model)
        adopted: set[str] = set()
        for t in wanted:
            sink = reuse.get(t.name)
            if sink is not None and sink.keeps(t.config, context):
                self.sinks[t.name] = sink
                self.adopted.add(t.name)
                adopted.add(t.name)
                logger.info("reload: the %s output is kept open (its configuration is "
                            "unchanged)", t.name)
        return adopted

    def forget_adopted(self) -> None:
        """Drop the adopted outputs without closing them (a start that failed: they are the
        running daemon's)."""
        for name in self.adopted:
            self.sinks.pop(name, None)

    def wire(self, attach: bool = True) -> None:
        """Give the open outputs to the pipeline; with ``attach``, bind the adopted ones to
        this daemon."""
        if attach:
            for name in self.adopted:
                self.sinks[name].attach(self._sink_context(has_gate=self.store is not None))
        self.pipeline.sinks = list(self.sinks.values())
        self.pipeline.keeper.gate = self.store  # a window it cannot store is not published

    def context(self, config: TwinwatchConfig, model: TwinModel) -> SinkContext:
        """The outputs' context for a daemon of this one's run, directories and shared
        connections on ``config`` (without the stored history)."""
        return sink_context(config, model, self.base_dir, self._run(), cwd=self.work_dir,
                            shared=self.shared)

    def _sink_context(self, *, has_gate: bool) -> SinkContext:
        """What the outputs get from this daemon (the stored history when a gate opens)."""
        return replace(self.context(self.config, self.model),
                       history=self.stored_history if has_gate else None,
                       outbox=self.outbox if has_gate else None)

    def handover(self, config: TwinwatchConfig, model: TwinModel
                 ) -> tuple[list[str], list[str]]:
        """What a reload to ``config`` (its twin ``model``) may do with the open outputs:
        ``(keep, wait)`` (:meth:`twinwatch.daemon.runner.Daemon.handover`)."""
        context = self.context(config, model)
        new = {t.name: t.config for t in config.output_tables() if t.config.enabled}
        old = {t.name: t.config for t in self.config.output_tables()}
        keep, wait = [], []
        for name, sink in self.sinks.items():
            table = new.get(name)
            if table is None:
                continue
            if sink.keeps(table, context):
                keep.append(name)
            elif (old[name].exclusive_resources(context.cwd)
                  & table.exclusive_resources(context.cwd)):
                wait.append(name)
        return keep, wait

    # -- the gate ---------------------------------------------------------------------------
    @property
    def store(self) -> Gate | None:
        """The gate (the state store) while it is open, or None."""
        return next((s for s in self.sinks.values() if isinstance(s, Gate)), None)

    def stored_history(self, t_from: float | None = None, t_to: float | None = None,
                       limit: int | None = 1000, by: Literal["plant", "wall"] = "plant",
                       run: str | None = None, after: float | None = None
                       ) -> list[HealthView]:
        """Stored health messages of this machine (the gate's
        :meth:`~twinwatch.sinks.base.Gate.history`); empty without a state database."""
        store = self.store
        if store is None:
            return []
        return store.history(t_from, t_to, limit, by=by, machine=self.machine, run=run,
                             after=after)

    def outbox(self, output: str) -> Outbox | None:
        """The gate's outbox of ``output`` for this machine, None without a gate."""
        store = self.store
        return None if store is None else store.outbox(output, self.machine)

    # -- accounting -------------------------------------------------------------------------
    def every(self) -> list[Sink]:
        """Every output of this daemon, open or closed (their accounting stays readable)."""
        return [*self.sinks.values(), *self.closed.values()]

    def counters(self) -> dict[str, int]:
        """Each open output's counters (``<prefix>_<name>``) and the gate's
        ``windows_not_stored``."""
        c: dict[str, int] = {}
        for sink in self.sinks.values():
            c.update({f"{sink.prefix}_{k}": int(v) for k, v in sink.counters().items()})
            if isinstance(sink, Gate):
                c["windows_not_stored"] = int(sink.not_stored)
        return c

    def problems(self) -> list[str]:
        """Each output's :attr:`~twinwatch.sinks.base.Sink.problem`, open or closed."""
        return [p for s in self.every() if (p := s.problem)]

    def lost(self) -> dict[str, int]:
        """Windows estimated but lost, by output (its counter prefix)."""
        return {s.prefix: int(s.lost) for s in self.every() if s.lost}

    def status(self) -> list[str]:
        """What the open outputs serve, in the order they opened (systemd's STATUS)."""
        opened = sorted(self.sinks.values(), key=lambda s: s.open_order)
        return [st for s in opened if (st := s.status)]

    def summary(self) -> list[str]:
        """The outputs' lines for the run's summary, in writing order."""
        return [line for s in self.every() for line in s.summary()]

    # -- closing ----------------------------------------------------------------------------
    def close(self, keep: Container[str] = ()) -> dict[str, Sink]:
        """Close the outputs in writing order reversed (the gate last), detaching those in
        ``keep`` instead (a reload hands them over). Idempotent.

        Returns:
            name -> output for the kept outputs.
        """
        kept: dict[str, Sink] = {}
        for name, sink in reversed(list(self.sinks.items())):
            if name in keep:
                sink.detach()
                kept[name] = sink
            else:
                close_logged(name, sink)
                self.closed[name] = sink  # for the final accounting (lost windows)
        self.sinks = {}
        self.pipeline.sinks = []
        self.pipeline.keeper.gate = None
        return kept


def sink_context(config: TwinwatchConfig, model: TwinModel, base_dir: Path,
                 run: str, *, cwd: Path | None = None,
                 shared: SharedResources | None = None) -> SinkContext:
    """The outputs' context for a daemon on ``config`` (without the stored history)."""
    bands = {}
    if config.alarms.enabled:
        for name, rule in config.alarms.parameters.items():
            (w_high, w_low), (a_high, a_low) = rule.thresholds("warning"), rule.thresholds("alarm")
            bands[name] = AlarmBands(warning_high=w_high, warning_low=w_low, alarm_high=a_high,
                                     alarm_low=a_low)
    return SinkContext(machine=config.machine.name, model=config.machine.model,
                       outputs=tuple(model.output_names),
                       parameters={p.name: p.unit for p in model.parameters},
                       base_dir=base_dir, cwd=cwd or Path.cwd(), shared=shared,
                       recent_windows=config.acquisition.history,
                       output_units={o.name: o.unit for o in model.outputs},
                       nominal={p.name: float(config.machine.parameters.get(p.name, p.nominal))
                                for p in model.parameters},
                       estimated=tuple(config.estimation.estimate or ()),
                       alarm_bands=bands, run=run)


def close_logged(name: str, obj: Sink | Driver) -> None:
    """Close ``obj``, logging (not raising) a failure: the others still close."""
    try:
        obj.close()
    except Exception as exc:  # noqa: BLE001 - the other sinks still close
        logger.error("error while closing the %s: %s: %s", name, type(exc).__name__, exc)
        logger.debug("closing the %s failed", name, exc_info=True)
