"""The held-out split the quoted figures rest on: the seed lists are apart, the split names map to the lists
the docs name, and the benchmarks' ``--split test`` reads the test seeds (and piles), ``--split dev`` the
development ones. Nothing here builds a dataset: each benchmark is stopped where it asks for its data."""

from __future__ import annotations

import re
import sys
from itertools import combinations
from pathlib import Path
from types import SimpleNamespace

import pytest

from don_gym.evaluation.splits import (
    BIN_DEVELOPMENT_SEED,
    BIN_TEST_SEED,
    DEVELOPMENT_SEEDS,
    SPENT_SEEDS,
    SPLIT_SEEDS,
    TEST_SEEDS,
    TRAINING_SEEDS,
    seed_split,
)

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))
import bench_bin  # noqa: E402
import bench_grasp  # noqa: E402

LISTS = {"test": TEST_SEEDS, "dev": DEVELOPMENT_SEEDS, "spent": SPENT_SEEDS, "training": TRAINING_SEEDS}


class _Asked(Exception):
    """Raised by a stand-in for the data step: the benchmark has said which seeds it reads."""


def test_seed_lists_are_pairwise_apart_and_each_seed_names_its_list() -> None:
    for (a, seeds_a), (b, seeds_b) in combinations(LISTS.items(), 2):
        assert not set(seeds_a) & set(seeds_b), f"{a} and {b} share seeds {set(seeds_a) & set(seeds_b)}"
    for name, seeds in LISTS.items():
        assert seeds and len(set(seeds)) == len(seeds), name
        assert all(seed_split(s) == name for s in seeds), name


def test_split_names_map_to_their_lists() -> None:
    assert SPLIT_SEEDS == {"test": TEST_SEEDS, "dev": DEVELOPMENT_SEEDS}


def test_bin_piles_of_the_two_splits_never_meet() -> None:
    # The clearing benchmark runs piles seed, seed + 1, ...; the development piles (the env's and the agents'
    # tuning used 0-39, docs/bin.md) must stay below the test piles however many a run takes.
    assert BIN_DEVELOPMENT_SEED + 10_000 <= BIN_TEST_SEED
    assert bench_bin.SPLIT_SEED == {"test": BIN_TEST_SEED, "dev": BIN_DEVELOPMENT_SEED}


def _seeds_in(text: str) -> set[int]:
    """Every 4-digit seed in ``text``, ranges ``a-b`` expanded; dates (``2026-12-04``) left out."""
    seeds: set[int] = set()
    for low, high in re.findall(r"\b(\d{4})(?:-(\d{4}))?\b(?!-\d\d-)", text):
        seeds |= set(range(int(low), int(high or low) + 1))
    return seeds


def _doc_item(text: str, label: str) -> str:
    match = re.search(rf"^- \*\*{label}\*\* (.*?)(?=^- )", text, re.S | re.M)
    assert match, label
    return match.group(1)


def test_the_docs_name_the_lists_the_code_holds() -> None:
    text = (ROOT / "docs" / "reproduction.md").read_text()
    assert _seeds_in(_doc_item(text, "test")) == set(TEST_SEEDS)
    assert _seeds_in(_doc_item(text, "development")) == set(DEVELOPMENT_SEEDS)
    assert _seeds_in(_doc_item(text, "spent")) == set(SPENT_SEEDS)
    # The README's test commands and quoted figures name the test seeds.
    readme = (ROOT / "README.md").read_text()
    quoted = re.findall(r"test scenes \(seeds ([\d, -]+)", readme) + re.findall(r"for seed in ([\d ]+); do", readme)
    assert len(quoted) >= 3 and all(_seeds_in(q) == set(TEST_SEEDS) for q in quoted), quoted


@pytest.mark.parametrize("split", ["test", "dev"])
def test_bench_grasp_tracking_reads_the_seeds_of_its_split(split: str, monkeypatch, tmp_path: Path) -> None:
    asked = {}

    def stand_in(object_name, seeds, work, split_name, *args, **kwargs):
        asked.update(object=object_name, seeds=tuple(seeds), split=split_name)
        raise _Asked

    monkeypatch.setattr(bench_grasp, "build_evaluation_datasets", stand_in)
    args = SimpleNamespace(
        split=split, quick=False, objects=["toolcap"], scenes=1, frames=2, workers=1, points=2, renderer="tiny"
    )
    with pytest.raises(_Asked):
        bench_grasp.tracking(args, tmp_path)
    assert asked == {"object": "toolcap", "seeds": SPLIT_SEEDS[split], "split": split}


@pytest.mark.parametrize(("argv", "split"), [([], "test"), (["--quick"], "dev"), (["--split", "dev"], "dev")])
def test_bench_grasp_runs_the_test_split_unless_told_otherwise(argv, split, monkeypatch) -> None:
    seen = {}

    def tracking(args, work):
        seen["split"] = args.split
        raise _Asked

    monkeypatch.setattr(bench_grasp, "freeze_commit_description", lambda: None)
    monkeypatch.setattr(bench_grasp, "preflight", lambda args: None)
    monkeypatch.setattr(bench_grasp, "tracking", tracking)
    monkeypatch.setattr(sys, "argv", ["bench_grasp.py", "--only", "tracking", *argv])
    with pytest.raises(_Asked):
        bench_grasp.main()
    assert seen == {"split": split}


@pytest.mark.parametrize("split", ["test", "dev"])
def test_bench_bin_reads_the_piles_and_seeds_of_its_split(split: str, monkeypatch, tmp_path: Path) -> None:
    asked = {}

    def clearing_stand_in(config, **kwargs):
        asked["pile_seed"] = config.seed
        raise _Asked

    def tracking_stand_in(object_name, seeds, work, split_name, *args, **kwargs):
        asked.update(seeds=tuple(seeds), split=split_name)
        raise _Asked

    monkeypatch.setattr(bench_bin, "run_bin_benchmark", clearing_stand_in)
    monkeypatch.setattr(bench_bin, "build_evaluation_datasets", tracking_stand_in)
    args = SimpleNamespace(
        quick=True,
        piles=2,
        multi_part=[],
        methods=None,
        workers=1,
        device="cpu",
        work=str(tmp_path),
        scenes=1,
        frames=2,
        points=2,
    )
    with pytest.raises(_Asked):
        bench_bin.clearing(args, split)
    with pytest.raises(_Asked):
        bench_bin.tracking(args, split)
    # The quick run takes the split's first seed only; the full run all of them.
    assert asked == {"pile_seed": bench_bin.SPLIT_SEED[split], "seeds": SPLIT_SEEDS[split][:1], "split": split}
    assert asked["pile_seed"] == (BIN_TEST_SEED if split == "test" else BIN_DEVELOPMENT_SEED)


@pytest.mark.parametrize(("argv", "split"), [([], "test"), (["--quick"], "dev"), (["--split", "dev"], "dev")])
def test_bench_bin_runs_the_test_split_unless_told_otherwise(argv, split, monkeypatch) -> None:
    seen = []
    monkeypatch.setattr(bench_bin, "freeze_commit_description", lambda: None)
    monkeypatch.setattr(bench_bin, "clearing", lambda args, s: seen.append(("clearing", s)))
    monkeypatch.setattr(bench_bin, "tracking", lambda args, s: seen.append(("tracking", s)))
    monkeypatch.setattr(sys, "argv", ["bench_bin.py", *argv])
    bench_bin.main()
    assert seen == [("clearing", split), ("tracking", split)]


def test_the_reliability_section_on_these_names_tests_that_exist() -> None:
    text = (ROOT / "docs" / "reliability.md").read_text()
    section = text.split("## Held-out split, rates, several instances and parts", 1)[1].split("\n## ", 1)[0]
    named = re.findall(r"`(tests/[\w/]+\.py)::(test_\w+)`", section)
    assert len(named) >= 25
    for path, name in named:
        assert re.search(rf"^def {name}\(", (ROOT / path).read_text(), flags=re.MULTILINE), f"{path}::{name}"
