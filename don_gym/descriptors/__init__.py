"""Optimal descriptors of object meshes (Kupcsik et al. 2021): :func:`embed` gives a
:class:`DescriptorField`; background facts are in docs/background.md, "Optimal descriptors"."""

from don_gym.descriptors.eigensolver import DIRECT_MAX_VERTICES, laplacian_eigenpairs
from don_gym.descriptors.embed import (
    CONSTANT_GROUP_RTOL,
    DEFAULT_TOLERANCE,
    background_descriptor,
    descriptor_functions,
    embed,
    group_eigenvalues,
)
from don_gym.descriptors.field import FIELD_MATCH_ATOL, DescriptorField, interpolate_field, mesh_content_hash
from don_gym.descriptors.laplacian import (
    MOLLIFY_FACTOR,
    cotan_laplacian,
    intrinsic_delaunay_laplacian,
    mesh_laplacian,
    normalize_to_unit_area,
)
from don_gym.descriptors.multi_part import DEFAULT_PART_GAP, PartRegion, PartSpace, build_part_space, part_space_for

__all__ = [
    "CONSTANT_GROUP_RTOL",
    "DEFAULT_PART_GAP",
    "DEFAULT_TOLERANCE",
    "DIRECT_MAX_VERTICES",
    "FIELD_MATCH_ATOL",
    "MOLLIFY_FACTOR",
    "DescriptorField",
    "PartRegion",
    "PartSpace",
    "background_descriptor",
    "build_part_space",
    "cotan_laplacian",
    "descriptor_functions",
    "embed",
    "group_eigenvalues",
    "interpolate_field",
    "intrinsic_delaunay_laplacian",
    "laplacian_eigenpairs",
    "mesh_content_hash",
    "mesh_laplacian",
    "normalize_to_unit_area",
    "part_space_for",
]
