"""noiselab: a live emulator and model checker for noisy sensors and actuators on dynamic systems."""

import os

BLAS_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def one_blas_thread() -> None:
    """One BLAS thread unless the environment sets another count; call it before numpy is
    imported (BLAS reads the count when numpy loads), in every entry point that runs a diagnosis.

    noiselab's matrices are small (a plant's states and its noises'), the diagnosis runs two
    workers of its own, and OpenBLAS's threads on top spin for the same cores. On 10^6 samples of
    the seed (2 cores) `diagnose` took 26.1-27.9 s wall and 40-43 s CPU with one thread, 30.3-34.9 s
    and 52-59 s with OpenBLAS's default; in the test suite, two workers with the default threads
    slowed each other's tests 2-2.7x. A BLAS worker also keeps the diagnosis from forking its second
    process (:func:`noiselab.parallel.can_fork`). Subprocesses inherit the setting."""
    for var in BLAS_VARS:
        os.environ.setdefault(var, "1")
