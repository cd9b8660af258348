"""``don-gym build-dataset``: record scenes and write targets for both training methods."""

from __future__ import annotations

import argparse

# DatasetConfig's renderers (don_gym.data.build.DATASET_RENDERERS, which a test keeps equal), listed here so that
# parsing the command line does not import the dataset builder.
RENDERER_CHOICES = ("tiny", "egl", "pbr", "mixed")

#: The pile of a bin build without --parts.
DEFAULT_PARTS = "toolcap:3,shaft:2"


def _size(text: str) -> tuple[int, int]:
    from don_gym.cli import parse_size
    from don_gym.errors import DonGymError

    try:
        return parse_size(text, "--size")
    except DonGymError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "build-dataset",
        help="record simulated scenes and write a DON dataset (targets, masks, fused depth)",
        description=(
            "Record scenes of one object with the Panda's wrist camera and write a versioned dataset: RGB, "
            "sensor and ideal depth (uint16 mm PNG), object masks, supervised descriptor targets rendered "
            "from the reported camera poses, and TSDF-fused depth with masks for self-supervised training. "
            "Resumable: finished scenes are skipped. Format: docs/dataset_format.md."
        ),
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    parser.add_argument(
        "--object",
        default=None,
        help="with --scene single: built-in name (toolcap, shaft) or a mesh file (default: toolcap); a bin build "
        "takes its parts from --parts",
    )
    parser.add_argument(
        "--scene",
        default="single",
        choices=["single", "bin"],
        help="single: one part on the table (--object); bin: a pile of several parts' instances in a bin (--parts)",
    )
    parser.add_argument(
        "--parts",
        default=None,
        help="with --scene bin: PART:COUNT[,PART:COUNT...] instances per pile (built-in names or mesh files; "
        f"default: {DEFAULT_PARTS})",
    )
    parser.add_argument(
        "--object-scale", type=float, default=None, help="mesh file units to metres (e.g. 0.001 for mm)"
    )
    parser.add_argument("--scenes", type=int, default=4, help="number of scenes (object poses)")
    parser.add_argument("--frames", type=int, default=24, help="camera frames per scene")
    parser.add_argument("--size", type=_size, default=(320, 240), help="image size WIDTHxHEIGHT in pixels")
    parser.add_argument("--sensor", default="d435", help="depth sensor preset (ideal, d435, ...)")
    parser.add_argument(
        "--renderer",
        default="tiny",
        choices=list(RENDERER_CHOICES),
        help="renderer of the RGB images: tiny (TinyRenderer, default), egl (OpenGL), pbr (path-traced, the pbr "
        "extra), mixed (odd-numbered scenes pbr, the others tiny: training data for networks that must hold on both)",
    )
    parser.add_argument("--dim", type=int, default=3, help="descriptor dimension D")
    parser.add_argument("--no-symmetry", action="store_true", help="plain Laplacian Eigenmaps (no GISIF merging)")
    parser.add_argument("--no-fusion", action="store_true", help="skip TSDF depth fusion (supervised data only)")
    parser.add_argument(
        "--backgrounds",
        default="classic",
        choices=["classic", "wide", "mixed"],
        help="backdrop texture families on the table and floor: classic (noise, stripes, checks), wide (nine "
        "families, docs/background.md) or mixed (half classic, half wide)",
    )
    parser.add_argument(
        "--distractors", type=int, default=0, help="coloured primitives placed on the table around the object per scene"
    )
    parser.add_argument(
        "--lighting", default="fixed", choices=["fixed", "random"], help="one fixed light, or a light drawn per scene"
    )
    parser.add_argument("--seed", type=int, default=0, help="base seed; scene i uses a seed derived from (seed, i)")
    parser.add_argument("--workers", type=int, default=1, help="worker processes, one PyBullet client each")
    parser.add_argument(
        "--shard",
        default="0/1",
        help="i/n (0 <= i < n): build only scenes i, i+n, ...; shards may run at once, on several machines "
        "sharing OUT (job arrays; README.md)",
    )
    parser.add_argument(
        "--overwrite", action="store_true", help="delete OUT first (after all options are checked) and build anew"
    )
    parser.add_argument("--out", required=True, help="output dataset directory")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from don_gym.data.build import DatasetConfig, build_dataset, parse_shard
    from don_gym.errors import DatasetError

    if args.scene == "bin" and args.object is not None:
        raise DatasetError(
            f"--object {args.object!r}: a bin build (--scene bin) takes its parts from --parts, e.g. "
            f"--parts {args.object}:3,shaft:2; leave out --object"
        )
    if args.scene == "single" and args.parts is not None:
        raise DatasetError(
            f"--parts {args.parts!r}: piles of several parts are built with --scene bin; a one-part build "
            "(--scene single, the default) takes its part from --object"
        )
    config = DatasetConfig(
        object="toolcap" if args.object is None else args.object,
        object_scale=args.object_scale,
        scenes=args.scenes,
        frames_per_scene=args.frames,
        image_size=tuple(args.size),
        sensor=args.sensor,
        renderer=args.renderer,
        seed=args.seed,
        descriptor_dim=args.dim,
        symmetric=not args.no_symmetry,
        fuse_depth=not args.no_fusion,
        backgrounds=args.backgrounds,
        distractors=args.distractors,
        lighting=args.lighting,
    )
    shard = parse_shard(args.shard)
    try:
        if args.scene == "bin":
            from don_gym.data.bin_dataset import build_bin_dataset, parse_parts

            parts = parse_parts(args.parts or DEFAULT_PARTS)
            report = build_bin_dataset(
                config, parts, args.out, workers=args.workers, shard=shard, overwrite=args.overwrite
            )
        else:
            report = build_dataset(config, args.out, workers=args.workers, shard=shard, overwrite=args.overwrite)
    except OSError as exc:  # a full disk, a lost mount: what is finished stays valid, so say how to go on
        raise DatasetError(
            f"{args.out}: {exc}; every finished scene is kept: fix this and run the same command again to resume"
        ) from exc
    print(
        f"{args.out}: wrote {report.scenes_written} scenes ({report.frames_written} frames, "
        f"{report.frames_per_second:.1f} frames/s), skipped {report.scenes_skipped} finished scenes; "
        f"{report.scenes_complete} of {report.scenes_total} scenes complete"
    )
    return 0
