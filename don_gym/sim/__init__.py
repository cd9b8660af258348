"""PyBullet simulation. The env (:mod:`~don_gym.sim.env`) joins robot (``robot``), task (``task``,
with ``part`` and the scripted grasp of ``script``), wrist camera (``camera``) and depth sensor
(``sensor``) on its own PyBullet client (``bullet``); ``recorder`` records dataset scenes. The bin-picking
env (``bin_env``) swaps the task for a bin of several part instances (``bin_task``).
Nothing holds global PyBullet state.
"""

from __future__ import annotations

import os
import sys


def _import_pybullet_quietly() -> None:
    """Import PyBullet with file descriptor 2 sent to /dev/null: its C code prints its build time to stderr
    at the first import, into every command's and benchmark worker's output (before a one-line error, too).
    Every module of this package imports PyBullet after this has run, so the banner never shows."""
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):  # no real fd 2 (e.g. some notebook front-ends)
        import pybullet  # noqa: F401

        return
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 2)
        import pybullet  # noqa: F401
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(devnull)


_import_pybullet_quietly()
