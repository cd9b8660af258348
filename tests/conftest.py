"""Test-session settings.

One BLAS/OpenMP thread: on a 2-core CI machine, multi-threaded OpenBLAS makes the many
small linear-algebra calls of the tests far slower whenever the other core is busy (seen:
a 27x27 eigh 300x slower). Set before numpy is imported by any test module.
"""

import os

import pytest

for _name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_name, "1")


@pytest.fixture(autouse=True)
def _one_torch_thread():
    """One torch thread in every test, restored afterwards: tiny tensors gain nothing from a second
    thread, and OpenMP threads stall at barriers when another process holds a core."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
