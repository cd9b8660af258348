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


@pytest.fixture
def ctrl_c_reaches_children():
    """Commands started during the test take Ctrl-C as from a terminal, even when the test run itself
    ignores SIGINT (launched with ``nohup ... &``, or as a background job of a script): an ignored signal
    stays ignored across exec, and Python then installs no KeyboardInterrupt handler. A Python handler
    here is reset to the default in every child at exec."""
    import signal

    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)
