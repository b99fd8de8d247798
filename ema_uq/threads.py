"""How many threads one process of ema_uq may use, when it shares the machine with others.

The simulator's batched kernels run their parameter sets over numba's thread pool, and the
linear algebra runs on a threaded BLAS; both default to one thread per core. That is right for
one process alone on the machine and wrong when several run at once - the self-check's worker
processes, or the jobs a workflow scheduler places side by side - because then every process
starts as many threads as there are cores, and the threads contend for the same cores (measured
on 2 cores, two HT/LS gap diagnoses at once: 20.6 s each with default threads, 15.6 s with one
BLAS thread, 12.6 s with one numba thread as well; one diagnosis alone, one thread: 12.2 s).

* :func:`single_threaded_worker` is the initializer of a worker process of a pool that already
  runs one worker per core. The worker also ends itself when the process that started it is
  gone: a parent stopped by a signal (a cancelled workflow job, a killed script) runs no clean-up,
  and its workers would otherwise go on diagnosing cases whose outcomes nobody will store.
* :func:`follow_scheduler_threads` is called by the command line before anything imports numba:
  a scheduler that gives a job its threads says so in ``OMP_NUM_THREADS`` (Snakemake sets it for
  every job to the rule's ``threads``; SLURM job scripts usually do), and numba is told the same
  share unless ``NUMBA_NUM_THREADS`` is set already.

numba's thread count changes how fast the kernels run, never what they compute: every parameter
set is integrated by one thread alone. A threaded BLAS may split a product differently and so
differ in the last bits; one thread per worker also makes the self-check's numbers independent
of the machine's core count.
"""
from __future__ import annotations

import os
import threading
from typing import MutableMapping

_limits = None      # the BLAS thread limit of this worker, kept alive for the worker's lifetime


def single_threaded_worker() -> None:
    """Initializer of a pool worker: one numba thread and one BLAS thread in this process."""
    global _limits
    import numba
    from threadpoolctl import threadpool_limits

    numba.set_num_threads(1)
    _limits = threadpool_limits(limits=1, user_api="blas")
    threading.Thread(target=_exit_with_parent, name="exit-with-parent", daemon=True).start()


def _exit_with_parent() -> None:
    """Block until the process that started this one ends, then end this one at once (no clean-up:
    a worker holds nothing that must be saved; only the parent writes results)."""
    from multiprocessing import parent_process
    from multiprocessing.connection import wait

    parent = parent_process()
    if parent is None:          # not a multiprocessing child: nothing to follow
        return
    wait([parent.sentinel])
    os._exit(1)


def follow_scheduler_threads(environ: MutableMapping[str, str] | None = None) -> int | None:
    """Give numba the thread share a scheduler set in ``OMP_NUM_THREADS`` (a positive integer),
    unless ``NUMBA_NUM_THREADS`` is set; returns the share applied, None when nothing was set.
    Must run before numba is imported (numba reads the variable once, at import)."""
    environ = os.environ if environ is None else environ
    share = environ.get("OMP_NUM_THREADS", "").strip()
    if "NUMBA_NUM_THREADS" in environ or not share.isdigit() or int(share) < 1:
        return None
    environ["NUMBA_NUM_THREADS"] = str(min(int(share), os.cpu_count() or int(share)))
    return int(environ["NUMBA_NUM_THREADS"])
