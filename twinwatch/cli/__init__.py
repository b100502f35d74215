"""Command line: ``twinwatch run``, ``check-config``, ``sample-config``, ``identify``,
``explain``, and ``watch`` / ``tail`` (the health on a Zenoh network, :mod:`twinwatch.watch`).

One module per command (``app``: the group, the logging, loading a configuration). The only
room that prints; everything else logs. Each command imports what it needs when it runs, so
``twinwatch --help`` loads click and nothing else (``benchmarks/bench_startup.py``).
"""

from __future__ import annotations

from twinwatch.cli.app import EX_CONFIG, main
from twinwatch.cli.check import check_config
from twinwatch.cli.explain import explain
from twinwatch.cli.fleet import fleet
from twinwatch.cli.identify import identify
from twinwatch.cli.run import run
from twinwatch.cli.samples import sample_config
from twinwatch.cli.watch import tail, watch

for _command in (run, check_config, watch, tail, fleet, explain, identify, sample_config):
    main.add_command(_command)

__all__ = ["EX_CONFIG", "main"]
