"""Reproduce the networks shipped in don_gym/shipped from scratch, and record the run.

For each object (toolcap, shaft): build a dataset (640x480, d435 sensor, seed 0; 64 scenes of the toolcap,
256 of the shaft, 6 frames each, mixed backdrops, 4 distractors, random light), train one network per method
(``resnet-lite``, ``resnet-lite-fine`` for supervised-mask; crops of 128x128 for the toolcap and 256x192 for
the shaft, half of them anywhere in the frame and half object-centred; 18000 steps, lr x0.9 every 750; fixed
seed), copy its final weights to
``don_gym/shipped/<object>/<method>.safetensors`` and record its training time, images/s and final loss in
benchmarks/RESULTS.md, one section per object (``shipped-<object>``). Each row names the scenes, their data,
steps and commit its network was made with; a run of some methods (``--methods``) keeps the rows of the
object's other shipped networks, so the table always describes what is shipped. Every network of an object is
trained on the same scenes.

    python benchmarks/train_shipped.py            # the shipped recipe
    python benchmarks/train_shipped.py --quick    # a smoke run into a temp dir (no copy)
    python benchmarks/train_shipped.py --restamp --work runs/shipped   # no training: add the part identity
    python benchmarks/train_shipped.py --renderer mixed --base runs/base --no-ship   # fine-tune candidates

``--renderer mixed`` (or ``pbr``) adds a second stage (issue 56): each method's network from the recipe above (stage 1,
TinyRenderer data; ``--base DIR`` takes them from ``DIR/<object>/<method>.safetensors`` instead of training them)
is fine-tuned for ``--fine-tune-steps`` on a dataset of that renderer (``FINE_TUNE_SCENES``, the same variety and
seed; for ``mixed`` half its scenes path-traced), with its own run directory ``run_<object>_<method>_<renderer>``;
the stage-2 network is the one shipped. ``--no-ship`` trains and reports without copying or recording anything, so
candidates can be judged on development seeds first; the same command without it then ships the finished runs
without training them again. ``--fine-tune-seed`` changes stage 2's training seed (0 otherwise): stage-2 runs
that differ only in seed spread widely on the path-traced scenes (docs/background.md, "Steel that looks like
steel"), so a change is judged on several seeds, each in its own ``--work``.

Every copied network carries the identity of its part and its descriptor field (docs/reliability.md, "Part
identity"). ``--restamp`` adds them in place to shipped networks saved without them (weights untouched),
with the field from ``<work>/data_<object>/descriptor_field.npz`` when that has the recorded hash, else
computed here and checked against it; networks that have them are left as they are.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _results import RESULTS_PATH, commit_description, read_section, record_section, section_origin  # noqa: E402
from check_shipped import record_regenerated  # noqa: E402

from don_gym.cli import decay_rate, nonnegative_int, parse_size, positive_int  # noqa: E402
from don_gym.data.build import DATASET_RENDERERS, DatasetConfig, build_dataset  # noqa: E402
from don_gym.data.dataset import FIELD_FILE  # noqa: E402
from don_gym.descriptors import DescriptorField  # noqa: E402
from don_gym.errors import DonGymError  # noqa: E402
from don_gym.learning.checkpoints import read_checkpoint_metadata, restamp_checkpoint  # noqa: E402
from don_gym.learning.methods import is_supervised  # noqa: E402
from don_gym.learning.model import ARCHS, DEFAULT_ARCH  # noqa: E402
from don_gym.learning.train import TrainConfig, TrainResult, train  # noqa: E402
from don_gym.objects import load_object  # noqa: E402
from don_gym.sim.backdrop import BACKDROP_SETS  # noqa: E402
from don_gym.zoo import SHIPPED_DIR  # noqa: E402

OBJECTS = ("toolcap", "shaft")
METHODS = ("supervised-edge", "supervised-mask", "self-supervised")
CROPS = {"toolcap": (128, 128), "shaft": (256, 192)}
# Many scenes of few frames each, with wide backdrops, distractors and random light (docs/background.md,
# "Training data"): networks trained on 16-32 scenes of 24 frames on the classic backdrops had a long tail of
# matches on unseen high-contrast backgrounds. Toolcap: 384 frames, as many as before. Shaft: 256 scenes (1536
# frames), not 128: on the development scenes its supervised-edge network then had no match on the shaft's other
# end (the failure on the earlier test scenes), a p99 of 15 mm instead of 22 and a far share of 0.46%, within
# the target of 0.5% (docs/background.md, "Training data").
SCENES = {"toolcap": 64, "shaft": 256}
FRAMES = 6
# Mixed backdrops (half from the classic three families, half from all nine): on the development scenes the
# toolcap's supervised-edge network trained on the wide set had most of its far matches on striped table tops,
# which the wide set shows in 1 draw of 9 (docs/background.md, "Training data").
VARIETY = {"backgrounds": "mixed", "distractors": 4, "lighting": "random"}
# Three times TrainConfig's 6000 steps, the lr decay stretched to keep the schedule's shape (x0.9 every 750 instead
# of 250): on the development scenes a lower median and fewer far matches than at 6000; 36000 was worse again
# (docs/background.md, "Training data").
STEPS = 18000
LR_DECAY_EVERY = 750
# Half of the crops anywhere in the frame (TrainConfig's default: a tenth). On the development scenes (seeds
# 3101-3103) the toolcap's supervised-edge network trained on the varied data with a tenth had 9.6% of its matches
# more than 100 mm off, most on the table near the frame's borders, which whole-frame inference sees and
# object-centred crops rarely show; with half, 1.0% (the network trained on the classic data: 2.1%).
BACKGROUND_CROPS = 0.5
# The supervised-mask networks' background channel turns the stride-8 blend of part and background a few pixels
# inside the silhouette into matches off the part (p99 of the shaft's 3D error 246 mm with resnet-lite); the
# decoder of resnet-lite-fine resolves the silhouette at stride 2.
ARCH = {"supervised-edge": "resnet-lite", "supervised-mask": "resnet-lite-fine", "self-supervised": "resnet-lite"}
# Stage 2 (issue 56), with "mixed" half path-traced and half TinyRenderer: 256 scenes for the toolcap, whose
# supervised candidates on 128 with the hard-pixel terms kept 0.6-0.9% of their matches on the path-traced
# development scenes more than 100 mm off, and 0.4-0.5% on 256 (docs/background.md, "Steel that looks like steel");
# 128 for the shaft, whose stage 1 saw 256 scenes (path-traced frames cost ~2.6 s each on 2 cores).
FINE_TUNE_SCENES = {"toolcap": 256, "shaft": 128}
# A sixth of stage 1's steps, at a third of its initial learning rate, decayed x0.9 every 300 steps: the network
# adapts to the new look without starting over (docs/background.md, "Training data").
FINE_TUNE_STEPS = 3000
FINE_TUNE_LR = 3e-4
FINE_TUNE_DECAY_EVERY = 300
# Stage 2 of the supervised methods also penalises each crop's worst 10% of part pixels and worst 1% of background
# pixels away from the part (TrainConfig.hard_object_fraction, hard_background_fraction). With the plain l2 loss the
# toolcap's supervised-edge candidate kept 1.6% of its matches on the path-traced development scenes more than
# 100 mm off: references on end faces that mirror the table, which the network called background, and a steel-grey
# cradle it painted with part descriptors; the two terms took the share to 0.6% (docs/background.md, "Steel that
# looks like steel").
FINE_TUNE_HARD_OBJECT = 0.1
FINE_TUNE_HARD_BACKGROUND = 0.01
TABLE_COLUMNS = (
    "object", "method", "arch", "scenes", "data", "bg crops", "steps", "lr decay every", "minutes", "images/s",
    "final loss", "MB", "commit",
)  # fmt: skip


def restamp_shipped(object_name: str, method: str, data: Path) -> None:
    """Give ``don_gym/shipped/<object>/<method>.safetensors`` its part identity and descriptor field, the field
    from the run's dataset ``data`` when it has the recorded one; idempotent."""
    target = SHIPPED_DIR / object_name / f"{method}.safetensors"
    candidates = [DescriptorField.load(data / FIELD_FILE)] if (data / FIELD_FILE).is_file() else []
    _, done = restamp_checkpoint(target, load_object(object_name), candidates)
    print(f"{object_name}/{method}: {done}")


def check_runs_match(work: Path, object_name: str, methods: list[str], scenes: int) -> None:
    """Refuse a work directory whose runs of ``object_name`` were trained on another number of scenes:
    building the dataset would grow it under them, and resuming a finished run would ship its network
    as trained on ``scenes``."""
    for method in methods:
        run = work / f"run_{object_name}_{method}"
        saved = [*sorted(run.glob("checkpoints/step_*.safetensors")), *run.glob("model.safetensors")]
        trained_on = read_checkpoint_metadata(saved[-1]).extra.get("dataset_scenes") if saved else None
        if trained_on is not None and trained_on != scenes:
            raise DonGymError(
                f"{run}: a run on {trained_on} scenes, not the {scenes} asked; pass --scenes {trained_on} to "
                "continue it, or another --work"
            )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--work", default="runs/shipped", help="directory for datasets and runs")
    parser.add_argument(
        "--scenes",
        type=positive_int,
        default=None,
        help="scenes of each object's dataset (default: per object, see SCENES)",
    )
    parser.add_argument("--frames", type=positive_int, default=FRAMES, help="camera frames per scene")
    parser.add_argument("--backgrounds", choices=tuple(BACKDROP_SETS), default=VARIETY["backgrounds"])
    parser.add_argument("--distractors", type=int, default=VARIETY["distractors"])
    parser.add_argument("--lighting", choices=("fixed", "random"), default=VARIETY["lighting"])
    # 640x480 rather than 320x240: at the env's observation pose (0.45 m above the table) the toolcap spans
    # about 30 px at 320x240, four cells of the network's output stride 8, too few to tell its flange end
    # from its open end; at 640x480 it spans about 60 px.
    parser.add_argument("--size", type=parse_size, default=(640, 480), help="image WIDTHxHEIGHT (default 640x480)")
    # The shaft spans a median 143 px and up to 230 px at 640x480: a 128x128 crop often holds one end only, and
    # a network trained on such crops cannot tell its ends apart (p90 ~65 mm); the toolcap spans ~60 px.
    parser.add_argument(
        "--crop", type=parse_size, default=None, help="training crop WIDTHxHEIGHT (default: per object, see CROPS)"
    )
    parser.add_argument("--steps", type=positive_int, default=STEPS)
    parser.add_argument(
        "--lr-decay-every",
        type=positive_int,
        default=LR_DECAY_EVERY,
        help="steps between learning-rate decays by x0.9 (scale it with --steps: 250 for 6000, 750 for 18000)",
    )
    parser.add_argument(
        "--background-crops",
        type=float,
        default=BACKGROUND_CROPS,
        help="share of crops placed anywhere in the frame (TrainConfig.background_crop_probability)",
    )
    parser.add_argument(
        "--arch", choices=sorted(ARCHS), default=None, help="network arch of every method (default: per method, ARCH)"
    )
    parser.add_argument(
        "--checkpoint-every",
        type=positive_int,
        default=None,
        help="steps between resumable checkpoints (default: a quarter of --steps); closer ones lose less of a run "
        "cut short, which benchmarks/resume/ keeps",
    )
    parser.add_argument("--batch-size", type=positive_int, default=8)
    parser.add_argument(
        "--threads", type=positive_int, default=1, help="torch threads per training (1: see TrainConfig)"
    )
    # Batches built in worker processes do not change the curve (don_gym.learning.train), only the time: the
    # loading share of a step was a third at 256x192 crops without them.
    parser.add_argument("--workers", type=int, default=2, help="processes that build the batches (0: in the loop)")
    parser.add_argument("--objects", nargs="+", choices=OBJECTS, default=list(OBJECTS))
    parser.add_argument("--methods", nargs="+", default=list(METHODS))
    parser.add_argument(
        "--renderer",
        choices=DATASET_RENDERERS,
        default="tiny",
        help="tiny: the networks of stage 1 are shipped; mixed or pbr: they are fine-tuned on data of that renderer "
        "(stage 2) and the result shipped",
    )
    parser.add_argument(
        "--base",
        default=None,
        help="stage 2 starts from DIR/<object>/<method>.safetensors instead of training stage 1 here",
    )
    parser.add_argument("--fine-tune-steps", type=positive_int, default=FINE_TUNE_STEPS)
    parser.add_argument(
        "--fine-tune-scenes", type=positive_int, default=None, help="stage 2's scenes (default: FINE_TUNE_SCENES)"
    )
    parser.add_argument(
        "--fine-tune-seed",
        type=nonnegative_int,
        default=0,
        help="stage 2's training seed (default 0); runs of several seeds, each with its own --work, measure the "
        "spread between runs that a change must beat",
    )
    parser.add_argument(
        "--fine-tune-ema",
        type=decay_rate,
        default=0.0,
        metavar="DECAY",
        help="stage 2 saves an exponential moving average of its weights with this decay (TrainConfig.ema_decay; "
        "default 0: the last step's weights)",
    )
    parser.add_argument("--no-ship", action="store_true", help="train and report; copy and record nothing")
    parser.add_argument("--quick", action="store_true", help="tiny smoke run in a temp dir; copies nothing")
    parser.add_argument(
        "--restamp", action="store_true", help="no training: add the part identity to the shipped networks in place"
    )
    args = parser.parse_args()
    if args.restamp:
        for object_name in args.objects:
            for method in args.methods:
                if (SHIPPED_DIR / object_name / f"{method}.safetensors").is_file():
                    restamp_shipped(object_name, method, Path(args.work) / f"data_{object_name}")
        return
    work = Path(tempfile.mkdtemp(prefix="don_gym_shipped_")) if args.quick else Path(args.work)
    if args.quick:
        args.scenes, args.frames, args.steps, args.fine_tune_steps, args.fine_tune_scenes = 2, 6, 20, 10, 2
    ship = not (args.quick or args.no_ship)
    archs = {method: args.arch or ARCH.get(method, DEFAULT_ARCH) for method in args.methods}
    rows: dict[str, dict[str, str]] = {name: {} for name in args.objects}
    shipped = []
    crops = {name: args.crop or CROPS[name] for name in args.objects}
    scenes = {name: SCENES[name] if args.scenes is None else args.scenes for name in args.objects}
    commit = commit_description()
    for object_name in args.objects:
        check_runs_match(work, object_name, args.methods, scenes[object_name])
        if args.base is None or args.renderer == "tiny":
            config = dataset_config(args, object_name, scenes[object_name])
            build_timed(config, work / f"data_{object_name}", object_name)
        if args.renderer != "tiny":
            fine_scenes, fine_data = stage_two_data(args, work, object_name)
            build_timed(dataset_config(args, object_name, fine_scenes, args.renderer), fine_data, object_name)
        for method in args.methods:
            if args.renderer == "tiny":
                row, result, trained_on = train_stage_one(args, work, object_name, method, archs[method], crops, scenes)
            else:
                row, result, trained_on = fine_tune(args, work, object_name, method, archs[method], crops, scenes)
            rows[object_name][method] = {**row, "commit": commit}
            if ship:
                target = SHIPPED_DIR / object_name / f"{method}.safetensors"
                target.parent.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(result.model_path, target)
                print(f"shipped {target}")
                restamp_shipped(object_name, method, trained_on)
                shipped.append(f"{object_name}/{method}")
    width, height = args.size
    for object_name in args.objects:
        crop_width, crop_height = crops[object_name]
        section = f"shipped-{object_name}"
        # A run of some methods keeps the rows of the others: they describe networks still shipped.
        kept = {} if args.quick else recorded_rows(section)
        table = sorted(
            {**kept, **rows[object_name]}.values(),
            key=lambda row: METHODS.index(row["method"]) if row["method"] in METHODS else len(METHODS),
        )
        body = f"""Datasets: the row's scenes, each of the frames and variety its data column names (backdrop families,
distractors, light: docs/background.md, "Training data"), {width}x{height}, sensor `d435`, TinyRenderer, seed 0; a row
with two figures in a column (stage 1 + stage 2) was then fine-tuned on the data its column names after the ";".
Training: the row's network arch, batch {args.batch_size} (images, or image pairs for self-supervised),
{crop_width}x{crop_height} crops (the row's bg crops share anywhere in the frame, the rest object-centred), Adam lr
1e-3 x0.9 every "lr decay every" steps, seed 0, {args.threads} torch thread(s), {args.workers} loader worker(s).
Final loss = mean of the last 5% of steps (the two methods' losses are on different scales and not comparable
with each other). Minutes and images/s add up every session of a resumed run; n/a marks a run resumed from a
state saved before don_gym recorded them. Each row names the commit its network was recorded at; a row from an
earlier run of this script is kept while its network is still the shipped one.

| {" | ".join(TABLE_COLUMNS)} |
|{"---|" * len(TABLE_COLUMNS)}
""" + "\n".join("| " + " | ".join(row.get(c, "n/a") for c in TABLE_COLUMNS) + " |" for row in table)
        print(body)
        if ship:
            record_section(section, f"Shipped networks: {object_name} (train_shipped.py)", body)
    if shipped:
        # The manifest of tests/test_shipped_fresh.py: these networks are made with the current sources.
        record_regenerated(shipped)


def _minutes(result: TrainResult) -> str:
    return "n/a" if result.seconds is None else f"{result.seconds / 60:.1f}"


def _images_per_second(result: TrainResult) -> str:
    return "n/a" if result.images_per_second is None else f"{result.images_per_second:.1f}"


def dataset_config(args: argparse.Namespace, object_name: str, scenes: int, renderer: str = "tiny") -> DatasetConfig:
    """The recipe's dataset of ``object_name``: ``scenes`` scenes of ``renderer``, the variety of the options."""
    return DatasetConfig(
        object=object_name,
        scenes=scenes,
        frames_per_scene=args.frames,
        image_size=args.size,
        sensor="d435",
        renderer=renderer,
        backgrounds=args.backgrounds,
        distractors=args.distractors,
        lighting=args.lighting,
    )


def build_timed(config: DatasetConfig, data: Path, object_name: str) -> None:
    """Build (or finish) the recipe's dataset ``config`` in ``data``, saying how many frames that took how long."""
    start = time.perf_counter()
    report = build_dataset(config, data)
    elapsed = time.perf_counter() - start
    print(f"{object_name}: {config.renderer} dataset, {report.frames_written} new frames in {elapsed:.0f} s")


def stage_two_data(args: argparse.Namespace, work: Path, object_name: str) -> tuple[int, Path]:
    """Stage 2's scenes of ``object_name`` and its dataset directory ``work/data_<object>_<renderer>``."""
    return args.fine_tune_scenes or FINE_TUNE_SCENES[object_name], work / f"data_{object_name}_{args.renderer}"


def run_config(
    args: argparse.Namespace,
    method: str,
    arch: str,
    data: Path,
    run: Path,
    crop: tuple[int, int],
    steps: int,
    seed: int = 0,
    **schedule: Any,
) -> TrainConfig:
    """The recipe's training run of ``steps`` steps on ``data`` into ``run`` with training seed ``seed``;
    ``schedule``: the stage's lr, decay and init."""
    return TrainConfig(
        method=method,
        data=str(data),
        out=str(run),
        steps=steps,
        arch=arch,
        batch_size=args.batch_size,
        seed=seed,
        crop_size=crop,
        background_crop_probability=args.background_crops,
        threads=args.threads,
        workers=args.workers,
        checkpoint_every=max(1, steps // 4) if args.checkpoint_every is None else args.checkpoint_every,
        **schedule,
    )


def train_stage_one(
    args: argparse.Namespace,
    work: Path,
    object_name: str,
    method: str,
    arch: str,
    crops: dict[str, tuple[int, int]],
    scenes: dict[str, int],
) -> tuple[dict[str, str], TrainResult, Path]:
    """Stage 1 (the TinyRenderer recipe) of one network in ``work/run_<object>_<method>``, resumed if there: its
    table row, result and dataset directory."""
    data = work / f"data_{object_name}"
    run = work / f"run_{object_name}_{method}"
    crop = crops[object_name]
    config = run_config(args, method, arch, data, run, crop, args.steps, lr_decay_every=args.lr_decay_every)
    result = train(config, resume=True)
    row = {
        "object": object_name,
        "method": method,
        "arch": arch,
        "scenes": str(scenes[object_name]),
        "data": data_description(args.frames, args.backgrounds, args.distractors, args.lighting),
        "bg crops": f"{args.background_crops:g}",
        "steps": str(args.steps),
        "lr decay every": str(args.lr_decay_every),
        "minutes": _minutes(result),
        "images/s": _images_per_second(result),
        "final loss": f"{result.final_loss:.4g}",
        "MB": f"{result.model_path.stat().st_size / 1e6:.1f}",
    }
    return row, result, data


def fine_tune(
    args: argparse.Namespace,
    work: Path,
    object_name: str,
    method: str,
    arch: str,
    crops: dict[str, tuple[int, int]],
    scenes: dict[str, int],
) -> tuple[dict[str, str], TrainResult, Path]:
    """Stage 2 of one network: stage 1's (``--base``'s, or trained here) fine-tuned on a dataset of ``--renderer``
    in ``work/run_<object>_<method>_<renderer>``, resumed if there (its dataset built already: :func:`stage_two_data`):
    its table row, result and dataset directory."""
    if args.base is not None:
        base = Path(args.base) / object_name / f"{method}.safetensors"
        if not base.is_file():
            raise DonGymError(f"--base {args.base}: no {object_name}/{method}.safetensors there to fine-tune")
        base_row = {"minutes": "n/a", "images/s": "n/a"}
    else:
        base_row, base_result, _ = train_stage_one(args, work, object_name, method, arch, crops, scenes)
        base = base_result.model_path
    fine_scenes, data = stage_two_data(args, work, object_name)
    steps = args.fine_tune_steps
    run = work / f"run_{object_name}_{method}_{args.renderer}"
    hard = {"hard_object_fraction": FINE_TUNE_HARD_OBJECT, "hard_background_fraction": FINE_TUNE_HARD_BACKGROUND}
    config = run_config(
        args, method, arch, data, run, crops[object_name], steps, seed=args.fine_tune_seed,
        lr=FINE_TUNE_LR, lr_decay_every=FINE_TUNE_DECAY_EVERY, init_path=str(base), ema_decay=args.fine_tune_ema,
        **(hard if is_supervised(method) else {}),
    )  # fmt: skip
    result = train(config, resume=True)
    description = data_description(args.frames, args.backgrounds, args.distractors, args.lighting)
    row = {
        "object": object_name,
        "method": method,
        "arch": arch,
        "scenes": f"{scenes[object_name]} + {fine_scenes}",
        "data": f"{description}; then {fine_scenes} scenes {args.renderer} ({RENDERER_WORDS[args.renderer]})"
        + (
            f", loss + worst {FINE_TUNE_HARD_OBJECT:.0%} part / {FINE_TUNE_HARD_BACKGROUND:.0%} background pixels"
            if is_supervised(method)
            else ""
        )
        + (f", training seed {args.fine_tune_seed}" if args.fine_tune_seed else "")
        + (f", weights averaged (EMA {args.fine_tune_ema:g})" if args.fine_tune_ema else ""),
        "bg crops": f"{args.background_crops:g}",
        "steps": f"{args.steps} + {steps}",
        "lr decay every": f"{args.lr_decay_every} + {FINE_TUNE_DECAY_EVERY} (lr {FINE_TUNE_LR:g})",
        "minutes": f"{base_row['minutes']} + {_minutes(result)}",
        "images/s": f"{base_row['images/s']} + {_images_per_second(result)}",
        "final loss": f"{result.final_loss:.4g}",
        "MB": f"{result.model_path.stat().st_size / 1e6:.1f}",
    }
    return row, result, data


RENDERER_WORDS = {
    "pbr": "path-traced",
    "mixed": "half path-traced, half TinyRenderer",
    "egl": "OpenGL",
    "tiny": "TinyRenderer",
}


def data_description(frames: int, backgrounds: str, distractors: int, lighting: str) -> str:
    """A row's training data in a few words, e.g. ``6 frames/scene, wide backdrops, 4 distractors, random light``."""
    parts = [f"{frames} frames/scene", f"{backgrounds} backdrops"]
    if distractors:
        parts.append(f"{distractors} distractors")
    parts.append(f"{lighting} light")
    return ", ".join(parts)


def recorded_rows(section: str, path: Path = RESULTS_PATH) -> dict[str, dict[str, str]]:
    """The rows of the table in RESULTS.md's section ``section``, by method, as column -> cell. A row without a
    ``scenes`` or ``arch`` cell takes it from its shipped network's metadata, one without a ``commit`` cell the
    section's commit line ("not recorded" when it has none)."""
    text = read_section(section, path)
    if text is None:
        return {}
    commit = section_origin(text)["Commit"]
    lines = [line.strip() for line in text.splitlines() if line.strip().startswith("|")]
    if len(lines) < 3:
        return {}
    header = [cell.strip() for cell in lines[0].strip("|").split("|")]
    rows = {}
    for line in lines[2:]:
        row = dict(zip(header, (cell.strip() for cell in line.strip("|").split("|")), strict=False))
        if "method" not in row or "object" not in row:
            continue
        network = SHIPPED_DIR / row["object"] / f"{row['method']}.safetensors"
        metadata = read_checkpoint_metadata(network) if network.is_file() else None
        if "data" not in row:
            # Rows recorded before the data column: networks trained before the variety options existed.
            frames = None if metadata is None else metadata.extra.get("dataset_frames_per_scene")
            row["data"] = "n/a" if frames is None else data_description(int(frames), "classic", 0, "fixed")
        if "bg crops" not in row:
            share = None if metadata is None else metadata.extra.get("background_crop_probability", 0.1)
            row["bg crops"] = "n/a" if share is None else f"{share:g}"
        if "scenes" not in row:
            scenes = None if metadata is None else metadata.extra.get("dataset_scenes")
            row["scenes"] = "n/a" if scenes is None else str(scenes)
        if "arch" not in row:
            row["arch"] = "n/a" if metadata is None else metadata.arch
        # Rows recorded before the column: every shipped network until then decayed its lr every 250 steps.
        row.setdefault("lr decay every", "250")
        row.setdefault("commit", commit)
        rows[row["method"]] = row
    return rows


if __name__ == "__main__":
    try:
        main()
    except DonGymError as exc:  # a bad option or work directory: one line, as the don-gym CLI says it
        sys.exit(f"train_shipped.py: {exc}")
