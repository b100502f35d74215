"""File replay driver: twin samples from a recording (CSV or MATLAB ``.mat``).

The whole recording is loaded when the driver is opened (recordings of a few hours at 100 Hz
are a few tens of MB) and replayed row by row, as fast as the caller reads or paced by the wall
clock (``realtime = true``). After the last row :meth:`~twinwatch.drivers.base.Driver.read`
raises :class:`~twinwatch.drivers.base.EndOfStream`.

Time stamps: ``t = k * sample_period`` where ``k`` is the row's index in the file (0-based,
counted before ``start`` is applied, so a cut recording keeps its own clock), or, with
``time_column``, ``t = value * time_scale`` read from that column. Rows are delivered as the
logger wrote them: an exact duplicate (a logger's retry) is dropped and counted by the ring
buffer, a stamp repeated with other values abandons only the window it falls in, and a
capture that restarts its clock (two files concatenated) costs at most the window at the seam
(a real-time replay is paced from the seam on).

Formats:

* CSV: one header row naming the columns, then one row per line; cells are decimal numbers.
  An empty or non-numeric cell is read as NaN; a row with fewer cells than the header has NaN
  in the missing cells. Blank lines are skipped. A quote left open is logged with its line
  number and costs that row only.
* MAT (MATLAB v5/v7, read with :func:`scipy.io.loadmat`; v7.3/HDF5 is not supported): every
  mapped "column" is a numeric variable holding a vector (N x 1, 1 x N or N), all of the same
  length N. MAT files usually hold no time vector, hence ``sample_period``.

Bad input is counted, logged once, and the driver goes on (see
:class:`~twinwatch.drivers.base.DriverStats`): NaN or infinite values count in
``stats.bad_values`` and are delivered as they are; a row whose time stamp is not a number is
skipped and counts in ``stats.bad_frames``.

Example configuration (TOML) for the MotoShield recording::

    [driver]
    type = "file"
    path = "../../shared/data/motoshield/aprbsResult.mat"  # relative to the config file
    sample_period = 0.02
    [driver.columns]
    Va = { column = "u" }
    omega = { column = "y" }
    ia = { column = "ifltr" }
"""

from __future__ import annotations

import csv
import difflib
import logging
import math
import time
import warnings
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any, Literal

import numpy as np
import numpy.typing as npt
from pydantic import ConfigDict, Field, StrictFloat, StrictInt, model_validator

from twinwatch.drivers.base import (
    Driver,
    DriverConfig,
    DriverConfigError,
    EndOfStream,
    Sample,
    ScaledChannel,
    validated_config,
)

logger = logging.getLogger(__name__)

__all__ = ["FileColumnMap", "FileDriver", "FileDriverConfig"]

_CSV_SUFFIXES = {".csv": ",", ".txt": ",", ".tsv": "\t"}
_MAT_SUFFIXES = {".mat"}

FloatArray = npt.NDArray[np.float64]


#: A real-time replay delivers a row at most this late [s]: it sleeps until the next row is
#: due plus this, and the rows due by then follow at once (one wake-up per 0.2 s, not one a
#: row; a window of the daemon is seconds long and stamped by the file's clock). A wake-up
#: costs 70-190 us of CPU on a virtual machine (measured): at 0.1 s, 3.8 ms a 2 s window,
#: at 0.2 s (the acquisition loop's read timeout, which caps a sleep anyway) 2 ms.
PACE_SLACK = 0.2

#: Rows converted to Python floats at once (:meth:`FileDriver._read_internal`).
_CHUNK_ROWS = 256


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
            early and at most 0.1 s late (:data:`PACE_SLACK`: one wake-up per 0.1 s).
        start: index of the first row to replay (0-based, like a Python slice; default 0).
        stop: index one past the last row to replay (default: the end of the file).
    """

    model_config = ConfigDict(extra="forbid")

    type: Literal["file"]
    path: Path
    format: Literal["csv", "mat", "auto"] = "auto"
    sample_period: StrictFloat | None = Field(default=None, gt=0, allow_inf_nan=False)
    time_column: str | None = Field(default=None, min_length=1)
    time_scale: StrictFloat = Field(default=1.0, gt=0, allow_inf_nan=False)
    delimiter: str | None = Field(default=None, min_length=1, max_length=1)
    columns: dict[str, FileColumnMap] = Field(min_length=1)
    realtime: bool = False
    start: StrictInt | None = Field(default=None, ge=0)
    stop: StrictInt | None = Field(default=None, ge=0)

    @model_validator(mode="after")
    def _check(self) -> FileDriverConfig:
        if self.sample_period is None and self.time_column is None:
            raise ValueError("sample_period is required unless time_column is given")
        if self.start is not None and self.stop is not None and self.stop < self.start:
            raise ValueError(f"stop ({self.stop}) is before start ({self.start})")
        return self

    def twin_channels(self) -> tuple[str, ...]:
        """The twin channels this driver delivers (``columns``)."""
        return tuple(self.columns)

    def required_files(self, base_dir: Path) -> dict[str, Path]:
        """Config key -> file that must exist to start (``path``)."""
        return {"driver.path": self.resolved(base_dir).path}

    def resolved(self, base_dir: Path | None) -> FileDriverConfig:
        """Return a copy whose relative ``path`` is joined to ``base_dir``."""
        if base_dir is None:
            return self
        path = self.path.expanduser()
        if path.is_absolute():
            return self
        return self.model_copy(update={"path": Path(base_dir) / path})


def _available(name: str, names: Iterable[str]) -> str:
    """``"did you mean 'X'? available: ..."`` for an error message (case-insensitive match)."""
    names = sorted(set(names))
    by_lower = {n.lower(): n for n in names}
    close = difflib.get_close_matches(name.lower(), list(by_lower), n=1)
    hint = f"did you mean {by_lower[close[0]]!r}? " if close else ""
    return hint + "available: " + (", ".join(names) if names else "none")


class FileDriver(Driver):
    """Replay a recorded CSV or MAT file as twin samples.

    Args:
        config: the validated configuration (see :class:`FileDriverConfig`).
        base_dir: directory that a relative ``path`` is resolved against (the configuration
            file's directory); None means the current directory.

    Attributes:
        channels: twin channel names, in the order of ``config.columns``.
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
    sample_model = "dc_motor"
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

    @classmethod
    def from_config(
        cls, config: FileDriverConfig | Mapping[str, Any], *, base_dir: Path | None = None
    ) -> FileDriver:
        """Build a driver from a validated config or a raw ``[driver]`` table.

        Raises:
            DriverConfigError: the table does not validate, or see :class:`FileDriver`.
        """
        config = validated_config(FileDriverConfig, config, "file")
        return cls(config, base_dir=base_dir)

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
        if fmt == "csv":
            delimiter = config.delimiter or _CSV_SUFFIXES.get(path.suffix.lower(), ",")
            table = self._load_csv(path, delimiter)
        else:
            table = self._load_mat(path)
        n_total = len(next(iter(table.values())))

        # values: one row per sample, one column per channel, in the twin's units
        values = np.empty((n_total, len(self.channels)), dtype=np.float64)
        for j, mapping in enumerate(config.columns.values()):
            values[:, j] = table[mapping.column] * mapping.scale + mapping.offset
        if config.time_column is not None:
            t = table[config.time_column] * config.time_scale
        else:
            assert config.sample_period is not None  # checked by the config model
            t = np.arange(n_total, dtype=np.float64) * config.sample_period

        lo, hi, _ = slice(config.start, config.stop).indices(n_total)
        self._t: FloatArray = t[lo:hi]
        self._values: FloatArray = values[lo:hi]
        self.n_rows = len(self._t)
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

    def _load_csv_fast(self, path: Path, delimiter: str) -> dict[str, FloatArray] | None:
        """The columns of a well-formed CSV (a header, then numbers only: no quotes, no empty
        or missing cells) read by numpy's parser, without a Python object per cell (a 15,400-
        row recording: 51 -> 12 ms of CPU, and about 1 MB less left in a fleet worker's heap);
        None for anything else, which :meth:`_load_csv` reads cell by cell."""
        try:
            skip, line = 0, ""
            with path.open(newline="", encoding="utf-8-sig") as f:
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
                data = np.loadtxt(path, delimiter=delimiter, skiprows=skip, usecols=used,
                                  ndmin=2, comments=None, encoding="utf-8-sig",
                                  dtype=np.float64)
        except (OSError, UnicodeDecodeError, ValueError):
            return None
        if data.shape[0] == 0:
            return None
        return {c: np.ascontiguousarray(data[:, used.index(header.index(c))]) for c in columns}

    def _load_csv(self, path: Path, delimiter: str) -> dict[str, FloatArray]:
        fast = self._load_csv_fast(path, delimiter)
        if fast is not None:
            return fast
        # One physical line is one row: a numeric recording never quotes a line break, so a
        # quote left open costs its own row only (read as NaN, named by its line), never the
        # rest of the file (the csv module would read it all as one cell).
        header: list[str] | None = None
        rows: list[list[str]] = []
        open_quotes: list[int] = []
        try:
            with path.open(newline="", encoding="utf-8-sig") as f:
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
        if not rows:
            raise DriverConfigError(f"path: CSV {str(path)!r} has no data rows")

        table: dict[str, FloatArray] = {}
        for column, j in index.items():
            out = np.full(len(rows), np.nan)
            not_numbers = 0
            example = ""
            for k, row in enumerate(rows):
                cell = row[j].strip() if j < len(row) else ""
                if not cell:
                    continue
                try:
                    out[k] = float(cell)
                except ValueError:
                    not_numbers += 1
                    example = example or cell
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
            if k >= self.n_rows:
                raise EndOfStream(f"end of {self.config.path.name} after {self.n_rows} rows")
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
                    k,
                )
                continue
            if not self._chunk_lo <= k < self._chunk_lo + len(self._chunk):
                # rows as Python floats a chunk at a time: a dict from a list of floats costs
                # 0.3 us, from a numpy row 1.1 us; the whole file as lists would take five
                # times its array's memory
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
                    k,
                    ", ".join(bad),
                )
            return Sample(t, values)

    def _wait_until(self, t: float, timeout: float | None) -> bool:
        """Sleep until file time ``t`` is due; False if ``timeout`` [s] ran out first."""
        now = time.monotonic()
        if self._origin is None or t < self._last_paced:
            # the first row, or a capture that restarts its clock (two recordings one after
            # the other): paced from here, not bursting until its time catches up
            self._origin = (now, t)
        self._last_paced = t
        wait = self._origin[0] + (t - self._origin[1]) - now
        if wait <= 0:
            return True
        if timeout is not None and wait > timeout:
            time.sleep(max(timeout, 0.0))
            return False
        # never early; up to PACE_SLACK late, so the rows due meanwhile come in one wake-up
        # (a sleep per 10 ms row cost 74 us of CPU a row, 15 ms per 2 s window)
        late = wait + PACE_SLACK
        time.sleep(late if timeout is None else min(late, timeout))
        return True
