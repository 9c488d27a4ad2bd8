"""The package's one logger, and the switch that keeps pycolmap/glog quiet."""

import contextlib
import logging
import math
import os
import sys
import time


class _CurrentStderrHandler(logging.StreamHandler):
    """Writes to whatever sys.stderr is when a record is emitted, not the one of import time,
    so a redirected or captured stderr (a script's, pytest's) receives the messages."""

    def __init__(self):
        super().__init__(sys.stderr)

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, _value):
        pass


logger = logging.getLogger("colmap_guided")
if not any(isinstance(h, _CurrentStderrHandler) for h in logger.handlers):
    _handler = _CurrentStderrHandler()
    _handler.setFormatter(
        logging.Formatter("[%(asctime)s %(name)s %(levelname)s] %(message)s", "%H:%M:%S")
    )
    logger.addHandler(_handler)
    logger.setLevel(logging.INFO)
    logger.propagate = False


class _LogLines:
    """tqdm's output as log lines: where stderr is no terminal (a log file), a bar's refresh is one
    line, none within LOG_EVERY / 2 of the last (tqdm's monitor and the next update both draw)."""

    def __init__(self) -> None:
        self.last = -math.inf

    def write(self, text: str) -> None:
        text, now = text.strip("\r\n "), time.monotonic()
        if text and now - self.last >= LOG_EVERY / 2:
            self.last = now
            logger.info("%s", text)

    def flush(self) -> None:
        pass


# seconds between a bar's lines in a log; none for a step shorter than that
LOG_EVERY = 60.0
_FORMAT = "{desc}: {n_fmt}/{total_fmt} {unit}s, {elapsed} elapsed, about {remaining} left"


def progress(iterable=None, desc: str = "", unit: str = "it", total=None, show: bool = True):
    """A progress bar with the time left (tqdm): drawn on a terminal, a log line a minute
    elsewhere; none with ``show`` False."""
    from tqdm import tqdm

    if not show:
        return tqdm(iterable, total=total, disable=True)
    # tqdm's monitor refreshes a bar idle for maxinterval: no sooner than the next line is due
    every = {"mininterval": LOG_EVERY, "maxinterval": LOG_EVERY, "delay": LOG_EVERY}
    options = {"file": _LogLines(), **every}
    options = {"dynamic_ncols": True} if sys.stderr.isatty() else {**options, "bar_format": _FORMAT}
    return tqdm(iterable, desc=desc, unit=unit, total=total, leave=False, **options)


def add_verbosity_flags(parser) -> None:
    """--verbose and --quiet, for ``set_verbosity``."""
    group = parser.add_mutually_exclusive_group()
    group.add_argument(
        "--verbose", "-v", action="store_true", help="debug messages and COLMAP's own log"
    )
    group.add_argument(
        "--quiet", "-q", action="store_true", help="only warnings and the final summary"
    )


def set_verbosity(verbose: bool = False, quiet: bool = False) -> None:
    """--verbose shows debug messages and pycolmap's own log; --quiet only warnings."""
    logger.setLevel(logging.DEBUG if verbose else logging.WARNING if quiet else logging.INFO)
    # glog level of COLMAP: 0 = INFO, 1 = WARNING, 2 = ERROR.
    level = 0 if verbose else 2
    os.environ["GLOG_minloglevel"] = str(level)
    try:
        import pycolmap

        pycolmap.logging.minloglevel = level
    except (ImportError, AttributeError):
        pass


@contextlib.contextmanager
def colmap_quiet():
    """COLMAP's own (glog) log silenced during a pycolmap call, unless our logger shows debug
    messages."""
    if logger.isEnabledFor(logging.DEBUG):
        yield
        return
    import pycolmap

    saved = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = max(saved, 2)
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = saved
