"""``don-gym embed``: optimal descriptors of a mesh, saved as .npz and/or drawn as a picture."""

from __future__ import annotations

import argparse

DESCRIPTION = """\
Compute the optimal dense descriptors of an object (Kupcsik et al., AAAI 2021): the Laplacian
Eigenmap of its mesh, where repeated eigenvalues of a symmetric part are merged (sum of squares of
their eigenvectors, GISIF) so that points that the symmetry maps onto each other get the same
descriptor. Each dimension is normalised to [0, 1]; the background descriptor is the point of the
unit cube furthest from all object descriptors.

MESH_OR_NAME is a built-in part (toolcap, shaft) or a mesh file trimesh reads (STL, OBJ, PLY, OFF,
GLB, ...). Files larger than 1 m are taken to be in millimetres unless --scale is given.
"""

EPILOG = """\
examples:
  don-gym embed toolcap --plot toolcap_descriptors.png
  don-gym embed part.stl --scale 0.001 --dim 3 --out part_descriptors.npz
  don-gym embed bunny.obj --no-symmetry --plot bunny.png

The .npz holds vertex_descriptors (N, dim), eigenvalues, background and metadata (groups, mesh
hash, field hash); read it with don_gym.descriptors.DescriptorField.load.
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "embed",
        help="optimal descriptors of a mesh (Laplacian Eigenmaps with symmetry)",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("mesh", metavar="MESH_OR_NAME", help="built-in name (toolcap, shaft) or mesh file path")
    parser.add_argument("--dim", type=int, default=3, help="number of descriptor dimensions (default: 3)")
    parser.add_argument(
        "--no-symmetry",
        dest="symmetric",
        action="store_false",
        help="plain Laplacian Eigenmaps: do not merge repeated eigenvalues (symmetric points then get "
        "different, basis-dependent descriptors)",
    )
    parser.add_argument(
        "--tolerance",
        type=float,
        default=None,
        help="relative tolerance under which consecutive eigenvalues count as equal (default: 0.01)",
    )
    parser.add_argument(
        "--scale",
        type=float,
        default=None,
        help="factor from file units to metres, e.g. 0.001 for millimetres (default: auto, see above)",
    )
    parser.add_argument(
        "--components",
        choices=("error", "largest"),
        default="error",
        help="a mesh in several pieces: 'error' (default) stops; 'largest' embeds the largest piece and "
        "gives every other vertex the descriptor of the nearest vertex of that piece",
    )
    parser.add_argument(
        "--method",
        choices=("auto", "direct", "multilevel"),
        default="auto",
        help="eigensolver: 'direct' solves on the whole mesh (robust Laplacian, shift-invert Lanczos); "
        "'multilevel' solves on a coarsened mesh and refines the eigenvectors on the full mesh (LOBPCG); "
        "'auto' (default): direct below 10000 vertices, multilevel above (how close and how fast: "
        "benchmarks/RESULTS.md)",
    )
    parser.add_argument("--out", metavar="FIELD.npz", default=None, help="write the descriptor field to this .npz")
    parser.add_argument(
        "--plot",
        metavar="PICTURE.png",
        default=None,
        help="draw the mesh coloured by each dimension (hot colour map) and by the RGB composite (.png/.pdf/.svg)",
    )
    parser.add_argument(
        "--view",
        nargs=2,
        type=float,
        metavar=("ELEV", "AZIM"),
        action="append",
        default=None,
        help="camera elevation and azimuth in degrees for --plot (z up); repeat for more rows "
        "(default: 25 -60 and -25 120)",
    )
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    import time

    from don_gym.descriptors import DEFAULT_TOLERANCE, embed
    from don_gym.errors import MeshError, SeveralPiecesError
    from don_gym.io import check_output_file
    from don_gym.objects import load_object
    from don_gym.plotting import DEFAULT_VIEWS, PLOT_SUFFIXES, plot_descriptor_field

    # Check outputs before the work, so that a typo or a read-only folder does not cost the computation.
    if args.out is not None:
        check_output_file(args.out, "--out", (".npz",))
    if args.plot is not None:
        check_output_file(args.plot, "--plot", tuple(PLOT_SUFFIXES))

    obj = load_object(args.mesh, scale=args.scale)
    tolerance = DEFAULT_TOLERANCE if args.tolerance is None else args.tolerance
    start = time.perf_counter()
    try:
        field = embed(
            obj, args.dim, args.symmetric, tolerance=tolerance, components=args.components, method=args.method
        )
    except SeveralPiecesError as exc:
        raise MeshError(f"{args.mesh}: {exc.detail}; pass --components largest to embed the largest one only") from exc
    seconds = time.perf_counter() - start

    mesh = obj.mesh
    print(f"object:      {obj.name} ({obj.source}), {len(mesh.vertices)} vertices, {len(mesh.faces)} faces")
    if field.embedded_vertices < len(mesh.vertices):
        print(f"             embedded the largest component: {field.embedded_vertices} vertices")
    unit = "1/m^2"
    print(f"eigenvalues: {', '.join(f'{v:.6g}' for v in field.eigenvalues)} ({unit}; constant one excluded)")
    parts = []
    for d, group in enumerate(field.groups):
        members = "+".join(str(i + 1) for i in group)
        parts.append(f"d{d + 1} = eigenvector {members}" if len(group) == 1 else f"d{d + 1} = sum of squares {members}")
    print(f"groups:      {'; '.join(parts)}" + ("" if field.symmetric else " (no symmetry merging)"))
    print(f"background:  [{', '.join(f'{v:.3f}' for v in field.background)}]")
    print(f"field hash:  {field.field_hash} (mesh {field.mesh_hash}); solver {field.solver}, {seconds:.2f} s")
    if args.out is not None:
        print(f"wrote {field.save(args.out)}")
    if args.plot is not None:
        labels = []
        for d, group in enumerate(field.groups):
            members = "+".join(str(i + 1) for i in group)
            labels.append(f"d{d + 1}: " + (f"eigvec {members}" if len(group) == 1 else f"sum sq. {members}"))
        mode = "symmetric (GISIF)" if field.symmetric else "plain Laplacian Eigenmaps"
        title = f"{obj.name}: optimal descriptors, {mode}, {len(mesh.vertices)} vertices"
        views = [tuple(v) for v in args.view] if args.view else DEFAULT_VIEWS
        path = plot_descriptor_field(
            mesh, field.vertex_descriptors, args.plot, title=title, dimension_labels=labels, views=views
        )
        print(f"wrote {path}")
    return 0
