"""``don-gym export``: write dataset scenes in another project's layout."""

from __future__ import annotations

import argparse


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "export",
        help="export dataset scenes in the original Dense Object Nets (pdc) layout or as a BOP dataset",
        description=(
            "Write scenes of a don_gym dataset in the layout of the original Dense Object Nets code "
            "(--format pdc: processed/images/*_rgb.png, *_depth.png, image_masks/, pose_data.yaml, "
            "camera_info.yaml), so that its loaders read our data, or as a BOP scene-wise dataset (--format bop: "
            "models/ in mm with models_info.json, SPLIT/NNNNNN/ with scene_camera.json, scene_gt.json, "
            "scene_gt_info.json, rgb/, depth/, mask/, mask_visib/), which BOP's toolkit reads."
        ),
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    parser.add_argument("data", help="dataset directory written by don-gym build-dataset")
    parser.add_argument("--format", default="pdc", choices=["pdc", "bop"], help="target layout")
    parser.add_argument(
        "--split", default="train", choices=["train", "test"], help="BOP split directory to write (--format bop)"
    )
    parser.add_argument("--scene", type=int, action="append", help="scene position to export (repeatable); default all")
    parser.add_argument("--out", required=True, help="output directory")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from don_gym.data.dataset import DONDataset
    from don_gym.data.export import export_scene_pdc
    from don_gym.errors import DatasetError
    from don_gym.io import check_output_dir

    check_output_dir(args.out, "--out")
    dataset = DONDataset(args.data)
    scenes = args.scene if args.scene else range(len(dataset.scenes))
    for scene in scenes:  # all of them before writing any
        if not 0 <= scene < len(dataset.scenes):
            raise DatasetError(
                f"--scene {scene}: no such scene; expected 0..{len(dataset.scenes) - 1}, the positions of the "
                "dataset's complete scenes"
            )
    if args.format == "bop":
        from don_gym.data.export import export_bop

        try:
            written = export_bop(dataset, args.out, split=args.split, scenes=scenes)
        except OSError as exc:
            raise DatasetError(f"{args.out}: {exc}") from exc
        ids = ", ".join(f"{name} = obj_id {obj_id}" for name, obj_id in written.object_ids.items())
        print(f"wrote {written.split_dir} ({len(scenes)} scenes); objects in {args.out}/models: {ids}")
        return 0
    from don_gym.data.export import pdc_scene_dir

    for scene in scenes:  # none exported while another is in the way
        if pdc_scene_dir(args.out, dataset, scene).exists():
            raise DatasetError(
                f"{pdc_scene_dir(args.out, dataset, scene)}: exists; export into another directory or remove it"
            )
    for scene in scenes:
        try:
            path = export_scene_pdc(dataset, scene, args.out)
        except OSError as exc:  # a full disk, no permission: one line, as for the errors of the input
            raise DatasetError(f"{args.out}: {exc}") from exc
        print(f"wrote {path}")
    return 0
