"""The console of ``twinwatch run`` (issue 16, item 6): the progress bar and the log lines never
share a line (before: ``...nRMSE 1.6e-05]2`` / ``026-11-22 ...``: a log line written after the
bar's last redraw, which ends without a newline).

The command runs as a user runs it (a subprocess, its stderr read as the terminal gets it: the
bar redraws with carriage returns); the log lines at INFO come from the worker thread (one per
window) and the alarm lines at WARNING as the terminal shows them.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

from .helpers.paths import ROOT

#: The start of a log record (``logging.basicConfig``'s format in cli.py).
RECORD = re.compile(r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3} (DEBUG|INFO|WARNING|ERROR)")
BAR = "s plant time ["


def test_log_lines_never_share_a_line_with_the_progress_bar(tmp_path: Path) -> None:
    text = (ROOT / "config" / "dc-motor-sim.toml").read_text()
    text = text.replace("duration = 1200.0", "duration = 20.0")
    text = text.replace("[zenoh]", "[zenoh]\nenabled = false")
    text = text.replace("[recording]", "[recording]\nenabled = false")
    # nameplate Ra 6.0 against the plant's 6.5 (+8 %): the warning is raised within the run
    text = text.replace("Ra = 6.5          # ohm", "Ra = 6.0          # ohm")
    cfg = tmp_path / "m.toml"
    cfg.write_text(text)
    out = subprocess.run([sys.executable, "-m", "twinwatch", "run", str(cfg), "--log-level",
                          "info"], cwd=tmp_path, capture_output=True, text=True, timeout=300,
                         env=dict(os.environ, PYTHONPATH=str(ROOT), CI="true", COLUMNS="120"))
    assert out.returncode == 0, out.stderr
    # what a terminal shows: each carriage return starts the line over
    segments = [seg for line in out.stderr.split("\n") for seg in line.split("\r")]
    records = [seg for seg in segments if RECORD.search(seg)]
    bars = [seg for seg in segments if BAR in seg]
    assert len(bars) >= 10, out.stderr  # the bar was drawn, window after window
    assert sum("window " in r for r in records) >= 10  # one INFO line per window
    assert any("WARNING" in r and "Ra is" in r for r in records), out.stderr  # the alarm line
    glued = [seg for seg in segments if (RECORD.search(seg) and not RECORD.match(seg))
             or (BAR in seg and RECORD.search(seg))]
    assert glued == [], glued[:3]
    # and no log line was cut by a bar drawn into it (every record ends where its line ends)
    lines = out.stderr.split("\n")
    assert not [ln for ln in lines if RECORD.match(ln) and BAR in ln]
