"""Test-session settings.

One BLAS/OpenMP thread: on a 2-core CI machine, multi-threaded OpenBLAS makes the many
small linear-algebra calls of the tests far slower whenever the other core is busy (seen:
a 27x27 eigh 300x slower). Set before numpy is imported by any test module.
"""

import os

for _name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_name, "1")
