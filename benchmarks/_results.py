"""Shared helpers for benchmark scripts: record a result section in benchmarks/RESULTS.md, and
replace a generated block of another document (README.md, docs/) with figures a benchmark computed, and
measure how many cores other processes kept busy while a benchmark timed something.

Each benchmark owns its sections and blocks, delimited by HTML comments, which it replaces on every run.
A section header records the exact command, the machine, the date and the commit, so every
figure in RESULTS.md can be traced to the run and the code that produced it.
"""

from __future__ import annotations

import datetime as _dt
import os
import platform
import re
import shlex
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path

RESULTS_PATH = Path(__file__).resolve().parent / "RESULTS.md"
REPO_ROOT = RESULTS_PATH.parent.parent
#: Where the benchmarks write their figures (RESULTS.md names them relative to REPO_ROOT).
FIGURES = RESULTS_PATH.parent / "figures"
#: Paths the benchmarks themselves write: changes there do not make a measurement's code uncommitted.
BENCHMARK_OUTPUTS = ("benchmarks/RESULTS.md", "benchmarks/figures/")


def machine_description() -> str:
    """One line: CPU model, cores, GPU (if torch sees one), OS and Python."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    gpu = "no GPU"
    try:
        import torch

        if torch.cuda.is_available():
            gpu = f"GPU {torch.cuda.get_device_name(0)}"
    except Exception:
        pass
    return f"{cores} cores ({cpu}), {gpu}, {platform.system()} {platform.release()}, Python {platform.python_version()}"


def command_line() -> str:
    script = Path(sys.argv[0])
    try:
        script = script.resolve().relative_to(Path.cwd())
    except ValueError:
        pass
    return " ".join(["python", shlex.quote(str(script)), *map(shlex.quote, sys.argv[1:])])


def _git(*args: str) -> str:
    return subprocess.run(["git", *args], cwd=REPO_ROOT, capture_output=True, text=True, check=True, timeout=30).stdout


#: The code state :func:`freeze_commit_description` saw at a run's start; None: look each time.
_frozen_commit: str | None = None


def freeze_commit_description() -> str:
    """Look at the code state now and let :func:`commit_description` answer that for the rest of the run: a
    benchmark that writes generated blocks into README.md or docs/ would otherwise find its own output
    among the uncommitted changes of the sections it records after them."""
    global _frozen_commit
    _frozen_commit = None
    _frozen_commit = commit_description()
    return _frozen_commit


def commit_description() -> str:
    """``<short hash>``, plus `` + uncommitted changes`` when tracked files other than the benchmarks'
    own outputs differ from it; ``unknown`` without git or outside a repository. After
    :func:`freeze_commit_description`, what it saw."""
    if _frozen_commit is not None:
        return _frozen_commit
    try:
        commit = _git("rev-parse", "--short", "HEAD").strip()
        status = _git("status", "--porcelain", "-z", "--untracked-files=no")
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    # -z entries: "XY path"; a rename or copy (X or Y is R or C) is followed by its source path.
    entries = iter(status.split("\0"))
    paths = []
    for entry in entries:
        if len(entry) > 3:
            paths.append(entry[3:])
            if "R" in entry[:2] or "C" in entry[:2]:
                paths.append(next(entries, ""))
    changed = [p for p in paths if p and not (p == BENCHMARK_OUTPUTS[0] or p.startswith(BENCHMARK_OUTPUTS[1]))]
    return f"{commit} + uncommitted changes" if changed else (commit or "unknown")


def utc_now() -> str:
    """The date and time a measurement is recorded with, e.g. ``2026-11-29 22:09 UTC``."""
    return _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")


def _machine_busy_seconds() -> float | None:
    """CPU seconds all processes have spent busy since boot (Linux /proc/stat), or None elsewhere."""
    try:
        with open("/proc/stat") as f:
            ticks = [int(v) for v in f.readline().split()[1:9]]
    except (OSError, ValueError):
        return None
    idle = ticks[3] + ticks[4]  # idle + iowait
    return (sum(ticks) - idle) / os.sysconf("SC_CLK_TCK")


class OtherProcessLoad:
    """Average number of CPU cores that *other* processes kept busy while the block ran.

    Timings on a shared machine are only meaningful when this is near 0; it is reported
    next to the figures so a reader can tell.
    """

    def __enter__(self) -> OtherProcessLoad:
        self.wall = time.perf_counter()
        self.busy = _machine_busy_seconds()
        self.own = sum(os.times()[:2])
        self.cores: float | None = None
        return self

    def __exit__(self, *exc: object) -> None:
        busy = _machine_busy_seconds()
        if busy is not None and self.busy is not None:
            own = sum(os.times()[:2]) - self.own
            self.cores = max(0.0, (busy - self.busy - own) / (time.perf_counter() - self.wall))

    def describe(self) -> str:
        return "unknown" if self.cores is None else f"{self.cores:.2f}"


def _section_pattern(name: str) -> re.Pattern[str]:
    """RESULTS.md's section ``name``, from its begin comment to its end comment and the newline after."""
    return re.compile(rf"<!-- begin {re.escape(name)} -->(.*?)<!-- end {re.escape(name)} -->\n?", re.S)


def read_section(name: str, path: Path = RESULTS_PATH) -> str | None:
    """The text of the section ``name`` of RESULTS.md between its begin and end comments; None when absent."""
    match = _section_pattern(name).search(path.read_text()) if path.exists() else None
    return None if match is None else match.group(1)


def section_origin(text: str) -> dict[str, str]:
    """The ``Command``, ``Date`` and ``Commit`` lines of a section's text (:func:`read_section`), each
    ``"not recorded"`` where the section has none."""
    fields = {key: re.search(rf"^- {key}: (.+)$", text, re.M) for key in ("Command", "Date", "Commit")}
    return {key: match.group(1).strip() if match else "not recorded" for key, match in fields.items()}


#: The renderers whose RGB the test-split benchmarks measure on: TinyRenderer's (every shipped network was trained on
#: it; the sections, blocks and figures keep the names they always had) and the physically based one
#: (:mod:`don_gym.sim.pbr`: the same scenes, depth, masks and targets, path-traced RGB; sections ``NAME-pbr``).
MEASURED_RENDERERS = ("tiny", "pbr")
_RENDERER_TITLES = {"tiny": "", "pbr": ", physically based rendering"}


def renderer_suffix(renderer: str, separator: str = "-") -> str:
    """What the name of a section, block or file adds for ``renderer``: nothing for TinyRenderer, ``-pbr`` (with
    ``separator`` "_": ``_pbr``) for the physically based renderer, so that its runs never overwrite TinyRenderer's."""
    if renderer not in MEASURED_RENDERERS:
        raise ValueError(f"renderer {renderer!r}: expected one of {list(MEASURED_RENDERERS)}")
    return "" if renderer == "tiny" else f"{separator}{renderer}"


def rendering_text(renderer: str) -> str:
    """What a data line adds for ``renderer`` after the sensor (nothing for TinyRenderer)."""
    renderer_suffix(renderer)
    return (
        ""
        if renderer == "tiny"
        else f', RGB path-traced (`renderer="{renderer}"`: the same scenes and depth, only the RGB differs)'
    )


def renderer_title(renderer: str) -> str:
    """What a section title adds for ``renderer`` (``", physically based rendering"``; nothing for TinyRenderer)."""
    renderer_suffix(renderer)
    return _RENDERER_TITLES[renderer]


def renderer_section(name: str, title: str, renderer: str, after: str | None = None) -> tuple[str, str, str | None]:
    """The name, title and predecessor (:func:`record_section`'s ``after``) of a section measured on the RGB of
    ``renderer``: TinyRenderer's as given; another renderer's ``NAME-pbr``, its title saying so, right after
    TinyRenderer's section ``name``."""
    if renderer == "tiny":
        return name, title, after
    return name + renderer_suffix(renderer), title + renderer_title(renderer), name


_SPLIT_SEEDS = re.compile(r"^Split `[^`]+`: dataset seeds ([0-9][0-9, ]*[0-9])", re.M)


def split_line(split: str, seeds: Sequence[int], spent: Sequence[int], trained_on_seed_0: bool = True) -> str:
    """The opening of a section's split line: which split (``"test"`` or ``"dev"``), its dataset seeds, what
    they may be used for, the spent seeds and (where ``trained_on_seed_0``) the shipped networks' training seed,
    e.g. ``Split `test`: dataset seeds 6101, 6102, 6103 (the test seeds: ...; spent: 1000)``. The caller goes on
    with the sizes and protocol; :func:`split_seeds` reads the seeds back."""
    role = (
        "the test seeds: no decision about data, networks or training has used them"
        if split == "test"
        else "the development seeds, for decisions; the README and the docs quote the test split"
    )
    trained = "; the shipped networks were trained on seed 0" if trained_on_seed_0 else ""
    seed_list, spent_list = ", ".join(map(str, seeds)), ", ".join(map(str, spent))
    return f"Split `{split}`: dataset seeds {seed_list} ({role}; spent: {spent_list}{trained})"


def split_seeds(text: str) -> str | None:
    """The dataset seeds of the first split line (:func:`split_line`) in ``text``, as written (``"6101, 6102,
    6103"``); None where ``text`` has none."""
    match = _SPLIT_SEEDS.search(text)
    return None if match is None else match.group(1)


def kept_object_subsections(
    name: str, objects: Sequence[str], measured: Sequence[str], path: Path = RESULTS_PATH
) -> dict[str, str]:
    """The markdown of each object in ``objects`` but not in ``measured`` that RESULTS.md's section ``name``
    holds, by object: from its first ``### <object>`` heading to the next object's (or the section's end), with
    a line naming the run that measured it (command, date, commit, and the dataset seeds where the section names
    them), so that a run of some objects can keep the others' figures without passing them off as its own. A
    part kept before keeps its original line."""
    text = read_section(name, path)
    if text is None:
        return {}
    origin = section_origin(text)
    # A run on other seeds (the test seeds renewed) must not lend its split line to figures it did not measure.
    seeds = split_seeds(text)
    on_seeds = f" on dataset seeds {seeds}" if seeds else ""
    starts = {}
    for object_name in objects:
        heading = re.search(rf"^### {re.escape(object_name)}\b", text, re.M)
        if heading is not None:
            starts[object_name] = heading.start()
    bounds = sorted(starts.values()) + [len(text)]
    kept = {}
    for object_name, start in starts.items():
        if object_name in measured:
            continue
        part = text[start : bounds[bounds.index(start) + 1]].strip()
        if f"*{object_name}: kept from " not in part:
            part += (
                f"\n\n*{object_name}: kept from the run of {origin['Date']} (commit {origin['Commit']}, "
                f"{origin['Command']}){on_seeds}; the run above measured {', '.join(measured)} only.*"
            )
        kept[object_name] = part
    return kept


def record_section(
    name: str, title: str, body_markdown: str, path: Path = RESULTS_PATH, after: str | None = None
) -> str:
    """Replace the section ``name`` of RESULTS.md, or add it after the section ``after`` (at the end when
    that is None or absent); returns the section text."""
    date = utc_now()
    section = (
        f"<!-- begin {name} -->\n## {title}\n\n"
        f"- Command: `{command_line()}`\n- Machine: {machine_description()}\n- Date: {date}\n"
        f"- Commit: {commit_description()}\n\n"
        f"{body_markdown.strip()}\n<!-- end {name} -->\n"
    )
    text = (
        path.read_text()
        if path.exists()
        else "# Benchmark results\n\nEvery figure below was written by the script named in its section.\n\n"
    )
    pattern = _section_pattern(name)
    end_of_after = f"<!-- end {after} -->\n" if after else None
    if pattern.search(text):
        text = pattern.sub(lambda _: section, text)
    elif end_of_after and end_of_after in text:
        head, tail = text.split(end_of_after, 1)
        text = head + end_of_after + "\n" + section + ("\n" + tail.lstrip("\n") if tail.strip() else "")
    else:
        text = text.rstrip("\n") + "\n\n" + section
    tmp = path.with_suffix(".md.partial")
    tmp.write_text(text)
    os.replace(tmp, path)
    return section


class BlockMarkersError(ValueError):
    """A document lacks the begin/end comments of a generated block, or has them more than once."""


def _block_span(text: str, name: str, path: Path) -> tuple[int, int]:
    """Start and end offsets of the content between ``<!-- begin NAME -->`` and ``<!-- end NAME -->``."""
    begin, end = f"<!-- begin {name} -->", f"<!-- end {name} -->"
    counts = (text.count(begin), text.count(end))
    if counts != (1, 1) or text.index(begin) > text.index(end):
        raise BlockMarkersError(
            f"{path}: expected the lines '{begin}' and, after it, '{end}' once each (found {counts[0]} and "
            f"{counts[1]}); add them where the generated block belongs"
        )
    return text.index(begin) + len(begin), text.index(end)


def require_blocks(path: Path, names: list[str]) -> None:
    """Raise :class:`BlockMarkersError` unless ``path`` has the markers of every block in ``names`` (a
    benchmark checks this before it runs, not after an hour of work)."""
    text = Path(path).read_text()
    for name in names:
        _block_span(text, name, Path(path))


def replace_block(path: Path, name: str, text: str) -> None:
    """Replace the content between ``<!-- begin NAME -->`` and ``<!-- end NAME -->`` in ``path`` with
    ``text`` (the markers stay, so the next run replaces it again); atomic: readers see the old or the new
    file, never a mix. :class:`BlockMarkersError` when the markers are missing or repeated."""
    from don_gym.io import write_text_atomic

    path = Path(path)
    document = path.read_text()
    start, end = _block_span(document, name, path)
    updated = document[:start] + "\n" + text.strip("\n") + "\n" + document[end:]
    if updated != document:
        write_text_atomic(path, updated)
