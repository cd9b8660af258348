"""bench_bin's tracking target: a network of several parts' median against the better single-part supervised
network's of the same part, the verdict drawn from their ratio."""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))
import bench_bin  # noqa: E402

MULTI = "runs/bin/model.safetensors"
SINGLES = ["toolcap/supervised-edge", "toolcap/supervised-mask", "toolcap/self-supervised"]


def _summary(medians_mm: dict[str, float | None]) -> dict:
    """A summary whose methods have only the figures the target reads: kind and median of the target's metric."""
    kinds = {name: name.rsplit("/", 1)[-1] if "/" in name else "supervised-edge" for name in medians_mm}
    kinds[MULTI] = "supervised-edge"
    return {
        "methods": {
            name: {
                "source": {"method": kinds[name]},
                bench_bin.TARGET_METRIC: {"p50": value},
                "intervals": {bench_bin.TARGET_METRIC: {"p50": None if value is None else [value - 1.0, value + 1.0]}},
            }
            for name, value in medians_mm.items()
        }
    }


def test_target_compares_with_the_better_supervised_single_part_network() -> None:
    # The self-supervised network's lower median is no baseline: the issue compares supervised networks.
    base = {"toolcap/supervised-edge": 3.0, "toolcap/supervised-mask": 2.9, "toolcap/self-supervised": 1.0}
    (line,) = bench_bin.tracking_target(_summary({**base, MULTI: 4.3}), SINGLES, [MULTI])
    assert "toolcap/supervised-mask's" in line and "= 1.48" in line and line.endswith("**met**")
    (line,) = bench_bin.tracking_target(_summary({**base, MULTI: 4.4}), SINGLES, [MULTI])
    assert "= 1.52" in line and line.endswith("**missed**")
    (line,) = bench_bin.tracking_target(_summary({**base, MULTI: None}), SINGLES, [MULTI])
    assert "not checked" in line
    (line,) = bench_bin.tracking_target(_summary(base), SINGLES, [])
    assert "not checked" in line and "--multi-part" in line
    (line,) = bench_bin.tracking_target(_summary({"toolcap/self-supervised": 1.0, MULTI: 4.0}), SINGLES, [MULTI])
    assert "no single-part supervised network" in line


def test_the_shipped_networks_of_several_parts_are_the_default() -> None:
    from don_gym.zoo import shipped_multi_part_names

    assert bench_bin.multi_part_networks(None, quick=False) == shipped_multi_part_names()
    assert "bin/supervised-edge" in shipped_multi_part_names()
    assert bench_bin.multi_part_networks(None, quick=True) == []  # --quick stays a minute with the oracles
    assert bench_bin.multi_part_networks([], quick=False) == []  # "--multi-part" with none leaves them out
    assert bench_bin.multi_part_networks([MULTI], quick=True) == [MULTI]
