"""``don-gym import-bop``: one part of a BOP scene-wise dataset as a don_gym dataset."""

from __future__ import annotations

import argparse


def register(subparsers: argparse._SubParsersAction) -> None:
    from don_gym.cli import positive_int

    parser = subparsers.add_parser(
        "import-bop",
        help="import one part of a BOP dataset (real RGB-D recordings with poses) as a don_gym dataset",
        description=(
            "Read a BOP scene-wise dataset (models/obj_NNNNNN.ply in mm, models_info.json, SPLIT/NNNNNN/ with "
            "scene_camera.json, scene_gt.json, rgb/ or gray/, depth/, optional mask_visib/) and write a don_gym "
            "dataset for one part: RGB, depth in metres, the part's masks with occlusion by every annotated "
            "object, descriptor targets from the ground-truth poses and rendered depth for the self-supervised "
            "method. 'don-gym train' and 'don-gym evaluate' then run on it. Format: docs/dataset_format.md."
        ),
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    parser.add_argument("root", help="BOP dataset directory (holds models/ and the split directories)")
    parser.add_argument("--split", required=True, help="split directory under ROOT, e.g. train_pbr, test")
    parser.add_argument("--object", type=positive_int, required=True, help="BOP object id (obj_id) of the part")
    parser.add_argument("--out", required=True, help="output dataset directory (new or empty)")
    parser.add_argument("--scenes", type=int, nargs="+", help="BOP scene ids to import; default all")
    parser.add_argument(
        "--models-dir", default="models", help="folder under ROOT with obj_NNNNNN.ply and models_info.json"
    )
    parser.add_argument("--dim", type=positive_int, default=3, help="descriptor dimension D")
    parser.add_argument("--no-symmetry", action="store_true", help="plain Laplacian Eigenmaps (no GISIF merging)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing dataset at --out")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from don_gym.data.import_bop import import_bop
    from don_gym.io import check_output_dir

    check_output_dir(args.out, "--out")
    result = import_bop(
        args.root,
        args.split,
        args.object,
        args.out,
        scenes=args.scenes,
        descriptor_dim=args.dim,
        symmetric=not args.no_symmetry,
        overwrite=args.overwrite,
        models_dir=args.models_dir,
    )
    for note in result.notes:
        print(f"note: {note}")
    print(f"wrote {result.out}: {result.scenes} scenes, {result.frames} frames of object {args.object}")
    return 0
