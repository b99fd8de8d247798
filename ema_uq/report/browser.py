"""Open a report in headless Chromium: screenshot of its first screen and the console errors.

A report is only useful if it opens: this drives the browser a reader would use, with the
flags a closed network needs (no background networking, sync or component updates, so the
browser makes no connection of its own) and a throw-away profile. Console messages are
read from Chromium's own log (``--enable-logging=stderr``); no driver library is needed.
That log does not keep the console level (``console.log`` and ``console.error`` both read
INFO), and the reports carry no script of their own, so every console message a page
emits counts as an error.
"""
from __future__ import annotations

import os
import re
import shutil
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path

from ..errors import EmaUqError

#: Where Chromium is looked for, in order (the environment variable wins).
BROWSER_NAMES = ("chromium", "chromium-browser", "google-chrome", "chrome")

# "[pid:tid:date:INFO:CONSOLE:12] "message", source: file:///... (12)" (older builds: CONSOLE(12)])
_CONSOLE = re.compile(r":CONSOLE[:(]\d+")


class BrowserError(EmaUqError, RuntimeError):
    """No usable browser, or the browser failed to render the page."""


@dataclass(frozen=True)
class PageCheck:
    """What the browser saw: the screenshot path and the console errors of the page."""

    screenshot: Path
    console_errors: tuple[str, ...]

    @property
    def ok(self) -> bool:
        return not self.console_errors

    def summary(self) -> str:
        state = "no console errors" if self.ok else f"{len(self.console_errors)} console error(s): " \
            + " | ".join(self.console_errors[:3])
        return f"screenshot {self.screenshot} ({self.screenshot.stat().st_size} bytes), {state}"


def find_browser() -> str | None:
    """Path of a Chromium executable (``EMA_UQ_CHROMIUM`` overrides), or None."""
    explicit = os.environ.get("EMA_UQ_CHROMIUM")
    if explicit:
        return explicit if Path(explicit).exists() else None
    for name in BROWSER_NAMES:
        found = shutil.which(name)
        if found:
            return found
    return None


def check_page(html_path: str | os.PathLike, screenshot: str | os.PathLike, *, width: int = 1280,
               height: int = 900, timeout_s: float = 120.0) -> PageCheck:
    """Render ``html_path`` headless, write a PNG of its first screen, collect console errors."""
    html_path = Path(html_path).resolve()
    if not html_path.is_file():
        raise BrowserError(f"report {html_path} does not exist; build it first (ema-uq report ...)")
    browser = find_browser()
    if browser is None:
        raise BrowserError("no Chromium found; install it (Debian: apt-get install chromium) "
                           "or point EMA_UQ_CHROMIUM at the executable")
    screenshot = Path(screenshot).resolve()
    screenshot.parent.mkdir(parents=True, exist_ok=True)
    if screenshot.exists():
        screenshot.unlink()
    with tempfile.TemporaryDirectory(prefix="ema_uq_browser_") as profile:
        command = [browser, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                   "--disable-background-networking", "--disable-component-update", "--disable-sync",
                   "--disable-extensions", "--hide-scrollbars", f"--user-data-dir={profile}",
                   "--enable-logging=stderr", "--log-level=0", "--virtual-time-budget=5000",
                   f"--window-size={width},{height}", f"--screenshot={screenshot}", html_path.as_uri()]
        try:
            proc = subprocess.run(command, capture_output=True, text=True, timeout=timeout_s)
        except subprocess.TimeoutExpired:
            raise BrowserError(f"Chromium did not finish rendering {html_path.name} in {timeout_s:.0f} s") from None
    if not screenshot.exists() or screenshot.stat().st_size == 0:
        tail = " ".join((proc.stderr or "").split())[-300:]
        raise BrowserError(f"Chromium wrote no screenshot (exit {proc.returncode}): {tail}")
    messages = tuple(line.split("] ", 1)[-1].strip() for line in (proc.stderr or "").splitlines()
                     if _CONSOLE.search(line))
    return PageCheck(screenshot=screenshot, console_errors=messages)
