"""Shared helper for benchmark scripts: record a result section in benchmarks/RESULTS.md.

Each benchmark owns one section, delimited by HTML comments, which it replaces on every run.
The section header records the exact command, the machine and the date, so every figure
in RESULTS.md can be traced to the run that produced it.
"""

from __future__ import annotations

import datetime as _dt
import os
import platform
import re
import shlex
import sys
from pathlib import Path

RESULTS_PATH = Path(__file__).resolve().parent / "RESULTS.md"


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


def record_section(name: str, title: str, body_markdown: str, path: Path = RESULTS_PATH) -> str:
    """Replace (or append) the section ``name`` of RESULTS.md; returns the section text."""
    date = _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    section = (
        f"<!-- begin {name} -->\n## {title}\n\n"
        f"- Command: `{command_line()}`\n- Machine: {machine_description()}\n- Date: {date}\n\n"
        f"{body_markdown.strip()}\n<!-- end {name} -->\n"
    )
    text = (
        path.read_text()
        if path.exists()
        else "# Benchmark results\n\nEvery figure below was written by the script named in its section.\n\n"
    )
    pattern = re.compile(rf"<!-- begin {re.escape(name)} -->.*?<!-- end {re.escape(name)} -->\n?", re.S)
    text = pattern.sub(lambda _: section, text) if pattern.search(text) else text.rstrip("\n") + "\n\n" + section
    tmp = path.with_suffix(".md.partial")
    tmp.write_text(text)
    os.replace(tmp, path)
    return section
