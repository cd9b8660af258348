"""bench_grasp's tracking verdicts are drawn from the intervals over scenes: separated intervals decide a
claim, overlapping ones leave it not settled."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from don_gym.evaluation.tracking_metrics import MATCH_CATEGORIES, TrackingMatches

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))
import bench_grasp  # noqa: E402

SCENES, PER_SCENE = 12, 50


def _matches(plain_mm: np.ndarray, symmetric_mm: np.ndarray, closer: float) -> TrackingMatches:
    m = len(plain_mm)
    scene = np.repeat(np.arange(SCENES), PER_SCENE)
    zeros = np.zeros(m, dtype=np.int64)
    return TrackingMatches(
        scene_id=scene,
        dataset=zeros,
        scene=scene,
        frame=zeros + 1,
        point=zeros,
        reference_frame=zeros,
        reference_uv=np.zeros((m, 2), dtype=np.int64),
        matched_uv=np.zeros((m, 2), dtype=np.int64),
        true_uv=np.zeros((m, 2)),
        pixel_error_px=np.full(m, 3.0),
        error_3d_m=plain_mm / 1000.0,
        symmetric_error_m=symmetric_mm / 1000.0,
        fraction_closer=np.full(m, closer),
        depth_valid=np.ones(m, dtype=bool),
        error_3d_ideal_m=plain_mm / 1000.0,
        category=np.full(m, MATCH_CATEGORIES.index("table"), dtype=np.int8),
        scenes_evaluated=SCENES,
    )


def _summary(object_name: str, ssl_symmetric_mm: tuple[float, float], ssl_scene_spread_mm: float = 0.0) -> dict:
    """Supervised networks: plain error 4-8 mm, modulo symmetry 2.5-3.5 mm, no far match. Self-supervised:
    a fifth of its matches 250 mm off in every scene; modulo symmetry drawn from ``ssl_symmetric_mm``, moved
    by ``ssl_scene_spread_mm`` down in even scenes and up in odd ones (scenes that differ: a wide interval)."""
    rng = np.random.default_rng(0)
    n = SCENES * PER_SCENE
    methods = {}
    for kind in ("supervised-edge", "supervised-mask"):
        plain = rng.uniform(4.0, 8.0, n)
        methods[f"{object_name}/{kind}"] = (kind, _matches(plain, rng.uniform(2.5, 3.5, n), 0.002))
    plain = rng.uniform(3.0, 6.0, n)
    plain[rng.random(n) < 0.2] = 250.0
    scene_offset = np.repeat(np.where(np.arange(SCENES) % 2, 1.0, -1.0) * ssl_scene_spread_mm, PER_SCENE)
    symmetric = rng.uniform(*ssl_symmetric_mm, n) + scene_offset
    methods[f"{object_name}/self-supervised"] = ("self-supervised", _matches(plain, symmetric, 0.004))
    return {
        "object": object_name,
        "scenes": SCENES,
        "split": "test",
        "dataset_seeds": [4101, 4102, 4103],
        "frames_per_scene": 12,
        "image_size": [640, 480],
        "methods": {name: {"source": {"method": kind}, **m.summary()} for name, (kind, m) in methods.items()},
    }


def test_claims_hold_on_separated_intervals_and_are_not_settled_on_overlapping_ones() -> None:
    separated = {o: _summary(o, (1.2, 2.4)) for o in ("toolcap", "shaft")}
    blocks = bench_grasp.tracking_claim_blocks(separated, "*source*")
    for claim in "abc":
        assert "Verdict: **holds** (toolcap, shaft)." in blocks[bench_grasp.block(f"claim-{claim}")]
    table = blocks[bench_grasp.block("claim-a")]
    assert "| toolcap | self-supervised |" in table and "| long tail |" in table and "| no long tail |" in table
    # The self-supervised medians now overlap the supervised ones: (a) and (b) cannot be decided.
    overlapping = {o: _summary(o, (2.5, 3.5), ssl_scene_spread_mm=1.5) for o in ("toolcap", "shaft")}
    blocks = bench_grasp.tracking_claim_blocks(overlapping, "*source*")
    assert "Verdict: **not settled** (toolcap, shaft)." in blocks[bench_grasp.block("claim-a")]
    assert "the intervals overlap" in blocks[bench_grasp.block("claim-a")]
    assert "Verdict: **not settled** (toolcap, shaft)." in blocks[bench_grasp.block("claim-b")]
    assert "Verdict: **holds** (toolcap, shaft)." in blocks[bench_grasp.block("claim-c")]


def test_tracking_targets_name_each_supervised_network_met_or_missed() -> None:
    """The shaft's supervised networks of the fixture (median mod symmetry about 3 mm, p99 under 8 mm, no far
    match) meet its targets; a network with a far share over 0.5% or a p99 over the toolcap's 45 mm misses."""
    block = bench_grasp.tracking_block("shaft", _summary("shaft", (1.2, 2.4)), "*source*")
    assert "Targets of the supervised networks:" in block
    for kind in ("supervised-edge", "supervised-mask"):
        assert any(line.startswith(f"- shaft/{kind}: ") and line.endswith(": met") for line in block.splitlines())
    assert "self-supervised:" not in block.split("Targets of the supervised networks:")[1]

    def figures(p99_mm: float, far_pct: float) -> dict:
        return {
            "name": "toolcap/supervised-edge", "p50_sym_mm": 2.5, "p50_sym_ci": (2.0, 3.0), "p99_mm": p99_mm,
            "p99_ci": (30.0, 60.0), "far_pct": far_pct, "far_pct_ci": (0.0, 1.0),
        }  # fmt: skip

    assert bench_grasp.tracking_targets("toolcap", {"supervised-edge": figures(44.0, 0.4)})[0].endswith(": met")
    for p99_mm, far_pct in ((44.0, 0.59), (46.0, 0.4), (float("nan"), 0.0)):
        line = bench_grasp.tracking_targets("toolcap", {"supervised-edge": figures(p99_mm, far_pct)})[0]
        assert line.endswith(": MISSED") and "(target <= 45 mm)" in line and "(target <= 0.5 %)" in line
    assert bench_grasp.tracking_targets("bracket", {"supervised-edge": figures(1.0, 0.0)}) == []


def test_the_development_split_shows_each_margin_beside_the_whole_image_search() -> None:
    """One row per method with its own border margin and both searches' figures, the baseline first."""
    with_margin = _summary("toolcap", (1.2, 2.4))
    for method in with_margin["methods"].values():
        method["source"]["border_margin_px"] = 16
    whole_image = _summary("toolcap", (1.2, 2.4))
    table = bench_grasp.margin_comparison_table(with_margin, whole_image)
    rows = [line for line in table.splitlines() if line.startswith("| toolcap/")]
    assert len(rows) == 3 and all("| 16 |" in row for row in rows)
    ssl = next(row for row in rows if row.startswith("| toolcap/self-supervised |")).split(" | ")
    # The fixture's self-supervised network has a fifth of its matches far in both searches.
    far_whole, far_margin = float(ssl[2].split()[0]), float(ssl[3].split()[0])
    assert 15.0 < far_whole == far_margin < 25.0


def test_the_physically_rendered_runs_write_sections_and_blocks_of_their_own() -> None:
    """--renderer pbr: every section is TinyRenderer's name with -pbr, placed right after it; the claims go to
    blocks of their own whose markers docs/reproduction.md holds; no README block; TinyRenderer's names as before."""
    objects = ["toolcap", "shaft"]
    assert bench_grasp.blocks_of("tracking", objects) == [
        "bench_grasp:tracking-toolcap", "bench_grasp:tracking-shaft",
        "bench_grasp:claim-a", "bench_grasp:claim-b", "bench_grasp:claim-c",
    ]  # fmt: skip
    assert bench_grasp.blocks_of("tracking", objects, "pbr") == [f"bench_grasp:claim-{c}-pbr" for c in "abc"]
    assert bench_grasp.blocks_of("grasp", objects, "pbr") == [f"bench_grasp:claim-{c}-pbr" for c in "def"]
    assert bench_grasp.blocks_of("grasp", ["shaft"], "pbr") == ["bench_grasp:claim-f-pbr"]
    pbr_blocks = [n for part in ("tracking", "grasp") for n in bench_grasp.blocks_of(part, objects, "pbr")]
    bench_grasp.require_blocks(bench_grasp.REPRODUCTION_PATH, pbr_blocks)  # raises where a marker is missing

    assert bench_grasp.tracking_section("test") == (
        "tracking", "Tracking error of the shipped DONs (paper's protocol), test split", None
    )  # fmt: skip
    name, title, after = bench_grasp.tracking_section("test", "pbr")
    assert (name, after) == ("tracking-pbr", "tracking") and title.endswith("test split, physically based rendering")
    assert bench_grasp.tracking_section("dev")[::2] == ("tracking-dev", "tracking")
    assert bench_grasp.tracking_section("dev", "pbr")[::2] == ("tracking-dev-pbr", "tracking-dev")
    assert [bench_grasp.grasp_section(o) for o in objects] == ["grasp", "grasp-shaft"]
    assert [bench_grasp.grasp_section(o, "pbr") for o in objects] == ["grasp-pbr", "grasp-shaft-pbr"]
    assert bench_grasp.grasp_title("toolcap")[1] is None and bench_grasp.grasp_title("shaft")[1] == "grasp"
    assert bench_grasp.grasp_title("shaft", "pbr")[1] == "grasp-shaft"
    assert bench_grasp.grasp_title("toolcap", "pbr")[0].endswith("physically based rendering")

    import bench_pose

    assert bench_pose.pose_section("test") == ("pose", "6D pose from descriptors (BOP metrics), test split", None)
    assert bench_pose.pose_section("test", "pbr")[::2] == ("pose-pbr", "pose")
    assert bench_pose.pose_section("dev", "pbr")[::2] == ("pose-dev-pbr", "pose-dev")
    with pytest.raises(ValueError, match="egl"):
        bench_grasp.renderer_suffix("egl")  # an EGL run would have no sections to go to


def test_the_physically_rendered_claims_name_their_blocks_and_rendering() -> None:
    summaries = {o: _summary(o, (1.2, 2.4)) for o in ("toolcap", "shaft")}
    tiny = bench_grasp.tracking_claim_blocks(summaries, "*source*")
    pbr = bench_grasp.tracking_claim_blocks(summaries, "*source*", "pbr")
    assert list(tiny) == [f"bench_grasp:claim-{c}" for c in "abc"]
    assert list(pbr) == [f"bench_grasp:claim-{c}-pbr" for c in "abc"]
    for c in "abc":
        assert "path-traced" not in tiny[bench_grasp.block(f"claim-{c}")]
        # The same figures give the same verdict; only the data line names the rendering.
        with_rendering = tiny[bench_grasp.block(f"claim-{c}")].replace("640x480,", "640x480" + (
            bench_grasp.rendering_text("pbr") + ","
        ))  # fmt: skip
        assert pbr[bench_grasp.block(f"claim-{c}", "pbr")] == with_rendering
