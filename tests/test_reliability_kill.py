"""No process outlives the command that started it: ``kill -9`` of a build on workers (one part and bins) or of a
training on data-loading workers leaves no worker, resource tracker or fork server alive, and the lock of the
directory it wrote is free again (docs/reliability.md, "Processes").

Each command is started with ``setsid``, so its processes are the members of one session; a few seconds after
the kill, none is left.
"""

from __future__ import annotations

import fcntl
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from don_gym.data.build import DatasetConfig, build_dataset
from don_gym.data.dataset import DatasetLock
from don_gym.io import DirectoryLock
from don_gym.processes import process_alive

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="sessions and /proc are Linux's")

#: Seconds the processes of a killed command may take to end.
GRACE_S = 8.0


def _session_members(session_id: int) -> list[int]:
    """Pids of the live (not zombie) processes of session ``session_id``."""
    members = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fields = (entry / "stat").read_bytes().rsplit(b")", 1)[1].split()
        except (OSError, IndexError):
            continue
        state, session = fields[0], int(fields[3])
        if session == session_id and state != b"Z":
            members.append(int(entry.name))
    return members


def _start(command: list[str], log: Path) -> subprocess.Popen:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    with open(log, "wb") as out:
        return subprocess.Popen(["setsid", *command], stdout=out, stderr=subprocess.STDOUT, env=env)


def _kill_when(process: subprocess.Popen, ready, what: str, log: Path, timeout_s: float = 240) -> int:
    """Wait for ``ready()`` (the workers at work), kill -9 the command's first process, return its session."""
    deadline = time.monotonic() + timeout_s
    while not ready():
        assert process.poll() is None, f"the command ended before {what}:\n{log.read_text()}"
        assert time.monotonic() < deadline, f"never saw {what}:\n{log.read_text()}"
        time.sleep(0.05)
    session = os.getsid(process.pid)
    assert session == process.pid  # setsid runs the command as the session's leader
    os.kill(process.pid, signal.SIGKILL)
    process.wait(timeout=30)
    return session


def _assert_session_ends(session: int) -> None:
    deadline = time.monotonic() + GRACE_S
    while _session_members(session) and time.monotonic() < deadline:
        time.sleep(0.1)
    left = _session_members(session)
    for pid in left:  # never leave them to the next test
        os.kill(pid, signal.SIGKILL)
    assert not left, f"processes {left} outlived the killed command by {GRACE_S} s"


def _worker_count(session: int) -> int:
    return len(_session_members(session)) - 1


@pytest.mark.parametrize("scene", ["single", "bin"])
def test_a_killed_build_on_workers_leaves_no_process_and_frees_the_lock(scene: str, tmp_path: Path) -> None:
    out = tmp_path / "KW"
    kind = ["--scene", "bin", "--parts", "toolcap:1,shaft:1"] if scene == "bin" else []
    command = [
        sys.executable, "-m", "don_gym.cli", "build-dataset", *kind, "--scenes", "40", "--frames", "2",
        "--size", "32x24", "--no-fusion", "--workers", "2", "--out", str(out),
    ]  # fmt: skip
    log = tmp_path / "log.txt"
    build = _start(command, log)

    def workers_writing() -> bool:
        # Both workers started (they hold the lock) and writing scenes.
        if build.poll() is not None or _worker_count(build.pid) < 2:
            return False
        return bool(list(out.glob("scenes/.scene_*.partial-*")) or list(out.glob("scenes/scene_*")))

    session = _kill_when(build, workers_writing, "two workers writing a scene", log)
    _assert_session_ends(session)
    # The lock went with them: --overwrite may replace the dataset at once.
    lock = DatasetLock(out)
    lock.hold_session(exclusive=True)
    lock.close()


def test_a_killed_training_leaves_no_data_loading_worker(tmp_path: Path) -> None:
    data = tmp_path / "data"
    build_dataset(
        DatasetConfig(scenes=1, frames_per_scene=2, image_size=(64, 48), fuse_depth=False, seed=3), data, progress=False
    )
    run = tmp_path / "run"
    command = [
        sys.executable, "-m", "don_gym.cli", "train", "--method", "supervised", "--data", str(data),
        "--out", str(run), "--steps", "100000", "--checkpoint-every", "100000", "--crop", "none",
        "--batch-size", "2", "--workers", "2", "--threads", "1",
    ]  # fmt: skip
    log = tmp_path / "log.txt"
    trainer = _start(command, log)

    def loading() -> bool:
        # The fork server and both workers besides the trainer, and the run under way (its lock taken).
        return trainer.poll() is None and _worker_count(trainer.pid) >= 3 and (run / "config.json").exists()

    session = _kill_when(trainer, loading, "the data-loading workers", log)
    _assert_session_ends(session)
    lock = DirectoryLock(run)
    assert lock.lock(0, fcntl.LOCK_EX, blocking=False)
    lock.close()


class SleepyRunner:
    """A benchmark's runner (``runner_type(config, device)``) whose every task marks its start in folder ``config``
    and then takes ten minutes."""

    def __init__(self, config: str, device: str) -> None:
        self.folder = Path(config)

    def run(self, task: int) -> dict:
        (self.folder / f"{os.getpid()}.started").touch()
        time.sleep(600)
        return {}

    def close(self) -> None:
        pass


def test_a_killed_benchmark_leaves_no_episode_worker(tmp_path: Path) -> None:
    """The episode pool of ``benchmark grasp`` and ``benchmark bin`` (don_gym.evaluation.episodes)."""
    script = (
        "import sys; sys.path.insert(0, sys.argv[1]); from test_reliability_kill import SleepyRunner; "
        "from don_gym.evaluation.episodes import run_tasks; "
        "run_tasks(SleepyRunner, sys.argv[2], 'cpu', list(range(8)), 2, False, 'episode', 'benchmark')"
    )
    log = tmp_path / "log.txt"
    benchmark = _start([sys.executable, "-c", script, str(Path(__file__).parent), str(tmp_path)], log)

    def running() -> bool:
        return benchmark.poll() is None and len(list(tmp_path.glob("*.started"))) >= 2

    _assert_session_ends(_kill_when(benchmark, running, "two episode workers at work", log))


def _processes_naming(text: str) -> list[int]:
    """Pids of the live processes whose command line holds ``text``."""
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit() and int(entry.name) != os.getpid():
            try:
                if text.encode() in (entry / "cmdline").read_bytes():
                    found.append(int(entry.name))
            except OSError:
                continue
    return [pid for pid in found if process_alive(pid)]


def test_a_killed_torchrun_leaves_no_training_process(tmp_path: Path) -> None:
    """torchrun starts each process in a session of its own: they watch torchrun itself."""
    data = tmp_path / "data"
    build_dataset(
        DatasetConfig(scenes=1, frames_per_scene=2, image_size=(64, 48), fuse_depth=False, seed=3), data, progress=False
    )
    run = tmp_path / "torchrun-run"
    command = [
        sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2",
        "-m", "don_gym.cli", "train", "--method", "supervised", "--data", str(data), "--out", str(run),
        "--steps", "100000", "--checkpoint-every", "100000", "--crop", "none", "--batch-size", "2", "--threads", "1",
    ]  # fmt: skip
    log = tmp_path / "log.txt"
    launcher = _start(command, log)
    ranks: list[int] = []

    def training() -> bool:
        ranks[:] = [p for p in _processes_naming(str(run)) if p != launcher.pid]
        return launcher.poll() is None and len(ranks) >= 2 and (run / "config.json").exists()

    session = _kill_when(launcher, training, "two training processes", log)
    _assert_session_ends(session)
    deadline = time.monotonic() + GRACE_S
    while any(process_alive(p) for p in ranks) and time.monotonic() < deadline:
        time.sleep(0.1)
    left = [p for p in ranks if process_alive(p)]
    for pid in left:
        os.kill(pid, signal.SIGKILL)
    assert not left, f"training processes {left} outlived torchrun by {GRACE_S} s"


def test_end_with_parent_ends_a_process_whose_owner_is_not_its_parent(tmp_path: Path) -> None:
    """The watch on the owner's pid, beyond the parent-death signal: a worker whose parent is a fork server (here
    a middle process that lives on) ends when its owner is killed."""
    watcher = (
        "import sys, time; from don_gym.processes import end_with_parent; end_with_parent(int(sys.argv[1])); "
        "print('watching', flush=True); time.sleep(600)"
    )
    middle = (
        "import subprocess, sys, time\n"
        "w = subprocess.Popen([sys.executable, '-c', sys.argv[1], sys.argv[2]], stdout=subprocess.PIPE, text=True)\n"
        "print(w.pid, w.stdout.readline().strip(), flush=True)\n"
        "time.sleep(600)\n"
    )
    owner = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(600)"])
    # The middle process has its own session: the owner's death does not reach it.
    server = subprocess.Popen(
        [sys.executable, "-c", middle, watcher, str(owner.pid)], stdout=subprocess.PIPE, text=True,
        start_new_session=True,
    )  # fmt: skip
    try:
        pid, state = server.stdout.readline().split()
        worker = int(pid)
        assert state == "watching"
        time.sleep(0.5)
        assert process_alive(worker)  # alive while its owner is
        owner.kill()
        owner.wait()
        deadline = time.monotonic() + GRACE_S
        while process_alive(worker) and time.monotonic() < deadline:
            time.sleep(0.05)
        alive = process_alive(worker)
        if alive:
            os.kill(worker, signal.SIGKILL)
        assert not alive, "the watched process outlived its owner"
        assert server.poll() is None  # its parent lives on: the watch, not the parent-death signal, ended it
    finally:
        owner.kill()
        server.kill()
        owner.wait()
        server.wait()


def test_end_with_parent_of_a_dead_owner_ends_at_once() -> None:
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    probe = subprocess.run(
        [sys.executable, "-c", f"from don_gym.processes import end_with_parent; end_with_parent({child.pid}); "
         "import time; time.sleep(30); print('survived')"],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert probe.returncode == -signal.SIGKILL and "survived" not in probe.stdout
