"""The run's thread accounting (``slam.app.thread_use``): CPU time per thread and the pools' sizes."""
import subprocess
import sys
import time

from slam.app.thread_use import ThreadClock, pool_sizes


def _spin(seconds: float) -> None:
    end = time.thread_time() + seconds
    while time.thread_time() < end:
        pass


def test_thread_clock_counts_each_threads_cpu_not_its_waiting():
    clock = ThreadClock()
    clock.start()
    for _ in range(3):
        with clock.measure("main"):
            _spin(0.02)
            time.sleep(0.05)            # waiting is not CPU time
    clock.stop()
    per_frame = clock.summary(3)
    assert 15.0 <= per_frame["main"] <= 45.0
    assert per_frame["process"] >= per_frame["main"] * 0.9


def test_pool_sizes_reports_numba_without_launching_its_pool():
    """Asking numba for its thread count launches an OpenMP team that spins beside the tracking
    (a quarter of the frame rate on two cores): the report must read the configuration instead."""
    code = ("import numba, numba.np.ufunc.parallel as par\n"
            "from slam.app.thread_use import pool_sizes\n"
            "sizes = pool_sizes()\n"
            "assert sizes['numba'] == numba.config.NUMBA_NUM_THREADS, sizes\n"
            "assert not par._is_initialized, 'numba pool launched'\n"
            "print('ok')\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "ok"


def test_pool_sizes_reads_torch_and_opencv():
    import cv2
    import torch
    sizes = pool_sizes()
    assert sizes["torch"] == torch.get_num_threads()
    assert sizes["opencv"] == cv2.getNumThreads()
