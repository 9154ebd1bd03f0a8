"""One thread budget for every library of a process: what a task with ``num_cpus=N`` runs with.

Ray sets ``OMP_NUM_THREADS`` to a task's CPUs (when the user has not set it), which reaches OpenBLAS
and OpenMP, but not OpenCV (its own pthreads pool, sized to the machine's cores unless
``OPENCV_FOR_THREADS_NUM`` is set) nor Open3D's thread limit (``open3d.utility.get_max_threads``: the
machine's cores). So a survey in a ``num_cpus=1`` Ray task ran with one BLAS thread but two OpenCV and
Open3D threads on this 2-core machine, and the plain loop with two of each: neither "one core per task"
nor the same configuration as the loop. :func:`limit_threads` sets all of them, in the environment
(libraries imported later) and in the libraries already imported (the forkserver preloads them).
"""

from __future__ import annotations

import os
import sys

# Read by the libraries when they load: OpenMP (Open3D's OpenMP parts), OpenBLAS, MKL, numexpr, OpenCV.
THREAD_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS",
              "OPENCV_FOR_THREADS_NUM")


def thread_env(threads: int) -> dict[str, str]:
    """The environment variables that size every pool to ``threads`` in a process not started yet."""
    return {name: str(threads) for name in THREAD_ENV}


def limit_threads(threads: int) -> dict[str, int]:
    """Size every thread pool of this process to ``threads`` (>= 1); returns what each library now uses.

    The environment is set for libraries imported later; OpenCV and Open3D, if imported, are set now;
    BLAS and OpenMP through ``threadpoolctl`` when it is installed (otherwise they keep the size they
    read from the environment when they loaded: set it before importing numpy, as Ray does for its workers).
    """
    threads = max(1, int(threads))
    os.environ.update(thread_env(threads))
    used: dict[str, int] = {}
    if "cv2" in sys.modules:
        cv2 = sys.modules["cv2"]
        cv2.setNumThreads(0 if threads == 1 else threads)  # 0: no worker threads, OpenCV runs in the caller's
        used["opencv"] = max(1, int(cv2.getNumThreads()))
    if "open3d" in sys.modules:
        utility = getattr(sys.modules["open3d"], "utility", None)
        if utility is not None and hasattr(utility, "set_max_threads"):
            utility.set_max_threads(threads)
            used["open3d"] = int(utility.get_max_threads())
    try:
        import threadpoolctl
    except ImportError:
        pass
    else:
        threadpoolctl.threadpool_limits(threads)
        for pool in threadpoolctl.threadpool_info():
            used[str(pool.get("internal_api"))] = int(pool.get("num_threads", 0))
    return used


__all__ = ["THREAD_ENV", "limit_threads", "thread_env"]
