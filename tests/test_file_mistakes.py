"""Issue 37, files a newcomer gets wrong: a CSV column of text passed ``check-config`` and the
run then exited 75 (every window abandoned); a directory given as the recording read "not
found"; a CSV with its header only leaked numpy's ``UserWarning`` and ``run`` named the key
``path``, not ``driver.path``. Each is refused by ``check-config`` and by ``run`` (exit 78) in one
line naming the configuration's key."""

from __future__ import annotations

import warnings
from pathlib import Path

import pytest

from harness.daemon import with_driver
from harness.sources import FILE_DRIVER, plant_csv

from .helpers.cli import cli


def _text_column(tmp_path: Path) -> Path:
    header, *rows = plant_csv(tmp_path / "plant.csv", 10.0).read_text().splitlines()
    j = header.split(",").index("Tload")
    out = tmp_path / "text.csv"
    out.write_text("\n".join([header, *(",".join("ON" if i == j else c for i, c in
                                                 enumerate(r.split(","))) for r in rows)]))
    return out


def _header_only(tmp_path: Path) -> Path:
    header = plant_csv(tmp_path / "plant.csv", 2.0).read_text().splitlines()[0]
    out = tmp_path / "header.csv"
    out.write_text(header + "\n")
    return out


def _directory(tmp_path: Path) -> Path:
    out = tmp_path / "recording.csv"
    out.mkdir()
    return out


CASES = {
    "text column": (_text_column, "driver.columns.Tload: column 'Tload' of text.csv holds "
                    "text, not numbers (1000 cells, e.g. 'ON')"),
    "header only": (_header_only, "driver.path: CSV"),
    "a directory": (_directory, "driver.path: "),
}


@pytest.mark.parametrize("case", list(CASES))
def test_a_bad_recording_is_refused_by_check_config_and_run_naming_the_key(
        tmp_path: Path, case: str) -> None:
    make, why = CASES[case]
    path = with_driver(tmp_path, FILE_DRIVER.format(path=make(tmp_path)))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # numpy's "input contained no data" was printed
        r = cli("check-config", str(path))
        assert r.exit_code == 1 and why in r.output and "OK" not in r.output, r.output
        r = cli("run", "--no-progress", "--duration", "4", str(path))
    assert r.exit_code == 78 and why in r.output, r.output
    if case == "header only":
        assert "has no data rows" in r.output and ": path:" not in r.output, r.output
    if case == "a directory":
        assert "is a directory" in r.output and "not found" not in r.output, r.output
