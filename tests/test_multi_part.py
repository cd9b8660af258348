"""Tests of several parts in one descriptor space (don_gym.descriptors.multi_part) and of rendering
several instances in one view (don_gym.data.render.MultiPartDescriptorRenderer, make_instances_target)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.distance import pdist
from scipy.spatial.transform import Rotation

from don_gym.data.render import (
    DescriptorRenderer,
    MultiPartDescriptorRenderer,
    make_instances_target,
    make_target,
    mask_background,
    render_instances,
)
from don_gym.descriptors import background_descriptor
from don_gym.descriptors.multi_part import (
    DEFAULT_PART_GAP,
    PartSpace,
    build_part_space,
    part_space_for,
    training_layout,
)
from don_gym.errors import DonGymError
from don_gym.geometry import CameraIntrinsics, make_transform
from don_gym.objects import load_object
from don_gym.perception.descriptor_sources import descriptor_field_for

#: Rounding allowed on the guarantees: box distances are computed in float64, descriptors stored as float32.
BOX_ATOL = 1e-12
DESCRIPTOR_ATOL = 1e-6


@pytest.fixture(scope="module")
def parts():
    """The two symmetric built-ins with their optimal fields."""
    models = [load_object("toolcap"), load_object("shaft")]
    return models, [descriptor_field_for(m) for m in models]


def asymmetric_field(n: int = 300) -> np.ndarray:
    """A field of a part without symmetry: scattered points filling [0, 1]^3, every dimension spanning it."""
    values = np.random.default_rng(7).random((n, 3))
    values[:3] = [[0, 0, 0], [1, 1, 1], [0, 1, 0]]
    return values


def check_separation(space: PartSpace, fields: list[np.ndarray]) -> None:
    """The stated guarantee, on the regions and on the mapped descriptors themselves."""
    gap, dims = space.gap, space.separated_dims
    between, to_background = space.region_distances()
    off_diagonal = between[~np.eye(len(fields), dtype=bool)]
    assert off_diagonal.min() >= gap - BOX_ATOL
    assert to_background.min() >= gap - BOX_ATOL
    mapped = [space.map_descriptors(i, f)[:, dims].astype(np.float64) for i, f in enumerate(fields)]
    for i, points in enumerate(mapped):
        low, high = space.region_bounds(i)
        assert np.all(points >= low[dims] - DESCRIPTOR_ATOL) and np.all(points <= high[dims] + DESCRIPTOR_ATOL)
        nearest_background = np.linalg.norm(points - space.background[dims], axis=1).min()
        assert nearest_background >= gap - DESCRIPTOR_ATOL
        for j in range(i + 1, len(mapped)):
            distance, _ = cKDTree(mapped[j]).query(points)
            assert distance.min() >= gap - DESCRIPTOR_ATOL


@pytest.mark.parametrize("mask_dim", [None, -1])
@pytest.mark.parametrize("count", [2, 3])
def test_parts_and_background_are_apart_by_the_gap(parts, count, mask_dim):
    models, fields = parts
    names = [m.name for m in models] + ["bracket"]
    arrays = [f.vertex_descriptors for f in fields] + [asymmetric_field()]
    space = build_part_space(names[:count], arrays[:count], mask_dim=mask_dim)
    check_separation(space, arrays[:count])
    assert space.layout == "corners" and space.gap == DEFAULT_PART_GAP
    if mask_dim is None:
        # Two parts on opposite corners (h = 3), three on corners differing in two axes.
        h = 3 if count == 2 else 2
        assert space.parts[0].scale == pytest.approx((1 - DEFAULT_PART_GAP / math.sqrt(h)) / 2)
    else:
        assert np.all(space.background[2] == 0)
        assert np.array_equal(space.separated_dims, [0, 1])


@pytest.mark.parametrize("gap", [0.1, 0.3])
@pytest.mark.parametrize("mask_dim", [None, 0])
def test_every_layout_keeps_the_guarantee(gap, mask_dim):
    fields = [np.random.default_rng(k).random((40, 3)) for k in range(12)]
    layouts = set()
    for count in range(2, 13):
        space = build_part_space([f"p{k}" for k in range(count)], fields[:count], gap=gap, mask_dim=mask_dim)
        check_separation(space, fields[:count])
        layouts.add(space.layout)
        assert all(part.scale == space.parts[0].scale for part in space.parts)
    assert layouts == {"corners", "grid"}


@pytest.mark.parametrize("gap", [0.6, 0.8, 0.95])
def test_wide_gaps_keep_the_background_apart_too(gap):
    fields = [np.random.default_rng(k).random((40, 3)) for k in range(7)]
    for count in range(2, 8):
        space = build_part_space([f"p{k}" for k in range(count)], fields[:count], gap=gap)
        assert space.layout == "corners"
        check_separation(space, fields[:count])


def test_a_part_keeps_its_structure_scaled_uniformly(parts):
    models, fields = parts
    space = part_space_for(models, fields)
    assert space.names == ("toolcap", "shaft")
    for i, field in enumerate(fields):
        own = field.vertex_descriptors[::7].astype(np.float64)
        mapped = space.map_descriptors(i, own).astype(np.float64)
        scale = space.parts[i].scale
        np.testing.assert_allclose(pdist(mapped), scale * pdist(own), rtol=0, atol=DESCRIPTOR_ATOL)
        np.testing.assert_allclose(mapped, scale * own + space.parts[i].offset, rtol=0, atol=DESCRIPTOR_ATOL)
    # The mask dimension passes through unchanged; the others are scaled.
    masked = part_space_for(models, fields, mask_dim=-1)
    own = fields[1].vertex_descriptors
    mapped = masked.map_descriptors("shaft", own)
    np.testing.assert_array_equal(mapped[:, 2], own[:, 2])
    np.testing.assert_allclose(
        mapped[:, :2], masked.parts[1].scale * own[:, :2] + masked.parts[1].offset[:2], atol=1e-6
    )


def test_one_part_is_the_single_part_space(parts):
    models, fields = parts
    space = part_space_for(models[:1], fields[:1])
    assert space.layout == "single" and space.parts[0].scale == 1.0
    np.testing.assert_array_equal(space.map_descriptors(0, fields[0].vertex_descriptors), fields[0].vertex_descriptors)
    np.testing.assert_array_equal(space.background, background_descriptor(fields[0].vertex_descriptors))
    np.testing.assert_array_equal(space.background, fields[0].background)
    masked = part_space_for(models[:1], fields[:1], mask_dim=-1)
    np.testing.assert_array_equal(masked.background, mask_background(fields[0].vertex_descriptors))


def test_the_record_keeps_every_parts_identity_and_region(parts):
    models, fields = parts
    space = part_space_for(models, fields, gap=0.3, mask_dim=-1)
    record = json.loads(json.dumps(space.to_dict()))
    back = PartSpace.from_dict(record)
    assert back.names == ("toolcap", "shaft") and back.gap == 0.3 and back.mask_dim == 2
    for a, b, model in zip(space.parts, back.parts, models, strict=True):
        assert b.signature == model.shape_signature and not b.signature.differences(model.shape_signature)
        assert b.scale == a.scale and np.array_equal(b.offset, a.offset)
    np.testing.assert_array_equal(back.background, space.background)
    np.testing.assert_array_equal(
        back.map_descriptors(1, fields[1].vertex_descriptors), space.map_descriptors(1, fields[1].vertex_descriptors)
    )
    for broken, what in [
        ({**record, "format": 99}, "format"),
        ({**record, "parts": []}, "no parts"),
        ({**record, "parts": [record["parts"][0]] * 2}, "repeat"),
        ({k: v for k, v in record.items() if k != "gap"}, "gap"),
    ]:
        with pytest.raises(DonGymError, match=f"checkpoint x.pt.*{what}"):
            PartSpace.from_dict(broken, source="checkpoint x.pt")


def test_bad_input_is_refused_naming_it():
    field = np.random.default_rng(0).random((20, 3))
    with pytest.raises(DonGymError, match="at least one part"):
        build_part_space([], [])
    with pytest.raises(DonGymError, match="'toolcap' is given more than once"):
        build_part_space(["toolcap", "shaft", "toolcap"], [field] * 3)
    with pytest.raises(DonGymError, match="different descriptor dimensions.*'shaft': D=4"):
        build_part_space(["toolcap", "shaft"], [field, np.random.default_rng(1).random((20, 4))])
    with pytest.raises(DonGymError, match="field of part 'shaft'.*within \\[0, 1\\]"):
        build_part_space(["toolcap", "shaft"], [field, field + 1])
    with pytest.raises(DonGymError, match="fields: 1 given for 2 parts"):
        build_part_space(["toolcap", "shaft"], [field])
    for gap in (0, 1.5, float("nan"), "0.2"):
        with pytest.raises(DonGymError, match="gap="):
            build_part_space(["toolcap", "shaft"], [field, field], gap=gap)
    with pytest.raises(DonGymError, match="gap=0.6: 4 parts in 2 dimensions .* below 0.500"):
        build_part_space(["a", "b", "c", "d"], [field] * 4, gap=0.6, mask_dim=0)
    with pytest.raises(DonGymError, match="mask_dim=3"):
        build_part_space(["toolcap", "shaft"], [field, field], mask_dim=3)
    space = build_part_space(["toolcap", "shaft"], [field, field])
    with pytest.raises(DonGymError, match="part 'flange' is not in this descriptor space"):
        space.map_descriptors("flange", field)
    with pytest.raises(DonGymError, match="instance 2 is in the image but not in instance_parts"):
        space.part_image(np.array([[0, 1], [2, 1]]), {1: "shaft"})
    with pytest.raises(DonGymError, match="part_image"):
        space.map_descriptor_image(np.zeros((4, 5, 3)), np.full((4, 5), 3))


# --- rendering several instances ----------------------------------------------------------------------

INTRINSICS = CameraIntrinsics.d435(96, 72)


def pose(euler: tuple[float, float, float], position_m: tuple[float, float, float]) -> np.ndarray:
    return make_transform(Rotation.from_euler("xyz", euler).as_matrix(), position_m)


#: A toolcap seen obliquely at 0.16 m and a shaft lying across it, nearer the camera.
FAR_TOOLCAP = pose((2.2, 0.4, 0.3), (0.004, -0.003, 0.16))
NEAR_SHAFT = pose((1.5, 0.0, 0.5), (0.0, 0.0, 0.12))


@pytest.fixture(scope="module")
def scene(parts):
    models, fields = parts
    space = part_space_for(models, fields)
    meshes = [m.mesh for m in models]
    mapped = [space.map_descriptors(i, f.vertex_descriptors) for i, f in enumerate(fields)]
    renderer = MultiPartDescriptorRenderer(meshes, mapped, space.background)
    singles = [
        DescriptorRenderer(mesh, d, space.background).render(INTRINSICS, T)
        for mesh, d, T in zip(meshes, mapped, [FAR_TOOLCAP, NEAR_SHAFT], strict=True)
    ]
    return space, meshes, mapped, renderer, singles


def test_the_nearer_instance_wins_exactly(scene):
    space, meshes, mapped, renderer, (toolcap, shaft) = scene
    both = toolcap.object_mask & shaft.object_mask
    assert both.sum() > 20 and (toolcap.object_mask & ~shaft.object_mask).sum() > 20
    for order in ([0, 1], [1, 0]):
        poses = [FAR_TOOLCAP, NEAR_SHAFT]
        ids = [10 + k for k in order]
        frame = renderer.render(INTRINSICS, [(k, poses[k]) for k in order], instance_ids=ids)
        toolcap_id, shaft_id = 10, 11
        shaft_in_front = shaft.object_mask & (~toolcap.object_mask | (shaft.depth_m <= toolcap.depth_m))
        toolcap_seen = toolcap.object_mask & ~shaft_in_front
        assert np.all(shaft.depth_m[both] < toolcap.depth_m[both])  # the shaft is in front wherever they overlap
        assert np.array_equal(frame.instance_ids == shaft_id, shaft_in_front)
        assert np.array_equal(frame.instance_ids == toolcap_id, toolcap_seen)
        for single, seen in ((shaft, shaft_in_front), (toolcap, toolcap_seen)):
            assert np.array_equal(frame.descriptor_image[seen], single.descriptor_image[seen])
            assert np.array_equal(frame.depth_m[seen], single.depth_m[seen])
            assert np.array_equal(frame.triangle_ids[seen], single.triangle_ids[seen])
        off = frame.instance_ids == 0
        assert np.array_equal(off, ~(toolcap.object_mask | shaft.object_mask))
        assert np.all(frame.descriptor_image[off] == space.background) and np.all(frame.depth_m[off] == 0)
        masks = frame.visible_masks
        assert masks.shape == (2, 72, 96) and np.array_equal(masks[order.index(1)], shaft_in_front)
    # The parts' regions are apart, so the image tells every pixel's part by its descriptor alone.
    region_of = [space.region_bounds(i) for i in range(2)]
    low, high = region_of[0]
    inside_toolcap = np.all((frame.descriptor_image >= low - 1e-6) & (frame.descriptor_image <= high + 1e-6), axis=-1)
    assert np.array_equal(inside_toolcap, frame.instance_ids == toolcap_id)


def test_one_instance_renders_as_the_single_part_renderer(scene):
    space, meshes, mapped, renderer, (toolcap, _) = scene
    frame = render_instances([(meshes[0], mapped[0], FAR_TOOLCAP)], space.background, INTRINSICS)
    assert np.array_equal(frame.descriptor_image, toolcap.descriptor_image)
    assert np.array_equal(frame.instance_ids == 1, toolcap.object_mask)
    assert np.array_equal(frame.depth_m, toolcap.depth_m) and np.array_equal(frame.triangle_ids, toolcap.triangle_ids)
    # A simulator's segmentation hides what it does not see as that instance (a gripper over the left half).
    segmentation = np.where(toolcap.object_mask, 1, 0)
    segmentation[:, :48] = 0
    hidden = renderer.render(INTRINSICS, [(0, FAR_TOOLCAP)], visible_instance_ids=segmentation)
    single = DescriptorRenderer(meshes[0], mapped[0], space.background).render(
        INTRINSICS, FAR_TOOLCAP, visible_mask=segmentation == 1
    )
    assert (toolcap.object_mask & (segmentation == 0)).sum() > 20
    assert np.array_equal(hidden.descriptor_image, single.descriptor_image)
    assert np.array_equal(hidden.object_mask, single.object_mask)


def test_rendering_own_fields_then_mapping_equals_rendering_mapped_fields(scene, parts):
    space, meshes, mapped, renderer, _ = scene
    _, fields = parts
    instances = [(0, FAR_TOOLCAP), (1, NEAR_SHAFT)]
    own = MultiPartDescriptorRenderer(meshes, [f.vertex_descriptors for f in fields], space.background)
    own_frame = own.render(INTRINSICS, instances)
    frame = renderer.render(INTRINSICS, instances)
    part_image = space.part_image(own_frame.instance_ids, {1: "toolcap", 2: "shaft"})
    assert np.array_equal(part_image, own_frame.instance_ids)  # instance k is of part k here
    np.testing.assert_allclose(
        space.map_descriptor_image(own_frame.descriptor_image, part_image), frame.descriptor_image, rtol=0, atol=1e-6
    )


def test_instance_targets(scene):
    space, meshes, mapped, renderer, (toolcap, _) = scene
    background = space.background
    # One instance: every variant is the single-part target.
    alone = renderer.render(INTRINSICS, [(0, FAR_TOOLCAP)])
    mask_bg = np.array([*background[:2], 0], dtype=np.float32)
    for variant, bg in (("geometric", background), ("edge", background), ("mask", mask_bg)):
        np.testing.assert_allclose(
            make_instances_target(variant, alone.descriptor_image, alone.instance_ids, bg),
            make_target(variant, toolcap.descriptor_image, toolcap.object_mask, bg),
            rtol=0,
            atol=1e-6,
        )
    # Two instances: each is blended at its own outline, also where the shaft hides the toolcap.
    frame = renderer.render(INTRINSICS, [(0, FAR_TOOLCAP), (1, NEAR_SHAFT)])
    edge = make_instances_target("edge", frame.descriptor_image, frame.instance_ids, background, edge_width_px=2.0)
    ids = frame.instance_ids
    toolcap_next_to_shaft = (ids == 1) & (np.roll(ids, 1, axis=0) == 2)
    assert toolcap_next_to_shaft.sum() > 3
    to_background = np.linalg.norm(edge - background, axis=-1)
    unblended = np.linalg.norm(frame.descriptor_image - background, axis=-1)
    ratio = to_background[toolcap_next_to_shaft] / unblended[toolcap_next_to_shaft]
    np.testing.assert_allclose(ratio, 0.25, atol=1e-5)  # distance 1 px - 0.5 over a 2 px width
    assert np.all(edge[ids == 0] == background)
    # Mask channel: per instance, 0 off every instance, each instance's own maximum 1.
    masked = make_instances_target("mask", frame.descriptor_image, ids, mask_bg)
    channel = masked[..., 2]
    assert np.all(channel[ids == 0] == 0)
    assert channel[ids == 1].max() == pytest.approx(1) and channel[ids == 2].max() == pytest.approx(1)
    assert channel[toolcap_next_to_shaft].max() < 0.5
    np.testing.assert_array_equal(masked[ids > 0][:, :2], frame.descriptor_image[ids > 0][:, :2])
    np.testing.assert_array_equal(masked[ids == 0], np.tile(mask_bg, (int((ids == 0).sum()), 1)))


def test_rendering_bad_input_is_refused_naming_it(scene):
    space, meshes, mapped, renderer, _ = scene
    with pytest.raises(DonGymError, match="part index 2 is outside 0..1"):
        renderer.render(INTRINSICS, [(2, FAR_TOOLCAP)])
    with pytest.raises(DonGymError, match="instance_ids"):
        renderer.render(INTRINSICS, [(0, FAR_TOOLCAP), (1, NEAR_SHAFT)], instance_ids=[3, 3])
    with pytest.raises(DonGymError, match="T_camera_object"):
        renderer.render(INTRINSICS, [(0, np.eye(3))])
    with pytest.raises(DonGymError, match="visible_instance_ids"):
        renderer.render(INTRINSICS, [(0, FAR_TOOLCAP)], visible_instance_ids=np.zeros((5, 5), dtype=int))
    with pytest.raises(DonGymError, match="vertex_descriptors"):
        MultiPartDescriptorRenderer(meshes, [mapped[0], mapped[1][:, :2]], space.background)
    with pytest.raises(DonGymError, match="meshes"):
        MultiPartDescriptorRenderer([], [], space.background)
    with pytest.raises(DonGymError, match="instances"):
        render_instances([], space.background, INTRINSICS)
    with pytest.raises(DonGymError, match="instance_ids"):
        make_instances_target("edge", mapped[0][None, :10], np.zeros((1, 10)), space.background)


# --- the identity layout: whole fields plus one dimension for part identity ----------------------------


def test_training_layout_is_identity_wherever_it_applies():
    # Two or more parts, not the mask variant, 1/K at least the gap: the whole fields plus an identity channel.
    assert training_layout("auto", ["a", "b"], 0.25, mask_variant=False) == "identity"
    assert training_layout("auto", ["a", "b", "c", "d"], 0.25, mask_variant=False) == "identity"
    # Otherwise the dataset's own layout: one part, the mask variant, or more parts than the gap lets apart.
    assert training_layout("auto", ["a"], 0.25, mask_variant=False) == "dataset"
    assert training_layout("auto", ["a", "b"], 0.25, mask_variant=True) == "dataset"
    assert training_layout("auto", ["a", "b", "c", "d", "e"], 0.25, mask_variant=False) == "dataset"
    # An explicit layout is returned as asked.
    assert training_layout("dataset", ["a", "b"], 0.25, mask_variant=False) == "dataset"
    assert training_layout("identity", ["a", "b"], 0.25, mask_variant=False) == "identity"
    with pytest.raises(
        DonGymError, match=r"part layout 'corners' is unknown; expected one of \['auto', 'identity', 'dataset'\]"
    ):
        training_layout("corners", ["a", "b"], 0.25, mask_variant=False)


@pytest.mark.parametrize("count", [2, 3, 4])
def test_identity_layout_keeps_every_field_whole_and_parts_apart(parts, count):
    models, fields = parts
    arrays = [f.vertex_descriptors for f in fields] + [asymmetric_field(), asymmetric_field()[::-1]]
    names = [m.name for m in models] + ["bracket", "flange"]
    space = build_part_space(names[:count], arrays[:count], layout="identity")
    assert space.layout == "identity" and (space.field_dim, space.dim) == (3, 4)
    check_separation(space, arrays[:count])
    between, to_background = space.region_distances()
    np.testing.assert_allclose(between[0], np.arange(count) / count)  # 1/K apart per step of identity
    np.testing.assert_allclose(to_background.min(), 1 / count)
    assert between[~np.eye(count, dtype=bool)].min() >= space.gap
    assert space.background[-1] == 0
    for k, own in enumerate(arrays[:count]):
        assert space.parts[k].scale == 1.0
        mapped = space.map_descriptors(k, own)
        assert mapped.shape == (len(own), 4)
        np.testing.assert_array_equal(mapped[:, :3], own.astype(np.float32))  # the part's field, unscaled
        np.testing.assert_array_equal(mapped[:, 3], np.float32((k + 1) / count))
        np.testing.assert_allclose(space.own_descriptors(k, mapped), own, rtol=0, atol=DESCRIPTOR_ATOL)
    # Images: (H, W, 3) own descriptors in, (H, W, 4) out, the background off every part.
    image = np.stack([arrays[0][:6], arrays[1][:6]]).reshape(2, 6, 3)
    labels = np.array([[1] * 6, [0, 0, 2, 2, 2, 2]])
    out = space.map_descriptor_image(image, labels)
    assert out.shape == (2, 6, 4)
    np.testing.assert_array_equal(out[1, :2], np.tile(space.background, (2, 1)))
    np.testing.assert_array_equal(out[0], space.map_descriptors(0, image[0]))


def test_identity_layout_record_and_format_1_records(parts):
    models, fields = parts
    space = part_space_for(models, fields, layout="identity")
    record = json.loads(json.dumps(space.to_dict()))
    assert (record["format"], record["field_dim"], record["layout"]) == (2, 3, "identity")
    back = PartSpace.from_dict(record)
    assert (back.layout, back.dim, back.field_dim) == ("identity", 4, 3)
    np.testing.assert_array_equal(back.background, space.background)
    np.testing.assert_array_equal(
        back.map_descriptors(1, fields[1].vertex_descriptors), space.map_descriptors(1, fields[1].vertex_descriptors)
    )
    for broken, what in [
        ({**record, "field_dim": 4}, "field_dim 4"),
        ({k: v for k, v in record.items() if k != "field_dim"}, "field_dim"),
        ({**record, "format": 1}, "field_dim 4 with layout 'identity'"),
        ({**record, "format": 3}, "format 3"),
    ]:
        with pytest.raises(DonGymError, match=f"checkpoint x.pt.*{what}"):
            PartSpace.from_dict(broken, source="checkpoint x.pt")
    # The other layouts are written as format 1, as every existing dataset and checkpoint holds them, and a
    # format-1 record reads as before: the fields have the space's D.
    corners = part_space_for(models, fields)
    old = corners.to_dict()
    assert old["format"] == 1 and "field_dim" not in old
    assert list(old) == ["format", "layout", "gap", "mask_dim", "background", "parts"]
    back = PartSpace.from_dict(old)
    assert back.field_dim == back.dim == 3 and back.layout == "corners"
    assert back.to_dict() == old


def test_identity_layout_refusals_are_one_line():
    field = np.random.default_rng(0).random((20, 3))
    refusals = [
        (dict(names=["a"], fields=[field]), "at least 2 parts"),
        (dict(names=list("abcde"), fields=[field] * 5), "1/K = 0.200 .* less than gap=0.25; at most 4 parts"),
        (dict(names=list("abc"), fields=[field] * 3, gap=0.4), "less than gap=0.4; at most 2 parts"),
        (dict(names=["a", "b"], fields=[field] * 2, mask_dim=-1), "mask variant is not supported"),
    ]
    for kwargs, message in refusals:
        with pytest.raises(DonGymError, match=message) as refused:
            build_part_space(**kwargs, layout="identity")
        assert "\n" not in str(refused.value)
    with pytest.raises(DonGymError, match=r"layout='grid': expected one of \['auto', 'identity'\]"):
        build_part_space(["a", "b"], [field] * 2, layout="grid")
    assert build_part_space(list("abcd"), [field] * 4, layout="identity").region_distances()[0][0, 1] == 0.25
