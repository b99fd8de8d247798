"""The headless-Chromium check must see a broken page as broken."""
from __future__ import annotations

import pytest

from ema_uq.cli import main
from ema_uq.report.browser import BrowserError, check_page, find_browser

needs_browser = pytest.mark.skipif(find_browser() is None, reason="no Chromium (Debian: apt-get install chromium)")


@needs_browser
def test_console_errors_of_a_broken_page_are_reported(tmp_path):
    page = tmp_path / "broken.html"
    page.write_text("<html><body><h1>x</h1><script>console.error('boom'); missingFunction();</script></body></html>")
    result = check_page(page, tmp_path / "broken.png")
    assert not result.ok
    assert any("boom" in m for m in result.console_errors)
    assert any("missingFunction" in m for m in result.console_errors)


@needs_browser
def test_clean_page_gives_screenshot_and_no_errors(tmp_path, capsys):
    page = tmp_path / "clean.html"
    page.write_text("<html><body><h1>clean</h1><p>text</p></body></html>")
    assert main(["screenshot", str(page), "--out", str(tmp_path / "clean.png")]) == 0
    assert (tmp_path / "clean.png").read_bytes()[:4] == b"\x89PNG"
    assert "no console errors" in capsys.readouterr().out


def test_missing_report_is_a_one_line_error(tmp_path, capsys):
    assert main(["screenshot", str(tmp_path / "absent.html"), "--out", str(tmp_path / "x.png")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "does not exist" in err


def test_no_browser_is_a_clear_error(tmp_path, monkeypatch):
    monkeypatch.setenv("EMA_UQ_CHROMIUM", str(tmp_path / "no-such-browser"))
    page = tmp_path / "p.html"
    page.write_text("<html></html>")
    with pytest.raises(BrowserError, match="no Chromium found"):
        check_page(page, tmp_path / "p.png")
