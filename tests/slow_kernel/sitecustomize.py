"""A deliberately slowed kernel for the bench guard's test (tests/structure/test_bench_guard.py).

On ``PYTHONPATH`` with ``CROSSFIELD_SLOW_KERNEL=1``, every Python process started
(the bench scripts ``bench/run.py`` runs) wraps
``EpipolarTriangulator.triangulate`` so that each call takes three times as long
(it busy-waits twice its own time). Test code only: nothing in the package reads
the variable.
"""

import os

if os.environ.get("CROSSFIELD_SLOW_KERNEL") == "1":
    import time

    from crossfield.plugins import triangulate_epipolar

    _original = triangulate_epipolar.EpipolarTriangulator.triangulate

    def _slowed(self, *args, **kwargs):
        start = time.perf_counter()
        result = _original(self, *args, **kwargs)
        until = start + 3 * (time.perf_counter() - start)
        while time.perf_counter() < until:
            pass
        return result

    triangulate_epipolar.EpipolarTriangulator.triangulate = _slowed
