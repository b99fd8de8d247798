"""Progress of the long stages: lines in a log, nothing with --quiet, the first-compile notice."""
import io

from ema_uq import progress as pg


def test_log_mode_prints_a_line_per_interval_and_a_final_one(monkeypatch):
    clock = iter([0.0, 5.0, 11.0, 12.0, 13.0])
    monkeypatch.setattr(pg.time, "perf_counter", lambda: next(clock))
    out = io.StringIO()                          # not a terminal: lines, no bar
    with pg.Progress(4, "stage", "run", stream=out) as bar:
        bar.update()                             # 5 s after the start: too soon for a line
        bar.update(2, "note")                    # 11 s: a line
        bar.update()
    lines = out.getvalue().splitlines()
    assert lines == ["stage: 3/4 runs, 11 s; note", "stage: 4/4 runs, 13 s; done"]


def test_disabled_progress_prints_nothing():
    out = io.StringIO()
    with pg.Progress(3, "stage", stream=out, enabled=False) as bar:
        bar.update(3)
    assert out.getvalue() == ""


def test_compile_notice_follows_the_cache_of_the_source(tmp_path):
    source = tmp_path / "kernels.py"
    source.write_text("x = 1\n")
    assert not pg.compiled_kernels_cached(source)
    cache = tmp_path / "__pycache__"
    cache.mkdir()
    import sys

    index = cache / f"kernels.f-1.py{sys.version_info.major}{sys.version_info.minor}.nbi"
    index.write_bytes(b"")
    assert pg.compiled_kernels_cached(source)
    import os

    os.utime(source, (index.stat().st_mtime + 10,) * 2)     # source edited after compilation
    assert not pg.compiled_kernels_cached(source)


def test_compile_notice_ignores_the_stale_index_of_a_moved_kernel(tmp_path):
    import os
    import sys

    source = tmp_path / "kernels.py"
    source.write_text("x = 1\n")
    cache = tmp_path / "__pycache__"
    cache.mkdir()
    tag = f"py{sys.version_info.major}{sys.version_info.minor}"
    stale, fresh = cache / f"kernels.f-1.{tag}.nbi", cache / f"kernels.f-9.{tag}.nbi"
    stale.write_bytes(b"")
    os.utime(source, (stale.stat().st_mtime + 10,) * 2)     # the kernel moved to line 9 ...
    assert not pg.compiled_kernels_cached(source)
    fresh.write_bytes(b"")
    os.utime(fresh, (stale.stat().st_mtime + 20,) * 2)      # ... and was compiled again there
    assert pg.compiled_kernels_cached(source)


def test_a_failed_stage_ends_without_a_final_line():
    out = io.StringIO()
    try:
        with pg.Progress(3, "stage", stream=out):
            raise ValueError("bad input")
    except ValueError:
        pass
    assert out.getvalue() == ""
