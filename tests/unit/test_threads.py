"""The thread share of a process: one numba and one BLAS thread in a self-check worker, and
numba told the share a scheduler gives a job (``OMP_NUM_THREADS``) unless it is told already."""
from __future__ import annotations

import os
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context

from ema_uq.threads import follow_scheduler_threads, single_threaded_worker


def _threads_in_this_process() -> tuple[int, list[int]]:
    import numba
    from threadpoolctl import threadpool_info

    return numba.get_num_threads(), [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"]


def test_a_pool_worker_runs_one_numba_and_one_blas_thread():
    with ProcessPoolExecutor(1, mp_context=get_context("spawn"), initializer=single_threaded_worker) as pool:
        numba_threads, blas_threads = pool.submit(_threads_in_this_process).result()
    assert numba_threads == 1 and blas_threads and set(blas_threads) == {1}


def test_numba_follows_the_schedulers_share_unless_told_otherwise():
    environ = {"OMP_NUM_THREADS": "1"}
    assert follow_scheduler_threads(environ) == 1 and environ["NUMBA_NUM_THREADS"] == "1"
    environ = {"OMP_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "2"}
    assert follow_scheduler_threads(environ) is None and environ["NUMBA_NUM_THREADS"] == "2"
    big = {"OMP_NUM_THREADS": str(10 * (os.cpu_count() or 1))}
    assert follow_scheduler_threads(big) == (os.cpu_count() or 1)            # never more than the cores
    for unset in ({}, {"OMP_NUM_THREADS": ""}, {"OMP_NUM_THREADS": "0"}, {"OMP_NUM_THREADS": "auto"}):
        assert follow_scheduler_threads(unset) is None and "NUMBA_NUM_THREADS" not in unset


def test_the_command_line_gives_numba_the_jobs_share(tmp_path):
    """A workflow job (Snakemake sets OMP_NUM_THREADS to the rule's threads) runs numba on that share."""
    import subprocess
    import sys

    script = ("import sys\n"
              "from ema_uq.cli import main\n"
              f"code = main(['simulate', '--concept', 'htls', '--experiment', 'deploy-retract', '--out', {str(tmp_path / 'run.csv')!r}])\n"
              "import numba\n"                 # after the command: it must not have needed us to import it
              "print('numba threads', numba.get_num_threads()); sys.exit(code)\n")
    environ = {k: v for k, v in os.environ.items() if k != "NUMBA_NUM_THREADS"}
    environ["OMP_NUM_THREADS"] = "1"
    done = subprocess.run([sys.executable, "-c", script], env=environ, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    assert "numba threads 1" in done.stdout


def test_the_jobs_share_is_set_before_a_study_brings_numba_in(tmp_path):
    """Reading a study imports the models and so numba, which reads its thread count once: the
    share must be set before (told after, a one-thread workflow job launched a thread per core and
    every self-check case then failed at its first compilation)."""
    import subprocess
    import sys

    script = ("import sys\n"
              "import ema_uq.threads as threads\n"
              "real, seen = threads.follow_scheduler_threads, []\n"
              "def spy(*args, **kwargs):\n"
              "    seen.append('numba' in sys.modules)\n"
              "    return real(*args, **kwargs)\n"
              "threads.follow_scheduler_threads = spy\n"
              "from ema_uq.cli import main\n"
              f"code = main(['simulate', '--concept', 'htls', '--study', 'studies/htls.yaml', '--role', 'estimation', '--out', {str(tmp_path / 'run.csv')!r}])\n"
              "import numba\n"
              "print('numba imported before the share:', seen, 'threads', numba.get_num_threads()); sys.exit(code)\n")
    environ = {k: v for k, v in os.environ.items() if k != "NUMBA_NUM_THREADS"}
    environ["OMP_NUM_THREADS"] = "1"
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    done = subprocess.run([sys.executable, "-c", script], env=environ, capture_output=True, text=True, timeout=600,
                          cwd=root)
    assert done.returncode == 0, done.stderr
    assert "numba imported before the share: [False] threads 1" in done.stdout, done.stdout


_ORPHANED_POOL = """
import os, sys, time
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from ema_uq.threads import single_threaded_worker

if __name__ == "__main__":
    pool = ProcessPoolExecutor(1, mp_context=get_context("spawn"), initializer=single_threaded_worker)
    print(pool.submit(os.getpid).result(), flush=True)
    pool.submit(time.sleep, 300)
    time.sleep(300)
"""


def _running(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().rsplit(")", 1)[1].split()[0] not in ("Z", "X")
    except FileNotFoundError:
        return False


def test_a_pool_worker_ends_when_its_parent_is_killed(tmp_path):
    """A parent stopped by SIGTERM runs no clean-up; its busy worker must still end (not diagnose on)."""
    import signal
    import subprocess
    import sys
    import time

    import pytest

    if not os.path.isdir("/proc/self"):
        pytest.skip("needs /proc to see whether the worker still runs")
    script = tmp_path / "orphaned_pool.py"
    script.write_text(_ORPHANED_POOL)
    parent = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True,
                              env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})
    worker = None
    try:
        worker = int(parent.stdout.readline())
        assert _running(worker)
        parent.send_signal(signal.SIGTERM)
        parent.wait(timeout=30)
        deadline = time.monotonic() + 20
        while _running(worker) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not _running(worker), "the worker went on after its parent was killed"
    finally:
        parent.kill()
        if worker is not None and _running(worker):
            os.kill(worker, signal.SIGKILL)
