"""The episode pool both robot benchmarks share: every task's record from one runner per process."""

from __future__ import annotations

import multiprocessing as mp
import os
from collections.abc import Sequence
from typing import Any

from tqdm.auto import tqdm

__all__ = ["run_tasks"]

_RUNNER: Any = None


def _worker_init(runner_type: type, config: Any, device: str, owner_pid: int) -> None:
    global _RUNNER  # one runner per worker process, kept for all its tasks
    import signal

    import torch

    from don_gym.processes import end_with_parent

    end_with_parent(owner_pid)  # a benchmark killed with kill -9 takes its workers along

    # Ctrl-C reaches every process of the terminal's process group; the parent stops the pool, and a
    # worker that took it too would print a traceback of its own.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # The workers already fill the cores; more threads per worker only contend.
    torch.set_num_threads(1)
    _RUNNER = runner_type(config, device)


def _worker_run(indexed: tuple[int, Any]) -> tuple[int, dict[str, Any]]:
    assert _RUNNER is not None
    index, task = indexed
    return index, _RUNNER.run(task)


def run_tasks(
    runner_type: type,
    config: Any,
    device: str,
    tasks: Sequence[Any],
    workers: int,
    progress: bool,
    unit: str,
    desc: str,
) -> tuple[list[dict[str, Any]], int]:
    """Every task's record, in task order, and the number of processes used: ``runner_type(config, device)``
    (a runner with ``run(task) -> dict`` and ``close()``) in this process for ``workers`` 1, else one runner
    in each of ``workers`` spawned processes (at most one per task). The grasp and bin benchmarks share it."""
    records: list[dict[str, Any] | None] = [None] * len(tasks)
    workers = max(1, min(workers, len(tasks)))
    with tqdm(total=len(tasks), unit=unit, desc=desc, disable=not progress) as bar:
        if workers == 1:
            runner = runner_type(config, device)
            try:
                for index, task in enumerate(tasks):
                    records[index] = runner.run(task)
                    bar.update(1)
            finally:
                runner.close()
        else:
            from don_gym.data.build import single_threaded_children

            context = mp.get_context("spawn")
            initargs = (runner_type, config, device, os.getpid())
            with (
                single_threaded_children(),
                context.Pool(workers, initializer=_worker_init, initargs=initargs) as pool,
            ):
                for index, record in pool.imap_unordered(_worker_run, list(enumerate(tasks))):
                    records[index] = record
                    bar.update(1)
                pool.close()  # clean shutdown: leaving the with-block terminates (leaked-semaphore warning)
                pool.join()
    return [r for r in records if r is not None], workers
