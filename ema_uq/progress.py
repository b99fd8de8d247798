"""Progress of the long stages: a tqdm bar in a terminal, plain lines in a log.

A workflow job writes its stderr to a log file, where a bar's carriage returns would pile up
into one unreadable line; there the same counter prints one line at most every
``LOG_EVERY_S`` seconds (and at the end), so a log shows a stage that runs for minutes moving.
Nothing here touches the numerics: the loops call ``update`` and nothing else.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import TextIO

#: seconds between two progress lines in a log (the brief for every stage over ~10 s)
LOG_EVERY_S = 10.0


class Progress:
    """A counter of ``total`` steps of one stage named ``desc``.

    ``update(n)`` advances it; ``close()`` (or leaving the ``with`` block) ends the bar or
    prints the final line. With ``enabled=False`` it does nothing at all (``--quiet``).
    """

    def __init__(self, total: int, desc: str, unit: str = "step", *, stream: TextIO | None = None,
                 enabled: bool = True):
        self.total, self.desc, self.unit = int(total), desc, unit
        self.stream = sys.stderr if stream is None else stream
        self.enabled = enabled
        self.n = 0
        self._t0 = self._last = time.perf_counter()
        self._bar = None
        if enabled and _is_terminal(self.stream):
            from tqdm import tqdm

            self._bar = tqdm(total=self.total, desc=desc, unit=unit, file=self.stream, dynamic_ncols=True)

    def update(self, n: int = 1, note: str = "") -> None:
        if not self.enabled:
            return
        self.n += n
        if self._bar is not None:
            if note:
                self._bar.set_postfix_str(note, refresh=False)
            self._bar.update(n)
            return
        now = time.perf_counter()
        if now - self._last >= LOG_EVERY_S:
            self._last = now
            self._line(note, now)

    def close(self, failed: bool = False) -> None:
        """End the bar, or print the final line; a stage that ``failed`` ends silently, so its
        error stays the one line on stderr."""
        if not self.enabled:
            return
        if self._bar is not None:
            self._bar.close()
        elif not failed:
            self._line("done", time.perf_counter())
        self.enabled = False

    def _line(self, note: str, now: float) -> None:
        elapsed = now - self._t0
        print(f"{self.desc}: {self.n}/{self.total} {self.unit}s, {elapsed:.0f} s" + (f"; {note}" if note else ""),
              file=self.stream, flush=True)

    def __enter__(self) -> "Progress":
        return self

    def __exit__(self, exc_type, *exc) -> None:
        self.close(failed=exc_type is not None)


def _is_terminal(stream: TextIO) -> bool:
    try:
        return stream.isatty()
    except (AttributeError, ValueError):
        return False


def compiled_kernels_cached(module_file: str | Path) -> bool:
    """Whether numba's on-disk cache holds kernels of ``module_file`` at least as new as its
    source. Numba keeps no public query for this; its cache index files sit in the module's
    ``__pycache__`` as ``<module>.<function>-<line>.py<XY>.nbi`` (or under NUMBA_CACHE_DIR, which
    this does not search: there the answer is a harmless False and the notice shows). An index
    older than the source does not count: numba keys it by the function's line, so an edit that
    moves a kernel leaves its old index behind for good."""
    source = Path(module_file)
    tag = f"py{sys.version_info.major}{sys.version_info.minor}"
    cache = source.parent / "__pycache__"
    indexes = list(cache.glob(f"{source.stem}.*.{tag}.nbi")) if cache.is_dir() else []
    return any(p.stat().st_mtime >= source.stat().st_mtime for p in indexes)


def first_compile_notice(modules: tuple[str, ...] = ("simulate.integrators",), stream: TextIO | None = None) -> bool:
    """Say, in one line, that the simulator's kernels are compiled now (about a minute, once per
    installation and source change) when numba has no cached copy of them; True when said.
    ``modules``: the package's modules (dotted, below ``ema_uq``) whose kernels the verb runs.
    The model and effect equations are compiled into these kernels, so their cache is the one
    that counts; one kernel per method serves every effect combination."""
    import importlib

    # the package's namespace holds a function named simulate, so the modules are imported by path
    modules = [importlib.import_module(f"ema_uq.{name}") for name in modules]
    missing = [m for m in modules if not compiled_kernels_cached(m.__file__)]
    if not missing:
        return False
    names = ", ".join(Path(m.__file__).stem for m in missing)
    print(f"ema-uq: compiling the numba kernels of {names} on first use (about a minute; cached afterwards)",
          file=sys.stderr if stream is None else stream, flush=True)
    return True
