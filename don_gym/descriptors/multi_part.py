"""One descriptor space for several parts (:class:`PartSpace`, :func:`build_part_space`).

Each part's optimal descriptors (:class:`~don_gym.descriptors.DescriptorField`, every dimension in
[0, 1]) are mapped by a uniform scale and a shift into a cube of their own inside the unit cube, the
cubes at least ``gap`` apart, and the background descriptor put on a corner of the unit cube at least
``gap`` from every cube. The ``"identity"`` layout instead keeps every part's field whole and appends
one dimension that says which part a descriptor is on. The constructions, the separation they guarantee
and what they cost are in docs/background.md, "Several parts in one descriptor space".
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from don_gym.descriptors.embed import background_descriptor
from don_gym.descriptors.field import DescriptorField
from don_gym.errors import DonGymError
from don_gym.objects import ObjectModel, ShapeSignature

#: Default gap between two parts' regions, and between a region and the background (descriptor
#: units; the unit cube has side 1). A modelling choice: a quarter of the cube's side, which leaves two
#: parts in D = 3 dimensions 43% of their single-part scale and three or four parts 41%.
DEFAULT_PART_GAP = 0.25
#: Newest version of :meth:`PartSpace.to_dict`'s record that :meth:`PartSpace.from_dict` reads. Version 2 adds
#: ``field_dim`` (the parts' own fields' D, one less than the space's with the ``"identity"`` layout); a space
#: whose fields have the space's D is written as version 1, as before version 2 existed.
PART_SPACE_FORMAT = 2
#: Layouts of a :class:`PartSpace` (docs/background.md, "Several parts in one descriptor space"):
#: :func:`build_part_space` chooses among the first three (``layout="auto"``); ``"identity"`` is asked for.
LAYOUTS = ("single", "corners", "grid", "identity")
#: The layout that appends one part-identity dimension to the parts' own fields.
IDENTITY_LAYOUT = "identity"
#: Values of :func:`build_part_space`'s ``layout`` argument.
LAYOUT_CHOICES = ("auto", IDENTITY_LAYOUT)
#: The layout a bin dataset stored its targets in (``part_space.json``: ``"corners"`` or ``"grid"``).
DATASET_LAYOUT = "dataset"
#: Layouts a supervised network of several parts can learn (:func:`training_layout`).
TRAINING_LAYOUT_CHOICES = ("auto", IDENTITY_LAYOUT, DATASET_LAYOUT)


@dataclass(frozen=True)
class PartRegion:
    """One part's identity and where its descriptors lie in a :class:`PartSpace`.

    Attributes:
        name: the part's name (:func:`don_gym.objects.part_name`).
        signature: the part's :class:`~don_gym.objects.ShapeSignature`, or None when not known.
        scale: factor applied to the part's own descriptors in the separated dimensions (0 < scale <= 1).
        offset: (D,) shift added after scaling, in the space's D dimensions; 0 in the mask dimension, which
            passes through unchanged; with the ``"identity"`` layout, the part's identity coordinate last.
    """

    name: str
    signature: ShapeSignature | None
    scale: float
    offset: np.ndarray

    def __post_init__(self) -> None:
        offset = np.array(self.offset, dtype=np.float64, copy=True)
        offset.setflags(write=False)
        object.__setattr__(self, "offset", offset)


@dataclass(frozen=True, eq=False)
class PartSpace:
    """A descriptor space shared by several parts: every part's region and the background.

    Part ``i``'s descriptor ``d`` (its own field's value, in [0, 1]^F, F = :attr:`field_dim`) is
    ``scale_i * d + offset_i`` in the separated dimensions (all but ``mask_dim``) and ``d`` unchanged in
    ``mask_dim``. Its region is the image of the unit cube, the box ``[offset_i, offset_i + scale_i]`` in the
    separated dimensions. With the ``"identity"`` layout the space has one dimension more than the fields
    (D = F + 1): the fields' F dimensions come first, each part's at scale 1, and the last holds
    ``offset_i``'s last entry, the part's identity coordinate, for every descriptor of part ``i``.

    Attributes:
        parts: one :class:`PartRegion` per part, in the order given to :func:`build_part_space`; a
            part's index here plus 1 is its label in part images (0 = background).
        background: (D,) float32 descriptor of pixels off every part.
        gap: the separation guaranteed between regions and from the background (descriptor units).
        layout: ``"single"``, ``"corners"``, ``"grid"`` or ``"identity"`` (:data:`LAYOUTS`).
        mask_dim: the dimension the ``"mask"`` target variant replaces, left out of the separation; None
            when every dimension is separated.
    """

    parts: tuple[PartRegion, ...]
    background: np.ndarray
    gap: float
    layout: str
    mask_dim: int | None

    def __post_init__(self) -> None:
        background = np.array(self.background, dtype=np.float32, copy=True)
        background.setflags(write=False)
        object.__setattr__(self, "background", background)

    @property
    def dim(self) -> int:
        """D, the number of descriptor dimensions of the space (a network trained in it outputs D channels)."""
        return int(self.background.shape[0])

    @property
    def field_dim(self) -> int:
        """F, the number of dimensions of the parts' own fields: D, or D - 1 with the ``"identity"`` layout."""
        return self.dim - 1 if self.layout == IDENTITY_LAYOUT else self.dim

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(part.name for part in self.parts)

    @property
    def separated_dims(self) -> np.ndarray:
        """Indices of the dimensions the regions are separated in (all but ``mask_dim``)."""
        dims = np.arange(self.dim)
        return dims if self.mask_dim is None else np.delete(dims, self.mask_dim)

    def index(self, part: int | str) -> int:
        """Index into :attr:`parts` of a part given by index or name; DonGymError naming it if absent."""
        if isinstance(part, str):
            if part not in self.names:
                raise DonGymError(f"part {part!r} is not in this descriptor space; it holds {list(self.names)}")
            return self.names.index(part)
        if isinstance(part, (bool, np.bool_)) or not isinstance(part, (int, np.integer)):
            raise DonGymError(f"part: expected a part name or index, got {type(part).__name__}")
        if not 0 <= part < len(self.parts):
            raise DonGymError(f"part index {part} is outside 0..{len(self.parts) - 1}")
        return int(part)

    def region_bounds(self, part: int | str) -> tuple[np.ndarray, np.ndarray]:
        """``(low, high)``, (D,) each: the box holding every descriptor of ``part`` in this space (the
        mask dimension spans [0, 1]; the identity dimension is the part's identity coordinate alone)."""
        region = self.parts[self.index(part)]
        low = np.zeros(self.dim)
        high = np.ones(self.dim)
        dims = self.separated_dims
        # The unit cube's extent per dimension of the space: 0 along dimensions the fields do not have.
        extent = (np.arange(self.dim) < self.field_dim).astype(np.float64)
        low[dims] = region.offset[dims]
        high[dims] = region.offset[dims] + region.scale * extent[dims]
        return low, high

    def map_descriptors(self, part: int | str, descriptors: np.ndarray) -> np.ndarray:
        """A part's own descriptors moved into its region.

        Args:
            part: name or index of the part.
            descriptors: (..., F) values of the part's own field (F = :attr:`field_dim`; e.g. its (N, F)
                vertex descriptors or an (H, W, F) image rendered from them), in [0, 1].

        Returns:
            (..., D) float32. The map is affine, so it commutes with the barycentric interpolation of
            rendering: mapping a rendered image equals rendering the mapped field.
        """
        region = self.parts[self.index(part)]
        values = np.asarray(descriptors, dtype=np.float64)
        if values.ndim < 1 or values.shape[-1] != self.field_dim:
            raise DonGymError(
                f"descriptors of part {region.name!r}: expected (..., {self.field_dim}), got {values.shape}"
            )
        if self.field_dim == self.dim:
            mapped = values.copy()
        else:  # the identity dimension: 0 before the shift, so the part's identity coordinate after it
            mapped = np.zeros((*values.shape[:-1], self.dim))
            mapped[..., : self.field_dim] = values
        dims = self.separated_dims
        mapped[..., dims] = region.scale * mapped[..., dims] + region.offset[dims]
        return mapped.astype(np.float32)

    def own_descriptors(self, part: int | str, descriptors: np.ndarray) -> np.ndarray:
        """The inverse of :meth:`map_descriptors`: (..., D) descriptors of ``part`` in this space back to
        (..., F) values of its own field, float64 (not clipped: values off the part's region map outside
        [0, 1])."""
        region = self.parts[self.index(part)]
        values = np.array(descriptors, dtype=np.float64)
        if values.ndim < 1 or values.shape[-1] != self.dim:
            raise DonGymError(f"descriptors of part {region.name!r}: expected (..., {self.dim}), got {values.shape}")
        dims = self.separated_dims
        values[..., dims] = (values[..., dims] - region.offset[dims]) / region.scale
        return values[..., : self.field_dim]

    def map_descriptor_image(self, descriptor_image: np.ndarray, part_image: np.ndarray) -> np.ndarray:
        """Pixels of several parts' own descriptors moved into their regions, background elsewhere.

        Args:
            descriptor_image: (H, W, F) each pixel holding the descriptor of its part's own field
                (F = :attr:`field_dim`).
            part_image: (H, W) int, the part's index in :attr:`parts` plus 1 per pixel; 0 = background.

        Returns:
            (H, W, D) float32: :meth:`map_descriptors` of each pixel's part, :attr:`background` where
            ``part_image`` is 0.
        """
        image = np.asarray(descriptor_image)
        labels = np.asarray(part_image)
        if image.ndim != 3 or image.shape[2] != self.field_dim:
            raise DonGymError(f"descriptor_image: expected (H, W, {self.field_dim}), got shape {image.shape}")
        if labels.shape != image.shape[:2] or not np.issubdtype(labels.dtype, np.integer):
            raise DonGymError(f"part_image: expected integer labels of shape {image.shape[:2]}, got {labels.shape}")
        if labels.size and (labels.min() < 0 or labels.max() > len(self.parts)):
            raise DonGymError(f"part_image: labels must lie in 0..{len(self.parts)} (0 = background)")
        out = np.empty((*image.shape[:2], self.dim), dtype=np.float32)
        out[:] = self.background
        for i in range(len(self.parts)):
            on = labels == i + 1
            if on.any():
                out[on] = self.map_descriptors(i, image[on])
        return out

    def part_image(self, instance_ids: np.ndarray, instance_parts: Mapping[int, int | str]) -> np.ndarray:
        """Per-pixel part labels of an instance id image, for :meth:`map_descriptor_image`.

        Args:
            instance_ids: (H, W) int, the instance seen at each pixel, 0 = none (e.g.
                ``RenderedInstances.instance_ids`` or a dataset's instance image).
            instance_parts: the part (name or index) of every instance id that occurs.

        Returns:
            (H, W) int32, the part's index in :attr:`parts` plus 1, 0 where ``instance_ids`` is 0.
        """
        ids = np.asarray(instance_ids)
        if ids.ndim != 2 or not np.issubdtype(ids.dtype, np.integer):
            raise DonGymError(f"instance_ids: expected an (H, W) integer image, got {ids.dtype} {ids.shape}")
        labels = np.zeros(ids.shape, dtype=np.int32)
        for instance in np.unique(ids[ids != 0]):
            if int(instance) not in instance_parts:
                raise DonGymError(f"instance {int(instance)} is in the image but not in instance_parts")
            labels[ids == instance] = self.index(instance_parts[int(instance)]) + 1
        return labels

    def region_distances(self) -> tuple[np.ndarray, np.ndarray]:
        """Euclidean distances in the separated dimensions: ``(between, to_background)``.

        ``between`` (K, K): between the regions of parts i and j (0 on the diagonal); ``to_background``
        (K,): from the background to each region. With two or more parts every off-diagonal entry and
        every background distance is at least :attr:`gap` (docs/background.md).
        """
        dims = self.separated_dims
        lows, highs = zip(*(self.region_bounds(i) for i in range(len(self.parts))), strict=True)
        low, high = np.array(lows)[:, dims], np.array(highs)[:, dims]
        # Per axis, the gap between two intervals is how far one starts after the other ends.
        axis_gap = np.maximum(0.0, np.maximum(low[:, None] - high[None], low[None] - high[:, None]))
        between = np.linalg.norm(axis_gap, axis=-1)
        point = self.background.astype(np.float64)[dims]
        to_background = np.linalg.norm(np.maximum(0.0, np.maximum(low - point, point - high)), axis=-1)
        return between, to_background

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready record of the space (for a checkpoint's metadata); :meth:`from_dict` reads it. A space
        whose fields have its own D is written in format 1, byte for byte as before format 2 existed; the
        ``"identity"`` layout in format 2, which adds ``field_dim``."""
        extra = {} if self.field_dim == self.dim else {"field_dim": self.field_dim}
        return {
            "format": 1 if not extra else PART_SPACE_FORMAT,
            **extra,
            "layout": self.layout,
            "gap": float(self.gap),
            "mask_dim": self.mask_dim,
            "background": [float(v) for v in self.background],
            "parts": [
                {
                    "name": part.name,
                    "signature": None if part.signature is None else part.signature.to_dict(),
                    "scale": float(part.scale),
                    "offset": [float(v) for v in part.offset],
                }
                for part in self.parts
            ],
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], source: str = "part space") -> PartSpace:
        """Read :meth:`to_dict`'s record; DonGymError naming ``source`` when it is not one."""
        try:
            if data["format"] not in range(1, PART_SPACE_FORMAT + 1) or isinstance(data["format"], bool):
                raise ValueError(f"format {data['format']!r}, expected 1 to {PART_SPACE_FORMAT}")
            background = np.asarray(data["background"], dtype=np.float32)
            parts = tuple(
                PartRegion(
                    name=str(p["name"]),
                    signature=None if p["signature"] is None else ShapeSignature.from_dict(p["signature"], source),
                    scale=float(p["scale"]),
                    offset=np.asarray(p["offset"], dtype=np.float64),
                )
                for p in data["parts"]
            )
            mask_dim = data["mask_dim"]
            space = cls(
                parts, background, float(data["gap"]), str(data["layout"]), None if mask_dim is None else int(mask_dim)
            )
            # Format 1 has no field_dim: its fields have the space's D (no layout then appended a dimension).
            field_dim = int(data["field_dim"]) if data["format"] >= 2 else space.dim
        except (KeyError, TypeError, ValueError) as exc:
            raise DonGymError(f"{source}: not a part space record ({type(exc).__name__}: {exc})") from exc
        problem = _space_problem(space)
        if problem is None and field_dim != space.field_dim:
            problem = (
                f"field_dim {field_dim} with layout {space.layout!r} and D={space.dim}; expected {space.field_dim}"
            )
        if problem:
            raise DonGymError(f"{source}: {problem}")
        return space


def _space_problem(space: PartSpace) -> str | None:
    dim = space.dim
    if space.background.ndim != 1 or dim == 0 or not np.all(np.isfinite(space.background)):
        return f"background has shape {space.background.shape}; expected a finite (D,) descriptor"
    if space.layout not in LAYOUTS:
        return f"layout {space.layout!r}; expected one of {list(LAYOUTS)}"
    if not space.parts:
        return "no parts"
    if len(set(space.names)) != len(space.names):
        return f"part names {list(space.names)} repeat"
    if space.mask_dim is not None and not 0 <= space.mask_dim < dim:
        return f"mask_dim {space.mask_dim} is outside 0..{dim - 1}"
    for part in space.parts:
        if part.offset.shape != (dim,) or not (0 < part.scale <= 1) or not np.all(np.isfinite(part.offset)):
            return (
                f"part {part.name!r} has scale {part.scale} and offset shape {part.offset.shape}; "
                f"expected a scale in (0, 1] and a finite ({dim},) offset"
            )
    if space.layout == IDENTITY_LAYOUT:
        if dim < 2 or space.mask_dim is not None:
            return f"layout 'identity' with D={dim} and mask_dim {space.mask_dim}; expected D >= 2 and no mask_dim"
        if any(part.scale != 1 or np.any(part.offset[:-1] != 0) for part in space.parts):
            return "layout 'identity' needs every part at scale 1 with offset 0 in the field's dimensions"
    return None


def _check_gap(gap: float) -> float:
    if isinstance(gap, bool) or not isinstance(gap, (int, float, np.floating, np.integer)):
        raise DonGymError(f"gap={gap!r}: expected a number of descriptor units in (0, 1)")
    gap = float(gap)
    if not (math.isfinite(gap) and 0 < gap < 1):
        raise DonGymError(f"gap={gap!r}: expected a number of descriptor units in (0, 1)")
    return gap


def _corner_layout(n_parts: int, dims: int) -> tuple[np.ndarray, np.ndarray, int, int] | None:
    """Corners of the unit cube for the parts and the background: ``(part_codes (K, L) 0/1, background
    code (L,), h, h_background)``, h = the least number of axes in which two part codes differ,
    h_background the least in which the background's code differs from a part's; None when K parts
    and the background do not fit on the 2^L corners."""
    if n_parts + 1 > 2**dims:
        return None
    corners = (np.arange(2**dims)[:, None] >> np.arange(dims)[::-1]) & 1
    weight = corners.sum(axis=1)
    if n_parts == 2:  # opposite corners differ in every axis
        codes, h = corners[[0, -1]], dims
    elif dims >= 2 and n_parts <= 2 ** (dims - 1):  # corners of even weight differ in at least 2 axes
        codes, h = corners[weight % 2 == 0][:n_parts], 2
    else:
        codes, h = corners[:n_parts], 1
    used = {tuple(c) for c in codes}
    free = np.array([c for c in corners if tuple(c) not in used])
    hamming = (free[:, None, :] != codes[None]).sum(axis=-1).min(axis=1)
    # The free corner furthest from every part; ties go to the one of largest weight (all ones first).
    best = np.lexsort((-free.sum(axis=1), -hamming))[0]
    return codes, free[best], h, int(hamming[best])


def _as_part_inputs(
    names: Sequence[str], fields: Sequence[np.ndarray], signatures: Sequence[ShapeSignature | None] | None
) -> tuple[list[str], list[np.ndarray], list[ShapeSignature | None]]:
    if isinstance(names, str) or len(names) == 0:
        raise DonGymError("parts: expected at least one part (a list of names with one field each), got none")
    names = list(names)
    for name in names:
        if not isinstance(name, str) or not name:
            raise DonGymError(f"part name {name!r}: expected a non-empty string")
    repeated = sorted({name for name in names if names.count(name) > 1})
    if repeated:
        raise DonGymError(f"part name {repeated[0]!r} is given more than once; each part must appear once")
    if len(fields) != len(names):
        raise DonGymError(f"fields: {len(fields)} given for {len(names)} parts {names}; expected one per part")
    if signatures is None:
        signatures = [None] * len(names)
    elif len(signatures) != len(names):
        raise DonGymError(f"signatures: {len(signatures)} given for {len(names)} parts; expected one per part")
    arrays = []
    for name, field in zip(names, fields, strict=True):
        values = np.asarray(field, dtype=np.float64)
        if values.ndim != 2 or values.shape[0] == 0 or values.shape[1] == 0:
            raise DonGymError(f"field of part {name!r}: expected (N, D) vertex descriptors, got shape {values.shape}")
        if not np.all(np.isfinite(values)) or values.min() < 0 or values.max() > 1:
            raise DonGymError(f"field of part {name!r}: descriptors must be finite and within [0, 1]")
        arrays.append(values)
    dims = {a.shape[1] for a in arrays}
    if len(dims) > 1:
        listing = ", ".join(f"{n!r}: D={a.shape[1]}" for n, a in zip(names, arrays, strict=True))
        raise DonGymError(f"fields have different descriptor dimensions ({listing}); expected one D for all parts")
    for signature, name in zip(signatures, names, strict=True):
        if signature is not None and not isinstance(signature, ShapeSignature):
            raise DonGymError(f"signature of part {name!r}: expected a ShapeSignature or None")
    return names, arrays, list(signatures)


def build_part_space(
    names: Sequence[str],
    fields: Sequence[np.ndarray],
    signatures: Sequence[ShapeSignature | None] | None = None,
    gap: float = DEFAULT_PART_GAP,
    mask_dim: int | None = None,
    layout: str = "auto",
) -> PartSpace:
    """Lay several parts' descriptors out in one space, each in a region of its own.

    With K >= 2 parts, part i's descriptors are ``s * d + offset_i`` in the L separated dimensions (all
    but ``mask_dim``), the same scale ``s`` for every part, so each part keeps its field's shape with
    every distance multiplied by ``s``. Guarantees (:meth:`PartSpace.region_distances`): the regions of
    two parts are at least ``gap`` apart, and the background is at least ``gap`` from every region. The
    layout (docs/background.md, "Several parts in one descriptor space"):

    - ``"corners"`` when K + 1 <= 2^L: cubes of side ``s = (1 - gap / sqrt(h)) / 2`` in corners of the
      unit cube whose codes differ in at least h axes (h = L for two parts, 2 for up to 2^(L-1) parts,
      else 1), the background on a free corner (differing from every part's in at least h_b axes;
      ``s`` is at most ``1 - gap / sqrt(h_b)``, which binds only for gaps above about 0.7);
    - ``"grid"`` otherwise: m^L cells, m the least with m^L >= K + 1, ``s = (1 - (m - 1) gap) / m``, the
      background on the corner of the last cell.

    One part (K = 1) gets the single-part space unchanged: scale 1 and its own background (the point
    of the unit cube furthest from its descriptors), so a one-part network is trained as before.

    ``layout="identity"`` (K >= 2, no ``mask_dim``) keeps every part's field whole instead: scale 1 and
    offset 0 in the fields' D dimensions, and one dimension appended (the space has D + 1) holding the
    part's identity, ``(i + 1) / K`` for part i and 0 for the background, whose other coordinates are the
    point of the unit cube furthest from every part's descriptors. Two parts' regions are then at least
    1/K apart and the background at least 1/K from every region; 1/K below ``gap`` is refused.

    Args:
        names: K distinct part names (:attr:`don_gym.objects.ObjectModel.name`).
        fields: K arrays (N_i, D) of each part's own optimal vertex descriptors in [0, 1], one D for all.
        signatures: K :class:`~don_gym.objects.ShapeSignature` (or None) recorded as the parts' identity.
        gap: guaranteed separation in descriptor units, in (0, 1).
        mask_dim: the dimension the ``"mask"`` target variant replaces by the mask channel; it is left
            out of the separation (passed through unchanged, 0 in the background), as only the other
            dimensions tell parts apart in that variant. None: separate in all D dimensions.
        layout: ``"auto"`` (``"single"``, ``"corners"`` or ``"grid"``, as above) or ``"identity"``
            (:data:`LAYOUT_CHOICES`).

    Returns:
        A :class:`PartSpace`.
    """
    if layout not in LAYOUT_CHOICES:
        raise DonGymError(f"layout={layout!r}: expected one of {list(LAYOUT_CHOICES)}")
    names, arrays, signatures = _as_part_inputs(names, fields, signatures)
    gap = _check_gap(gap)
    if layout == IDENTITY_LAYOUT:
        return _identity_space(names, arrays, signatures, gap, mask_dim)
    dim = arrays[0].shape[1]
    if mask_dim is not None:
        if isinstance(mask_dim, bool) or not isinstance(mask_dim, (int, np.integer)) or not -dim <= mask_dim < dim:
            raise DonGymError(f"mask_dim={mask_dim!r}: expected a dimension index in [{-dim}, {dim - 1}] or None")
        if dim < 2:
            raise DonGymError(f"mask_dim={mask_dim}: the fields have D={dim}; the mask variant needs D >= 2")
        mask_dim = int(mask_dim) % dim
    separated = np.arange(dim) if mask_dim is None else np.delete(np.arange(dim), mask_dim)
    n_dims, n_parts = len(separated), len(names)

    def full_offset(offset: np.ndarray) -> np.ndarray:
        out = np.zeros(dim)
        out[separated] = offset
        return out

    background = np.zeros(dim, dtype=np.float32)
    if n_parts == 1:
        background[separated] = background_descriptor(arrays[0][:, separated])
        regions = [PartRegion(names[0], signatures[0], 1.0, np.zeros(dim))]
        return PartSpace(tuple(regions), background, gap, "single", mask_dim)

    corners = _corner_layout(n_parts, n_dims)
    if corners is not None:
        codes, background_code, h, h_background = corners
        if gap >= math.sqrt(h):
            raise DonGymError(f"gap={gap}: {n_parts} parts in {n_dims} dimensions need a gap below {math.sqrt(h):.3f}")
        # Cubes in corners differing in h axes are sqrt(h) (1 - 2 s) apart; the background corner is
        # sqrt(h_background) (1 - s) from the nearest cube, which binds only for gaps above ~0.7.
        scale = min((1.0 - gap / math.sqrt(h)) / 2.0, 1.0 - gap / math.sqrt(h_background))
        offsets = codes * (1.0 - scale)
        background[separated] = background_code
        layout = "corners"
    else:
        cells = 3
        while cells**n_dims < n_parts + 1:
            cells += 1
        if (cells - 1) * gap >= 1:
            raise DonGymError(
                f"gap={gap}: {n_parts} parts in {n_dims} dimensions take a grid of {cells} cells per axis, "
                f"which needs a gap below {1 / (cells - 1):.3f}"
            )
        scale = (1.0 - (cells - 1) * gap) / cells
        index = (np.arange(n_parts)[:, None] // cells ** np.arange(n_dims)[::-1]) % cells
        offsets = index * (scale + gap)
        background[separated] = 1.0  # the corner of the last cell, which no part takes
        layout = "grid"
    regions = [
        PartRegion(name, signature, scale, full_offset(offset))
        for name, signature, offset in zip(names, signatures, offsets, strict=True)
    ]
    return PartSpace(tuple(regions), background, gap, layout, mask_dim)


def _identity_refusal(names: Sequence[str], gap: float, mask_dim: int | None) -> str | None:
    """Why the ``"identity"`` layout does not apply to parts ``names`` with ``gap`` and ``mask_dim``, or None."""
    n_parts = len(names)
    if mask_dim is not None:
        return (
            f"layout='identity' with mask_dim={mask_dim}: the mask variant is not supported with the identity "
            "layout; use layout='auto'"
        )
    if n_parts < 2:
        return (
            f"layout='identity' needs at least 2 parts, got {n_parts} ({names[0]!r}); a single part keeps its "
            "own space (layout='auto')"
        )
    if 1.0 / n_parts < gap:
        return (
            f"layout='identity': {n_parts} parts are 1/K = {1.0 / n_parts:.3f} apart along the identity "
            f"dimension, less than gap={gap}; at most {math.floor(1.0 / gap + 1e-9)} parts fit with this gap"
        )
    return None


def _identity_space(
    names: list[str],
    arrays: list[np.ndarray],
    signatures: list[ShapeSignature | None],
    gap: float,
    mask_dim: int | None,
) -> PartSpace:
    """:func:`build_part_space`'s ``"identity"`` layout, for checked inputs."""
    refusal = _identity_refusal(names, gap, mask_dim)
    if refusal is not None:
        raise DonGymError(refusal)
    n_parts, dim = len(names), arrays[0].shape[1]
    background = np.zeros(dim + 1, dtype=np.float32)
    # Identity 0 already keeps the background 1/K from every part; in the fields' dimensions it is put where
    # a single part's background is, furthest from every part's descriptors, for what margin that adds.
    background[:dim] = background_descriptor(np.concatenate(arrays))
    regions = [
        PartRegion(name, signature, 1.0, np.r_[np.zeros(dim), (k + 1) / n_parts])
        for k, (name, signature) in enumerate(zip(names, signatures, strict=True))
    ]
    return PartSpace(tuple(regions), background, gap, IDENTITY_LAYOUT, None)


def training_layout(layout: str, names: Sequence[str], gap: float, mask_variant: bool) -> str:
    """The layout a supervised network of the parts ``names`` learns for a requested ``layout``
    (:data:`TRAINING_LAYOUT_CHOICES`): ``"identity"`` or ``"dataset"``.

    ``"auto"`` is ``"identity"`` wherever :func:`build_part_space` would build it (two parts or more, not the mask
    variant, whose mask channel would replace a descriptor dimension, and ``1 / K >= gap``, the separation the
    identity coordinate guarantees), else ``"dataset"``: every part's whole field keeps its descriptors as far
    apart as a single-part network's, against about 0.43 of that for two parts shrunk into corners
    (docs/background.md, "Several parts in one descriptor space"). An explicit layout is returned as asked;
    whether it fits is checked where the space is built.
    """
    if layout not in TRAINING_LAYOUT_CHOICES:
        raise DonGymError(f"part layout {layout!r} is unknown; expected one of {list(TRAINING_LAYOUT_CHOICES)}")
    if layout != "auto":
        return layout
    fits = _identity_refusal(names, gap, -1 if mask_variant else None) is None
    return IDENTITY_LAYOUT if fits else DATASET_LAYOUT


def part_space_for(
    models: Sequence[ObjectModel],
    fields: Sequence[DescriptorField],
    gap: float = DEFAULT_PART_GAP,
    mask_dim: int | None = None,
    layout: str = "auto",
) -> PartSpace:
    """:func:`build_part_space` for object models and their fields: names and shape signatures from
    the models, vertex descriptors from the fields (checked to be each model's, by mesh hash)."""
    if len(models) != len(fields):
        raise DonGymError(f"fields: {len(fields)} given for {len(models)} parts; expected one per part")
    for model, field in zip(models, fields, strict=True):
        if not isinstance(model, ObjectModel) or not isinstance(field, DescriptorField):
            raise DonGymError("part_space_for: expected ObjectModel parts and DescriptorField fields")
        if model.mesh_hash and field.mesh_hash != model.mesh_hash:
            raise DonGymError(
                f"field for part {model.name!r} is of mesh {field.mesh_hash}, but the part's mesh is {model.mesh_hash}"
            )
    return build_part_space(
        [m.name for m in models],
        [f.vertex_descriptors for f in fields],
        [m.shape_signature for m in models],
        gap=gap,
        mask_dim=mask_dim,
        layout=layout,
    )
