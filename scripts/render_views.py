"""Render what an operator sees: run the examples, screenshot their recordings, write the PNGs
(to ``build/views/``; with ``--update`` over the tracked ``docs/images/`` the docs show).

    python scripts/render_views.py                 # all four, into build/views/ (a few min)
    python scripts/render_views.py --update        # the same, written over docs/images/*.png
    python scripts/render_views.py --only discovery --keep /tmp/views --out /tmp/views

For each example it runs ``twinwatch run`` as a user does (``--fresh``, in a directory of its
own, Zenoh off so nothing else on the machine is disturbed, the simulated Modbus device on a
free port), opens the recording's link in the Rerun viewer (``rerun FILE --renderer vulkan
--window-size 1600x1000 --screenshot-to``, under Xvfb with Mesa's Vulkan) without touching it:
what the default blueprint shows is what the picture shows. The screenshot (HiDPI, 3200x2000)
is scaled to 1600x1000 and quantised to 256 colours.

* ``demo``: the default configuration (``twinwatch sample-config``), stopped at 1000 s of
  plant time (``--duration``): Ra drifts from 6.5 ohm, its RUL warning and alarm raised, the
  deviation warning at about 14:38 (878 s), the deviation alarm predicted at about 18:10
  (1090 s) with its interval: the picture shows the RUL before the alarm;
* ``discovery``: ``config/dc-motor-unbalanced-sim.toml``, 300 s: the periodic term of the
  unbalanced shaft (paper Eq. 13) and its meaning in the model panel;
* ``hydraulic``: ``config/hydraulic-modbus-sim.toml`` stopped at 435 s: D, the fluid, rising
  from 100 N/(m/s), the warning at about 5:44 (344 s), the alarm predicted for about 7:28;
* ``leak``: ``config/hydraulic-modbus-leak-sim.toml``, 300 s: the internal leak discovered as
  a meta-model term, the diagnosis naming the piston seal (not the fluid) in the model panel.

The hydraulic run stops a little after a whole minute (435 s, not 420): the viewer labels the
time axis at whole minutes and clips a label on the plot's right edge (``+7m`` was cut in half;
the 300 s runs end at 299.99 s, before their ``+5m``).

Needs: ``xvfb-run`` and Mesa's Vulkan driver (Debian: xvfb, mesa-vulkan-drivers), Pillow
(``pip install -e '.[dev]'``). Prints, per example, the run's wall time, the recording's size
and the PNG's size.
"""

from __future__ import annotations

import argparse
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
IMAGES = ROOT / "docs" / "images"
BUILD = ROOT / "build" / "views"
SIZE = (1600, 1000)


@dataclass(frozen=True)
class Example:
    name: str
    config: Path | None  # None: the built-in default (twinwatch sample-config)
    recording: str  # its [recording] path
    what: str
    duration: float | None = None  # plant time to run [s] (None: the configuration's)


EXAMPLES = (
    Example("demo", None, "twinwatch.rrd", "the default: Ra degrades, 1000 s", 1000.0),
    Example("discovery", ROOT / "config" / "dc-motor-unbalanced-sim.toml",
            "twinwatch-unbalanced.rrd", "discovery: the unbalanced shaft's periodic term"),
    Example("hydraulic", ROOT / "config" / "hydraulic-modbus-sim.toml",
            "twinwatch-hydraulic.rrd", "the hydraulic actuator: D, the fluid, degrades",
            435.0),
    Example("leak", ROOT / "config" / "hydraulic-modbus-leak-sim.toml",
            "twinwatch-hydraulic-leak.rrd", "the internal leak: discovered, the seal named, D "
            "not reported as the fluid"),
)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
    return port


def _config(example: Example, work: Path) -> Path:
    """The example's configuration, written to ``work``: Zenoh off, a free Modbus port."""
    if example.config is None:
        text = subprocess.run([sys.executable, "-m", "twinwatch", "sample-config"],
                              check=True, capture_output=True, text=True).stdout
    else:
        text = example.config.read_text()
    text = text.replace("[zenoh]", "[zenoh]\nenabled = false", 1)
    text = text.replace("port = 5020 ", f"port = {_free_port()} ", 1)
    path = work / f"{example.name}.toml"
    path.write_text(text)
    return path


def _screenshot(recording: Path, out: Path) -> None:
    """The Rerun viewer's first frame of ``recording`` at 1600x1000 (the pointer is off the
    window: no tooltip)."""
    rerun = shutil.which("rerun", path=str(Path(sys.executable).parent)) or "rerun"
    cmd = ["xvfb-run", "-a", "-s", "-screen 0 7000x4200x24", rerun, str(recording),
           "--renderer", "vulkan", "--window-size", f"{SIZE[0]}x{SIZE[1]}",
           "--screenshot-to", str(out)]
    # RUST_LOG=error: the viewer's start-up notices (Docker, the software rasteriser) were
    # in some pictures as toasts over the top right views
    done = subprocess.run(cmd, env={**os.environ, "CI": "true", "RUST_LOG": "error"},
                          capture_output=True, text=True, timeout=600)
    if done.returncode != 0 or not out.exists():
        raise SystemExit(f"the viewer did not write {out}:\n{done.stderr[-2000:]}")


def _small(raw: Path, out: Path) -> None:
    """``raw`` scaled to 1600x1000 and quantised to 256 colours (no dithering: the text stays
    sharp)."""
    try:
        from PIL import Image
    except ImportError:
        raise SystemExit("Pillow is needed: pip install -e '.[dev]'") from None
    with Image.open(raw) as im:
        small = im.convert("RGB").resize(SIZE, Image.Resampling.LANCZOS)
    small.quantize(colors=256, method=Image.Quantize.FASTOCTREE,
                   dither=Image.Dither.NONE).save(out, optimize=True)


def render(example: Example, work: Path, images: Path) -> None:
    work.mkdir(parents=True, exist_ok=True)
    config = _config(example, work)
    t0 = time.monotonic()
    duration = ["--duration", f"{example.duration:g}"] if example.duration else []
    run = subprocess.run([sys.executable, "-m", "twinwatch", "run", str(config), "--fresh",
                          "--no-progress", *duration], cwd=work, capture_output=True,
                         text=True)
    took = time.monotonic() - t0
    if run.returncode != 0:
        raise SystemExit(f"{example.name}: twinwatch run exited {run.returncode}:\n"
                         f"{run.stdout[-3000:]}\n{run.stderr[-3000:]}")
    recording = work / example.recording
    raw = work / f"{example.name}-raw.png"
    _screenshot(recording, raw)
    images.mkdir(parents=True, exist_ok=True)
    out = images / f"{example.name}.png"
    _small(raw, out)
    print(f"{example.name:<10} {example.what}: run {took:.0f} s, recording "
          f"{recording.resolve().stat().st_size / 2**20:.1f} MiB, {out} "
          f"{out.stat().st_size / 1024:.0f} KiB")


def images_dir(argv: list[str] | None = None) -> Path:
    """Where the PNGs go for these arguments: ``build/views/`` (or ``--out``), the tracked
    ``docs/images/`` only with ``--update``."""
    args = _parser().parse_args(argv)
    return IMAGES if args.update else Path(args.out)


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--only", choices=[e.name for e in EXAMPLES], action="append",
                        help="render only this example (repeatable)")
    parser.add_argument("--keep", type=Path, help="run in this directory and keep it "
                        "(default: a temporary directory, removed)")
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--out", type=Path, default=BUILD,
                       help="write the PNGs here (default: build/views/, not tracked)")
    where.add_argument("--update", action="store_true",
                       help="write the PNGs over the tracked docs/images/*.png")
    return parser


def main() -> None:
    args = _parser().parse_args()
    images = IMAGES if args.update else args.out
    chosen = [e for e in EXAMPLES if not args.only or e.name in args.only]
    if args.keep is not None:
        for example in chosen:
            render(example, args.keep / example.name, images)
        return
    with tempfile.TemporaryDirectory(prefix="twinwatch-views-") as tmp:
        for example in chosen:
            render(example, Path(tmp) / example.name, images)


if __name__ == "__main__":
    main()
