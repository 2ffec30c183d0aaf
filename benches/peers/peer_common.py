"""Helpers shared by the OpenCV peer scripts of the benches: installing cv2
on demand and timing a call (median of repeats)."""
import subprocess, sys, time


def ensure_cv2():
    """Installs opencv-contrib-python-headless (and numpy) with pip when cv2 is missing."""
    try:
        import cv2  # noqa: F401
    except ImportError:
        subprocess.check_call([sys.executable, "-m", "pip", "install", "--quiet",
                               "opencv-contrib-python-headless", "numpy"])


def timed(fn, repeats, warmup=False):
    """Runs fn `repeats` times (after one untimed call when `warmup`, for
    allocations and thread pools); returns its last result and the median ms."""
    out = fn() if warmup else None
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        times.append((time.perf_counter() - t) * 1e3)
    times.sort()
    return out, times[len(times) // 2]
