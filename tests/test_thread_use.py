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


def test_threads_is_the_runs_budget_of_cores():
    """``threads`` cores: torch gets all but the read-ahead thread's, OpenCV all; 0: every core."""
    import cv2
    import torch

    from slam.app.thread_use import ThreadBudget, available_cores

    cores = available_cores()
    assert ThreadBudget.of(1, read_ahead=True) == ThreadBudget(torch=1, opencv=1)
    assert ThreadBudget.of(cores, read_ahead=False) == ThreadBudget(torch=cores, opencv=cores)
    assert ThreadBudget.of(cores, read_ahead=True) == ThreadBudget(torch=max(1, cores - 1), opencv=cores)
    assert ThreadBudget.of(0, read_ahead=True) == ThreadBudget(torch=max(1, cores - 1), opencv=cores)
    assert ThreadBudget.of(cores + 1, read_ahead=True) == ThreadBudget.of(cores, read_ahead=True)    # capped
    before = torch.get_num_threads(), cv2.getNumThreads()
    with ThreadBudget(torch=1, opencv=1).applied():
        assert (torch.get_num_threads(), cv2.getNumThreads()) == (1, 1)
        assert pool_sizes()["torch"] == 1 and pool_sizes()["opencv"] == 1
    assert (torch.get_num_threads(), cv2.getNumThreads()) == before


def test_a_run_reports_the_pools_of_its_budget(synth_dir, tmp_path):
    import json

    from slam.app.runner import run_from_config
    from slam.config import load_config

    data = synth_dir("rigid", 4)
    run_from_config(data, load_config(None, ["threads=1"]), tmp_path / "run", print_summary=False)
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert metrics["thread_pools"]["torch"] == 1 and metrics["thread_pools"]["opencv"] == 1
    assert metrics["thread_cpu_ms"]["main"] > 0 and metrics["thread_cpu_ms"]["reader"] > 0
