"""File replay driver: twin samples from a recording (CSV or MATLAB ``.mat``).

The whole recording is loaded when the driver is opened (recordings of a few hours at 100 Hz
are a few tens of MB) and replayed row by row, as fast as the caller reads or paced by the wall
clock (``realtime = true``). After the last row :meth:`~twinwatch.drivers.base.Driver.read`
raises :class:`~twinwatch.drivers.base.EndOfStream`.

Time stamps: ``t = k * sample_period`` where ``k`` is the row's index in the file (0-based,
counted before ``start`` is applied, so a cut recording keeps its own clock), or, with
``time_column``, ``t = value * time_scale`` read from that column. Rows are delivered as the
logger wrote them (the ring buffer drops an exact duplicate and abandons the window of a
repeated stamp or of a clock restart, e.g. two files concatenated).

Formats:

* CSV: one header row naming the columns, then one row per line; cells are decimal numbers.
  An empty or non-numeric cell is read as NaN; a row with fewer cells than the header has NaN
  in the missing cells. Blank lines are skipped. A quote left open is logged with its line
  number and costs that row only.
* MAT (MATLAB v5/v7, read with :func:`scipy.io.loadmat`; v7.3/HDF5 is not supported): every
  mapped "column" is a numeric variable holding a vector (N x 1, 1 x N or N), all of the same
  length N. MAT files usually hold no time vector, hence ``sample_period``.

A CSV still being written (a logger's file): ``follow = true`` reads it as ``tail -f`` does,
each appended line once it is complete, until ``idle_timeout`` without a row, a truncated or
replaced file, or ``stop`` rows (:meth:`FileDriver._wait_for_rows`). A file opened without
``follow`` that has grown by the time its last row is replayed says so once.

Bad input is counted, logged once, and the driver goes on (see
:class:`~twinwatch.drivers.base.DriverStats`): NaN or infinite values count in
``stats.bad_values`` and are delivered as they are; a row whose time stamp is not a number is
skipped and counts in ``stats.bad_frames``.

A commented ``[driver]`` table: ``twinwatch/config/samples/driver_file.toml``; a MAT
recording: ``config/dc-motor-motoshield.toml``.
"""

from __future__ import annotations

import csv
import difflib
import io
import logging
import math
import os
import time
import warnings
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import ClassVar, Literal

import numpy as np
import numpy.typing as npt
from pydantic import Field, StrictFloat, StrictInt, model_validator

from twinwatch.drivers.base import (
    Driver,
    DriverConfig,
    DriverConfigError,
    EndOfStream,
    Sample,
    ScaledChannel,
)

logger = logging.getLogger(__name__)

__all__ = ["FileColumnMap", "FileDriver", "FileDriverConfig"]

_CSV_SUFFIXES = {".csv": ",", ".txt": ",", ".tsv": "\t"}
_MAT_SUFFIXES = {".mat"}

FloatArray = npt.NDArray[np.float64]


#: A real-time replay delivers a row at most this late [s of the recording's time, this over
#: ``speed`` of wall time]: it sleeps until the next row is due plus that, and the rows due by
#: then follow at once (one wake-up per second of the recording, not one a row: a wake-up
#: costs a few tenths of a millisecond of CPU on a shared box; the acquisition loop's read
#: timeout, :data:`twinwatch.daemon.acquisition.READ_TIMEOUT_S`, caps a sleep).
PACE_SLACK = 1.0

#: Rows converted to Python floats at once (:meth:`FileDriver._read_internal`).
_CHUNK_ROWS = 256
#: Rows a block read looks at, at most (:meth:`FileDriver._read_block_internal`): a read for a
#: long window (``limit``) checks this many, not the rest of the file, each time.
_BLOCK_ROWS = 4096

#: How often a followed file (``follow = true``) is looked at for new rows [s].
FOLLOW_POLL = 0.1


class FileColumnMap(ScaledChannel):
    """Where one twin channel comes from: ``value_twin = value_file * scale + offset``.

    ``column`` is a CSV header name or a MAT variable name.
    """

    column: str = Field(min_length=1)


class FileDriverConfig(DriverConfig):
    """Configuration of :class:`FileDriver` (the ``[driver]`` table with ``type = "file"``).

    Attributes:
        type: always ``"file"``.
        path: the recording; a relative path is resolved against the configuration file's
            directory (``base_dir``).
        format: ``"csv"``, ``"mat"`` or ``"auto"`` (by suffix: ``.csv``, ``.txt``, ``.tsv``
            are CSV, ``.mat`` is MAT).
        sample_period: sample period [s] (> 0). Required unless ``time_column`` is given;
            with a time column it is the nominal period (default: the median time step).
        time_column: column (or MAT variable) holding the time stamps; None: t = k *
            sample_period.
        time_scale: seconds per unit of ``time_column`` (0.001 for a column in ms).
        delimiter: CSV field separator (one character); default ``","`` (tab for ``.tsv``).
        columns: twin channel name -> :class:`FileColumnMap`, at least one. The order of the
            table is the order of :attr:`FileDriver.channels`.
        realtime: False replays as fast as the caller reads; True delivers each row when its
            time stamp is due on the wall clock (relative to the first row delivered), never
            early and at most 1 s of the recording late (:data:`PACE_SLACK`: one wake-up
            per second of the recording).
        speed: with ``realtime``: the replay's speed over the recording's own (10: ten times
            faster, a 2 s window every 0.2 s; > 0, default 1).
        start: index of the first row to replay (0-based, like a Python slice; default 0).
        stop: index one past the last row to replay (default: the end of the file; with
            ``follow``, the end once that row is written).
        follow: CSV only: after the rows there at open, read the rows appended to the file as
            they are written (``tail -f``), until ``idle_timeout``; False: the file as it is
            at open (a file that grew meanwhile is said once at its end).
        idle_timeout: with ``follow``: seconds without a new row after which the file counts
            as finished (> 0; the run ends as at the end of a file).
    """

    file_keys: ClassVar[tuple[str, ...]] = ("path",)

    type: Literal["file"]
    path: Path
    format: Literal["csv", "mat", "auto"] = "auto"
    sample_period: StrictFloat | None = Field(default=None, gt=0, allow_inf_nan=False)
    time_column: str | None = Field(default=None, min_length=1)
    time_scale: StrictFloat = Field(default=1.0, gt=0, allow_inf_nan=False)
    delimiter: str | None = Field(default=None, min_length=1, max_length=1)
    columns: dict[str, FileColumnMap] = Field(min_length=1)
    realtime: bool = False
    speed: StrictFloat = Field(default=1.0, gt=0, le=1000, allow_inf_nan=False)
    start: StrictInt | None = Field(default=None, ge=0)
    stop: StrictInt | None = Field(default=None, ge=0)
    follow: bool = False
    idle_timeout: StrictFloat = Field(default=60.0, gt=0, allow_inf_nan=False)

    @model_validator(mode="after")
    def _check(self) -> FileDriverConfig:
        if self.sample_period is None and self.time_column is None:
            raise ValueError("sample_period is required unless time_column is given")
        # a table as dumped (every field, the default too) still validates: only a changed
        # idle_timeout is refused without follow
        default = type(self).model_fields["idle_timeout"].default
        if not self.follow and self.idle_timeout != default:
            raise ValueError("idle_timeout applies to a followed file only: set follow = true "
                             "or remove idle_timeout")
        if not self.realtime and self.speed != 1.0:
            raise ValueError("speed paces a realtime replay only: set realtime = true or "
                             "remove speed")
        if self.follow and self.sample_period is None:
            raise ValueError("sample_period is required with follow = true (the rows there at "
                             "open may be too few to infer it)")
        if self.start is not None and self.stop is not None and self.stop < self.start:
            raise ValueError(f"stop ({self.stop}) is before start ({self.start})")
        return self

    def twin_channels(self) -> tuple[str, ...]:
        """The twin channels this driver delivers (``columns``)."""
        return tuple(self.columns)



def _available(name: str, names: Iterable[str]) -> str:
    """``"did you mean 'X'? available: ..."`` for an error message (case-insensitive match)."""
    names = sorted(set(names))
    by_lower = {n.lower(): n for n in names}
    close = difflib.get_close_matches(name.lower(), list(by_lower), n=1)
    hint = f"did you mean {by_lower[close[0]]!r}? " if close else ""
    return hint + "available: " + (", ".join(names) if names else "none")


class FileDriver(Driver):
    """Replay a recorded CSV or MAT file as twin samples.

    Args: as :meth:`~twinwatch.drivers.base.Driver.from_config`'s.

    Attributes:
        sample_period: ``config.sample_period`` [s], or the median time step of
            ``time_column`` when no period is configured.
        n_rows: number of rows that will be replayed (after ``start``/``stop``).

    Raises:
        DriverConfigError: the file is missing or unreadable, its format is unknown, a
            mapped column or variable is missing (the message names the config key and lists
            the available ones), a MAT variable is not a numeric vector, or the variables have
            different lengths.
    """

    config_class = FileDriverConfig
    driver_name = "file"
    sample_machine = "dc-motor-recording"
    sample_title = "a DC motor recording replayed from a file"

    @classmethod
    def safe_to_probe(cls, config: DriverConfig) -> bool:
        """Opening reads the file's header and checks the mapped columns: no device."""
        return True

    @classmethod
    def time_starts_over(cls, config: DriverConfig) -> bool:
        """The recording is replayed from its start at every open: a new run."""
        return True

    def __init__(self, config: FileDriverConfig, *, base_dir: Path | None = None) -> None:
        super().__init__()
        try:
            self._setup(config.resolved(base_dir))
        except BaseException:
            self.close()
            raise

    # -- loading ----------------------------------------------------------------------------
    def _setup(self, config: FileDriverConfig) -> None:
        self.config = config
        self.channels = tuple(config.columns)
        # a real-time replay cannot wait for the estimator (architecture: a live source): a
        # full queue drops the window as an overrun instead of falling behind the clock
        self.live = config.realtime
        path = config.path
        if path.is_dir():
            raise DriverConfigError(f"path: {str(path)!r} is a directory: give the recording "
                                    f"file in it")
        if not path.is_file():
            raise DriverConfigError(f"path: file {str(path)!r} not found")
        fmt = config.format
        if fmt == "auto":
            suffix = path.suffix.lower()
            if suffix in _CSV_SUFFIXES:
                fmt = "csv"
            elif suffix in _MAT_SUFFIXES:
                fmt = "mat"
            else:
                raise DriverConfigError(
                    f"format: cannot tell the format of {str(path)!r} from its suffix "
                    f"{suffix!r}; set format = 'csv' or 'mat'"
                )
        self._size_at_open = _size(path)
        self._follow: _Tail | None = None
        if fmt == "csv":
            delimiter = config.delimiter or _CSV_SUFFIXES.get(path.suffix.lower(), ",")
            text: str | None = None
            if config.follow:  # the complete lines there now; the rest is read as it comes
                self._follow, text = _Tail.open(path, delimiter)
            table = self._load_csv(path, delimiter, text=text)
            if self._follow is not None:  # the header checked: where the columns are
                header = next(row for row in csv.reader(io.StringIO(text or ""),
                                                        delimiter=delimiter)
                              if any(cell.strip() for cell in row))
                header = [h.strip() for h in header]
                self._follow.index = {c: header.index(c) for _, c in self._keys()}
        elif config.follow:
            raise DriverConfigError(f"follow: {path.name} is a MAT file, written whole; "
                                    "follow = true reads a CSV still being written")
        else:
            table = self._load_mat(path)
        n_total = len(next(iter(table.values())))
        t, values = self._arrays(table.__getitem__, n_total, 0)
        lo, hi, _ = slice(config.start, config.stop).indices(n_total)
        self._t: FloatArray = t[lo:hi]
        self._values: FloatArray = values[lo:hi]
        self.n_rows = len(self._t)
        self._base = 0  # rows dropped from the front of _t (delivered) while following
        self._rows_in_file = n_total  # rows of the file read so far (before start/stop)
        self.sample_period = (
            config.sample_period
            if config.sample_period is not None
            else self._median_step(self._t, config.time_column)
        )
        self._next = 0
        self._chunk: list[list[float]] = []  # rows _chunk_lo.. as Python floats
        self._chunk_lo = 0
        self._origin: tuple[float, float] | None = None  # (wall clock, file time) of 1st row
        self._last_paced = -math.inf  # file time of the last row paced
        logger.info(
            "file driver ready: %s (%s), rows %d..%d of %d, sample period %g s, channels %s",
            path,
            fmt,
            lo,
            hi,
            n_total,
            self.sample_period,
            ", ".join(self.channels),
        )

    @staticmethod
    def _median_step(t: FloatArray, column: str | None) -> float:
        steps = np.diff(t[np.isfinite(t)])
        steps = steps[steps > 0]
        if steps.size == 0:
            raise DriverConfigError(
                f"sample_period: cannot infer it from time_column {column!r} "
                "(fewer than two increasing time stamps); set sample_period"
            )
        return float(np.median(steps))

    def _load_csv_fast(self, path: Path, delimiter: str, text: str | None = None
                       ) -> dict[str, FloatArray] | None:
        """The columns of a well-formed CSV (a header, then numbers only: no quotes, no empty
        or missing cells) read by numpy's parser, without a Python object per cell; None for
        anything else, which :meth:`_load_csv` reads cell by cell."""
        try:
            skip, line = 0, ""
            with _open_text(path, text) as f:
                while not line.strip():  # the header: the first line that is not blank
                    line = f.readline()
                    skip += 1
                    if not line:
                        return None
            if '"' in line:
                return None
            header = [h.strip() for h in line.rstrip("\r\n").split(delimiter)]
            columns = [column for _, column in self._keys()]
            if any(header.count(c) != 1 for c in columns):
                return None  # the cell-by-cell reading names what is wrong
            used = sorted({header.index(c) for c in columns})
            with warnings.catch_warnings():  # a header alone: said below, naming the key
                warnings.simplefilter("ignore", UserWarning)
                data = np.loadtxt(path if text is None else io.StringIO(text),
                                  delimiter=delimiter, skiprows=skip, usecols=used,
                                  ndmin=2, comments=None, encoding="utf-8-sig",
                                  dtype=np.float64)
        except (OSError, UnicodeDecodeError, ValueError):
            return None
        if data.shape[0] == 0:
            return None
        return {c: np.ascontiguousarray(data[:, used.index(header.index(c))]) for c in columns}

    def _load_csv(self, path: Path, delimiter: str, text: str | None = None
                  ) -> dict[str, FloatArray]:
        """The mapped columns of the CSV at ``path`` (or of ``text``, its complete lines as
        read at open when it is followed: then a header alone is no error)."""
        fast = self._load_csv_fast(path, delimiter, text)
        if fast is not None:
            return fast
        # One physical line is one row: a numeric recording never quotes a line break, so a
        # quote left open costs its own row only (read as NaN, named by its line), never the
        # rest of the file (the csv module would read it all as one cell).
        header: list[str] | None = None
        rows: list[list[str]] = []
        open_quotes: list[int] = []
        try:
            with _open_text(path, text) as f:
                for lineno, line in enumerate(f, start=1):
                    if not line.strip():
                        continue
                    if line.count('"') % 2:
                        open_quotes.append(lineno)
                    row = next(csv.reader((line.rstrip("\r\n"),), delimiter=delimiter), [])
                    if header is None:
                        header = row
                    elif any(cell.strip() for cell in row):
                        rows.append(row)
        except (OSError, UnicodeDecodeError, csv.Error) as exc:
            raise DriverConfigError(f"path: cannot read CSV {str(path)!r}: {exc}") from exc
        if open_quotes:
            logger.warning(
                "CSV %s: a quote is not closed on %d line(s) (first: line %d); each such "
                "row is read up to its end and its cells that are not numbers are NaN",
                path.name,
                len(open_quotes),
                open_quotes[0],
            )
        if header is None:
            raise DriverConfigError(f"path: CSV {str(path)!r} is empty (no header row)")
        header = [h.strip() for h in header]
        index: dict[str, int] = {}
        key_of: dict[str, str] = {}
        for key, column in self._keys():
            key_of.setdefault(column, key)
            if header.count(column) > 1:
                raise DriverConfigError(
                    f"{key}: column {column!r} appears {header.count(column)} times in "
                    f"{str(path)!r}"
                )
            if column not in header:
                raise DriverConfigError(
                    f"{key}: column {column!r} not in {path.name}; {_available(column, header)}"
                )
            index[column] = header.index(column)
        if not rows and self._follow is None:
            raise DriverConfigError(f"path: CSV {str(path)!r} has no data rows")

        table: dict[str, FloatArray] = {}
        for column, j in index.items():
            out, not_numbers, example = _cells(rows, j)
            if not_numbers and not np.isfinite(out).any():
                # a column of text (a state, a label): every window would be abandoned
                raise DriverConfigError(
                    f"{key_of[column]}: column {column!r} of {path.name} holds text, not "
                    f"numbers ({not_numbers} cells, e.g. {example[:20]!r}): map a column of "
                    f"numbers")
            if not_numbers:
                logger.warning(
                    "CSV %s column %r: %d cells are not numbers; read as NaN",
                    path.name,
                    column,
                    not_numbers,
                )
            table[column] = out
        return table

    def _load_mat(self, path: Path) -> dict[str, FloatArray]:
        try:
            import scipy.io  # loaded for a MAT file only

            mat = scipy.io.loadmat(path)
        except NotImplementedError as exc:  # MATLAB v7.3 files are HDF5
            raise DriverConfigError(
                f"path: {str(path)!r} is a MATLAB v7.3 (HDF5) file; save it with -v7: {exc}"
            ) from exc
        except (OSError, ValueError, TypeError) as exc:
            raise DriverConfigError(f"path: cannot read MAT {str(path)!r}: {exc}") from exc
        variables = [name for name in mat if not name.startswith("__")]
        table: dict[str, FloatArray] = {}
        length: tuple[str, int] | None = None
        for key, name in self._keys():
            if name not in mat or name.startswith("__"):
                raise DriverConfigError(
                    f"{key}: variable {name!r} not in {path.name}; {_available(name, variables)}"
                )
            array = np.asarray(mat[name])
            if array.dtype.kind not in "biuf" or sum(d > 1 for d in array.shape) > 1:
                raise DriverConfigError(
                    f"{key}: variable {name!r} in {path.name} is not a numeric vector "
                    f"(dtype {array.dtype}, shape {array.shape})"
                )
            vector = array.astype(np.float64).ravel()
            if length is not None and vector.size != length[1]:
                raise DriverConfigError(
                    f"{key}: variable {name!r} has {vector.size} samples, "
                    f"{length[0]!r} has {length[1]}"
                )
            length = (name, vector.size)
            table[name] = vector
        if length is None or length[1] == 0:
            raise DriverConfigError(f"path: {str(path)!r}: the variables are empty")
        return table

    def _arrays(self, column: Callable[[str], FloatArray], n: int, first: int
                ) -> tuple[FloatArray, FloatArray]:
        """(t (n,), values (n, channels) in the twin's units) of ``n`` rows whose columns
        ``column(name)`` gives; ``first``: the file row of the first (``t = k *
        sample_period``)."""
        cfg = self.config
        values = np.empty((n, len(self.channels)), dtype=np.float64)
        for j, mapping in enumerate(cfg.columns.values()):
            values[:, j] = column(mapping.column) * mapping.scale + mapping.offset
        if cfg.time_column is not None:
            return column(cfg.time_column) * cfg.time_scale, values
        assert cfg.sample_period is not None  # checked by the config model
        return (first + np.arange(n, dtype=np.float64)) * cfg.sample_period, values

    def _keys(self) -> list[tuple[str, str]]:
        """(config key, column) of every column to load; the key names it in errors."""
        keys = [(f"columns.{ch}", m.column) for ch, m in self.config.columns.items()]
        if self.config.time_column is not None:
            keys.append(("time_column", self.config.time_column))
        return keys

    # -- reading ----------------------------------------------------------------------------
    def _read_internal(self, timeout: float | None) -> Sample | None:
        while True:
            k = self._next
            if k >= len(self._t):
                if self._follow is None:
                    self._say_grown()
                    raise EndOfStream(f"end of {self.config.path.name} after {self.n_rows} rows")
                if not self._wait_for_rows(timeout):
                    return None
                continue
            t = float(self._t[k])
            if self.config.realtime and math.isfinite(t) and not self._wait_until(t, timeout):
                return None
            self._next = k + 1
            self.stats.frames += 1
            if not math.isfinite(t):
                self.stats.bad_frames += 1
                self.log_once(
                    "time",
                    "%s row %d has no valid time stamp; row skipped (stats.bad_frames)",
                    self.config.path.name,
                    self._base + k,
                )
                continue
            if not self._chunk_lo <= k < self._chunk_lo + len(self._chunk):
                # rows as Python floats a chunk at a time: a dict from floats is ~4x faster
                # than from a numpy row; the whole file as lists would take 5x the memory
                self._chunk_lo = k
                self._chunk = self._values[k:k + _CHUNK_ROWS].tolist()
            values = dict(zip(self.channels, self._chunk[k - self._chunk_lo], strict=True))
            if not all(map(math.isfinite, values.values())):
                bad = [ch for ch, v in values.items() if not math.isfinite(v)]
                self.stats.bad_values += len(bad)
                self.log_once(
                    "nonfinite",
                    "%s row %d: %s empty or not finite; delivered as NaN (stats.bad_values)",
                    self.config.path.name,
                    self._base + k,
                    ", ".join(bad),
                )
            return Sample(t, values)

    reads_blocks = True

    def _read_block_internal(self, timeout: float | None, limit: int
                             ) -> tuple[FloatArray, FloatArray] | None:
        """The rows :meth:`_read_internal` would deliver next without a second look (a
        finite stamp, not before the last one, finite values; in real time those due now),
        up to ``limit``; any other row alone, through :meth:`_read_internal`."""
        k = self._next
        end = min(len(self._t), k + max(min(limit, _BLOCK_ROWS), 1))
        t = self._t[k:end]
        if t.size and np.isfinite(t[0]) and t[0] >= self._last_paced:
            ok = np.isfinite(t) & np.isfinite(self._values[k:end]).all(axis=1)
            ok[1:] &= t[1:] >= t[:-1]
            n = t.size if ok.all() else int(np.argmin(ok))
            if n:
                if self.config.realtime:
                    if not self._wait_until(float(t[0]), timeout):
                        return None
                    assert self._origin is not None
                    due = self._origin[1] + (time.monotonic() - self._origin[0]) * self.config.speed
                    n = max(1, int(np.searchsorted(t[:n], due, side="right")))
                    self._last_paced = float(t[n - 1])
                self._next = k + n
                self.stats.frames += n
                return t[:n], self._values[k:k + n]
        sample = self._read_internal(timeout)
        if sample is None:
            return None
        return (np.array([sample.t]),
                np.array([[sample.values[c] for c in self.channels]], dtype=np.float64))

    def _say_grown(self) -> None:
        """Once, at the end of a file opened without ``follow``: say that it grew since."""
        size = _size(self.config.path)
        if size > self._size_at_open and "grown" not in self._logged_once:
            self.log_once(
                "grown",
                "%s grew by %d bytes after it was opened (still being written?): the rows "
                "written since are not replayed; set driver.follow = true to read them as they "
                "come",
                self.config.path.name,
                size - self._size_at_open,
            )

    def _wait_for_rows(self, timeout: float | None) -> bool:
        """A followed file whose rows are all replayed: wait up to ``timeout`` [s] (None: until
        a row comes) for rows appended to it. True when some came.

        Raises:
            EndOfStream: no row for ``idle_timeout`` s, the file was truncated or replaced,
                or ``stop`` rows were read.
        """
        tail = self._follow
        assert tail is not None
        cfg = self.config
        end = None if timeout is None else time.monotonic() + timeout
        delivered = self._base + self._next
        if delivered != tail.delivered:  # idle from the last row delivered, or come
            tail.delivered = delivered
            tail.last_row = max(tail.last_row, time.monotonic())
        while True:
            if cfg.stop is not None and self._rows_in_file >= cfg.stop:
                raise EndOfStream(f"end of {cfg.path.name} after {self.n_rows} rows "
                                  f"(driver.stop = {cfg.stop})")
            lines = tail.poll()
            if lines is None:
                self.log_once("replaced", "%s was truncated or replaced while followed: "
                              "its run ends here (start again to read the new file)",
                              cfg.path.name)
                raise EndOfStream(f"end of {cfg.path.name}: truncated or replaced after "
                                  f"{self.n_rows} rows")
            if lines and self._append(lines):
                return True
            idle = time.monotonic() - tail.last_row
            if idle >= cfg.idle_timeout:
                raise EndOfStream(f"end of {cfg.path.name}: no new row for "
                                  f"{cfg.idle_timeout:g} s (driver.idle_timeout) after "
                                  f"{self.n_rows} rows")
            now = time.monotonic()
            if end is not None and now >= end:
                return False
            pause = min(FOLLOW_POLL, cfg.idle_timeout - idle)
            time.sleep(max(0.0, pause if end is None else min(pause, end - now)))

    def _append(self, lines: list[str]) -> int:
        """Parse the complete lines appended to a followed file and queue their rows (those
        within ``start``/``stop``); the rows already delivered are dropped. Returns the rows
        queued."""
        tail = self._follow
        assert tail is not None and tail.index is not None
        index = tail.index
        cfg = self.config
        rows = [row for row in csv.reader(lines, delimiter=tail.delimiter)
                if any(cell.strip() for cell in row)]
        if not rows:
            return 0
        first = self._rows_in_file
        self._rows_in_file += len(rows)
        lo = max(cfg.start or 0, first) - first
        hi = len(rows) if cfg.stop is None else max(0, min(len(rows), cfg.stop - first))
        rows = rows[lo:hi] if lo < hi else []
        if not rows:
            return 0
        tail.last_row = time.monotonic()
        # an empty cell or text: NaN, counted when delivered
        t, values = self._arrays(lambda name: _cells(rows, index[name])[0], len(rows),
                                 first + lo)
        done = self._next  # delivered: dropped, so a file followed for days stays small
        self._t = np.concatenate((self._t[done:], t))
        self._values = np.concatenate((self._values[done:], values))
        self._base += done
        self._next = 0
        self._chunk, self._chunk_lo = [], 0
        self.n_rows = self._base + len(self._t)
        return len(rows)

    def _wait_until(self, t: float, timeout: float | None) -> bool:
        """Sleep until file time ``t`` is due; False if ``timeout`` [s] ran out first."""
        now = time.monotonic()
        if self._origin is None or t < self._last_paced:
            # the first row, or a capture that restarts its clock (two recordings one after
            # the other): paced from here, not bursting until its time catches up
            self._origin = (now, t)
        self._last_paced = t
        wait = self._origin[0] + (t - self._origin[1]) / self.config.speed - now
        if wait <= 0:
            return True
        if timeout is not None and wait > timeout:
            time.sleep(max(timeout, 0.0))
            return False
        # never early; up to PACE_SLACK of the recording late, so the rows due meanwhile come
        # in one wake-up
        late = wait + PACE_SLACK / self.config.speed
        time.sleep(late if timeout is None else min(late, timeout))
        return True


def _cells(rows: list[list[str]], j: int) -> tuple[FloatArray, int, str]:
    """Column ``j`` of CSV ``rows`` as numbers (NaN for an empty or missing cell and for
    text), the count of cells that are not numbers, and the first of them."""
    out = np.full(len(rows), np.nan)
    not_numbers, example = 0, ""
    for k, row in enumerate(rows):
        cell = row[j].strip() if j < len(row) else ""
        if not cell:
            continue
        try:
            out[k] = float(cell)
        except ValueError:
            not_numbers += 1
            example = example or cell
    return out, not_numbers, example


def _size(path: Path) -> int:
    try:
        return path.stat().st_size
    except OSError:
        return 0


def _open_text(path: Path, text: str | None) -> io.TextIOBase:
    """The CSV's lines: the file, or ``text`` (its lines as read at open when followed)."""
    if text is not None:
        return io.StringIO(text, newline="")
    return path.open(newline="", encoding="utf-8-sig")  # type: ignore[return-value]


class _Tail:
    """A CSV followed as it is written: where its complete lines end, which file it is.

    Attributes:
        offset: bytes read so far (the end of the last complete line read).
        inode: the file's (device, inode) at open: another file under its name is a
            replacement (a logger's rotation).
        index: column name -> its index in the header (set once the header is read).
        last_row: monotonic time [s] a row last came, or the rows queued were last all
            delivered (what ``idle_timeout`` counts from).
        delivered: the rows delivered when the replay last waited for more.
    """

    def __init__(self, path: Path, delimiter: str, offset: int, inode: tuple[int, int]
                 ) -> None:
        self.path = path
        self.delimiter = delimiter
        self.offset = offset
        self.inode = inode
        self.index: dict[str, int] | None = None
        self.last_row = time.monotonic()
        self.delivered = -1  # rows delivered when the replay last waited for more

    @classmethod
    def open(cls, path: Path, delimiter: str) -> tuple[_Tail, str]:
        """Start following ``path``: its complete lines now (a line being written is read
        once it ends) as text, and the tail after them.

        Raises:
            DriverConfigError: the file cannot be read, or it is not UTF-8.
        """
        try:
            with path.open("rb") as f:
                st = os.fstat(f.fileno())
                data = f.read()
        except OSError as exc:
            raise DriverConfigError(f"path: cannot read CSV {str(path)!r}: {exc}") from exc
        cut = data.rfind(b"\n") + 1
        try:
            text = data[:cut].decode("utf-8-sig")
        except UnicodeDecodeError as exc:
            raise DriverConfigError(f"path: cannot read CSV {str(path)!r}: {exc}") from exc
        return cls(path, delimiter, cut, (st.st_dev, st.st_ino)), text

    def poll(self) -> list[str] | None:
        """The complete lines appended since the last poll ([] when none); None when the file
        was truncated, replaced or removed."""
        try:
            with self.path.open("rb") as f:
                st = os.fstat(f.fileno())
                if (st.st_dev, st.st_ino) != self.inode or st.st_size < self.offset:
                    return None
                if st.st_size == self.offset:
                    return []
                f.seek(self.offset)
                data = f.read(st.st_size - self.offset)
        except FileNotFoundError:
            return None
        except OSError:
            return []  # read again at the next poll
        cut = data.rfind(b"\n") + 1
        self.offset += cut
        return data[:cut].decode("utf-8", errors="replace").splitlines()
