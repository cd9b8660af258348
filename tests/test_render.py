"""Tests of don_gym.data.render: ray-cast descriptor targets, masks and view-dependent descriptors."""

from __future__ import annotations

import cv2
import numpy as np
import pybullet as p
import pytest
import trimesh
from pybullet_utils.bullet_client import BulletClient
from scipy.ndimage import distance_transform_edt
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from don_gym.data.render import (
    TARGET_VARIANTS,
    DescriptorRenderer,
    RenderedTarget,
    default_edge_width_px,
    edge_blend,
    embree_available,
    make_target,
    mask_background,
    mask_channel,
    render_descriptor_image,
)
from don_gym.errors import DonGymError
from don_gym.geometry import (
    CameraIntrinsics,
    backproject_depth,
    invert_transform,
    make_transform,
    pose_from_transform,
    transform_points,
)
from don_gym.objects import load_object
from don_gym.perception.descriptor_sources import descriptor_field_for

BACKGROUND = np.array([0.0, 0.0, 1.0], dtype=np.float32)


@pytest.fixture(scope="module")
def toolcap() -> trimesh.Trimesh:
    return load_object("toolcap").mesh


def coordinate_descriptors(mesh: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Normalised vertex coordinates as descriptors: an affine function of position, so the
    exact descriptor of any surface point is its own normalised coordinate."""
    lower, upper = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    return ((mesh.vertices - lower) / (upper - lower)).astype(np.float32), lower, upper


def oblique_pose(distance_m: float, offset_m: tuple[float, float] = (0.004, -0.003)) -> np.ndarray:
    """Toolcap tilted so that the bore, the body and the flange are all in view."""
    rotation = Rotation.from_euler("xyz", [2.2, 0.4, 0.3]).as_matrix()
    return make_transform(rotation, [offset_m[0], offset_m[1], distance_m])


def test_rendered_descriptors_match_surface_points(toolcap):
    descriptors, lower, upper = coordinate_descriptors(toolcap)
    intrinsics = CameraIntrinsics.d435(160, 120)
    T_camera_object = oblique_pose(0.15)
    rendered = DescriptorRenderer(toolcap, descriptors, BACKGROUND).render(intrinsics, T_camera_object)

    assert isinstance(rendered, RenderedTarget)
    assert rendered.descriptor_image.shape == (120, 160, 3) and rendered.descriptor_image.dtype == np.float32
    assert rendered.object_mask.dtype == bool and rendered.depth_m.dtype == np.float32
    assert rendered.triangle_ids.dtype == np.int32
    count = int(rendered.object_mask.sum())
    assert 500 < count < 5000
    off = ~rendered.object_mask
    assert np.all(rendered.descriptor_image[off] == BACKGROUND)
    assert np.all(rendered.depth_m[off] == 0) and np.all(rendered.triangle_ids[off] == -1)
    assert np.all(rendered.depth_m[rendered.object_mask] > 0.1)

    # Back-project the rendered depth into the object frame; the point must lie on the surface
    # and its exact descriptor (normalised coordinate of the nearest surface point) must match.
    v, u = np.nonzero(rendered.object_mask)
    points_camera = backproject_depth(intrinsics, rendered.depth_m, np.stack([u, v], axis=1))
    points_object = transform_points(invert_transform(T_camera_object), points_camera)
    # trimesh 5.2's closest_point uses absolute tolerances that misplace points on millimetre-sized
    # triangles of a mesh in metres (seen: 0.8 mm off for a point inside a triangle), so query
    # in millimetres.
    toolcap_mm = toolcap.copy()
    toolcap_mm.apply_scale(1000.0)
    closest_mm, distance_mm, triangle = trimesh.proximity.closest_point(toolcap_mm, points_object * 1000.0)
    assert np.percentile(distance_mm, 99) < 1e-3  # 1 micrometre: float32 depth rounding only
    expected = (closest_mm / 1000.0 - lower) / (upper - lower)
    error = np.abs(rendered.descriptor_image[v, u] - expected).max(axis=1)
    assert np.percentile(error, 99) < 0.02
    assert np.median(error) < 1e-4
    # The hit triangle is the one the point lies on, except where a point sits on a shared edge.
    assert np.mean(rendered.triangle_ids[v, u] == triangle) > 0.95


def _pybullet_segmentation(mesh: trimesh.Trimesh, intrinsics: CameraIntrinsics, T_camera_object, tmp_path):
    """Object mask and depth of ``mesh`` at ``T_camera_object`` rendered by PyBullet's TinyRenderer.

    The camera sits at the world origin with OpenCV axes, so the object's world pose is
    ``T_camera_object`` and the view matrix only flips OpenCV to OpenGL axes.
    """
    obj_path = tmp_path / "mesh.obj"
    mesh.export(obj_path)
    client = BulletClient(connection_mode=p.DIRECT)
    try:
        visual = client.createVisualShape(p.GEOM_MESH, fileName=str(obj_path), meshScale=[1.0, 1.0, 1.0])
        position, quaternion = pose_from_transform(T_camera_object)
        body = client.createMultiBody(
            baseMass=0.0,
            baseVisualShapeIndex=visual,
            basePosition=position.tolist(),
            baseOrientation=quaternion.tolist(),
        )
        W, H = intrinsics.width, intrinsics.height
        near, far = 0.01, 2.0
        # The projection of docs/background.md, section "PyBullet and the Panda", with the principal
        # point where TinyRenderer needs it to sample each pixel (u, v) at the integer pixel
        # coordinate, as the ray cast does: cx unchanged, cy + 1 (TinyRenderer samples at
        # viewport-pixel corners and flips rows).
        # Found by scanning quarter-pixel shifts: IoU 1.0 on 11 of 12 random poses at 160x120 to
        # 640x480, against 0.86-0.97 with the plain formula.
        cx, cy = intrinsics.cx, intrinsics.cy + 1.0
        projection = np.array(
            [
                [2 * intrinsics.fx / W, 0, 1 - 2 * cx / W, 0],
                [0, 2 * intrinsics.fy / H, 2 * cy / H - 1, 0],
                [0, 0, -(far + near) / (far - near), -2 * far * near / (far - near)],
                [0, 0, -1, 0],
            ]
        )
        view = np.diag([1.0, -1.0, -1.0, 1.0])  # inverse of the OpenCV -> OpenGL axis flip
        _, _, _, zbuffer, segmentation = client.getCameraImage(
            W,
            H,
            viewMatrix=view.T.reshape(16).tolist(),
            projectionMatrix=projection.T.reshape(16).tolist(),
            renderer=p.ER_TINY_RENDERER,
        )
    finally:
        client.disconnect()
    mask = np.asarray(segmentation).reshape(H, W) == body
    zbuffer = np.asarray(zbuffer, dtype=np.float64).reshape(H, W)
    depth = far * near / (far - (far - near) * zbuffer)
    return mask, depth


def test_mask_agrees_with_pybullet_segmentation(toolcap, tmp_path):
    descriptors, _, _ = coordinate_descriptors(toolcap)
    intrinsics = CameraIntrinsics.d435(320, 240)
    T_camera_object = oblique_pose(0.25, offset_m=(0.02, 0.01))
    rendered = render_descriptor_image(toolcap, descriptors, BACKGROUND, intrinsics, T_camera_object)
    bullet_mask, bullet_depth = _pybullet_segmentation(toolcap, intrinsics, T_camera_object, tmp_path)

    assert bullet_mask.sum() > 1000
    union = np.logical_or(rendered.object_mask, bullet_mask).sum()
    iou = np.logical_and(rendered.object_mask, bullet_mask).sum() / union
    assert iou >= 0.99  # the spec asks 0.97; 1.0 is measured, and a half-pixel shift gives ~0.96
    both = rendered.object_mask & bullet_mask
    assert np.median(np.abs(rendered.depth_m[both] - bullet_depth[both])) < 1e-3


def test_visible_mask_makes_occluded_pixels_background(toolcap):
    descriptors, _, _ = coordinate_descriptors(toolcap)
    intrinsics = CameraIntrinsics.d435(160, 120)
    T_camera_object = oblique_pose(0.15)
    renderer = DescriptorRenderer(toolcap, descriptors, BACKGROUND)
    full = renderer.render(intrinsics, T_camera_object)
    columns = np.nonzero(full.object_mask.any(axis=0))[0]
    visible = np.ones((120, 160), dtype=bool)
    visible[:, : int(np.median(columns))] = False  # a gripper finger over the left half of the part
    occluded = renderer.render(intrinsics, T_camera_object, visible_mask=visible)

    assert np.array_equal(occluded.object_mask, full.object_mask & visible)
    hidden = full.object_mask & ~visible
    assert hidden.sum() > 100
    assert np.all(occluded.descriptor_image[hidden] == BACKGROUND)
    assert np.all(occluded.depth_m[hidden] == 0) and np.all(occluded.triangle_ids[hidden] == -1)
    kept = occluded.object_mask
    assert np.array_equal(occluded.descriptor_image[kept], full.descriptor_image[kept])
    with pytest.raises(DonGymError, match="visible_mask"):
        renderer.render(intrinsics, T_camera_object, visible_mask=np.ones((60, 80), dtype=bool))


def disc_mask(size: int, radius: float, centre: tuple[int, int]) -> np.ndarray:
    v, u = np.mgrid[0:size, 0:size]
    return (u - centre[0]) ** 2 + (v - centre[1]) ** 2 <= radius**2


def test_mask_channel_on_disc():
    mask = disc_mask(41, 10.0, (20, 20))
    channel = mask_channel(mask)
    assert channel.dtype == np.float32 and channel.shape == mask.shape
    assert channel[20, 20] == pytest.approx(1.0)
    assert np.all(channel[~mask] == 0.0)
    boundary = mask & ~disc_mask(41, 9.0, (20, 20))
    assert np.all((channel[boundary] > 0.0) & (channel[boundary] < 0.15))
    # Independent reference: scipy's exact Euclidean distance transform, normalised.
    reference = distance_transform_edt(mask)
    np.testing.assert_allclose(channel, reference / reference.max(), atol=1e-5)
    # Along a radius the value falls from 1 at the centre towards the edge.
    assert np.all(np.diff(channel[20, 20:31]) < 0)

    # Two components are normalised together: only the larger one reaches 1.
    two = mask | disc_mask(41, 3.0, (4, 4))
    channel_two = mask_channel(two)
    assert channel_two[20, 20] == pytest.approx(1.0)
    assert 0.2 < channel_two[4, 4] < 0.5
    assert np.all(mask_channel(np.zeros((5, 5), dtype=bool)) == 0.0)
    # The image border counts as off-object: a mask filling the image peaks in its middle.
    full = mask_channel(np.ones((9, 9), dtype=bool))
    assert full[4, 4] == pytest.approx(1.0) and full[0, 4] == pytest.approx(0.2)


def test_edge_blend_on_disc():
    mask = disc_mask(41, 10.0, (20, 20))
    object_descriptor = np.array([0.8, 0.6, 0.2], dtype=np.float32)
    background = np.array([0.0, 0.1, 1.0], dtype=np.float32)
    image = np.where(mask[..., None], object_descriptor, background).astype(np.float32)
    blended = edge_blend(image, mask, background, width_px=3.0)

    assert blended.dtype == np.float32 and blended.shape == image.shape
    np.testing.assert_allclose(blended[20, 20], object_descriptor)
    assert np.all(blended[~mask] == background)
    # Weight of the object descriptor: distance to the boundary (half a pixel less than to the
    # nearest off-object pixel centre) over the width, clipped to [0, 1].
    weight = np.clip((distance_transform_edt(mask) - 0.5) / 3.0, 0.0, 1.0)
    expected = background + weight[..., None] * (object_descriptor - background)
    np.testing.assert_allclose(blended, expected, atol=1e-5)
    # The outermost pixels sit strictly between object and background descriptor.
    boundary = mask & ~disc_mask(41, 9.0, (20, 20))
    low, high = np.minimum(object_descriptor, background), np.maximum(object_descriptor, background)
    edge_values = blended[boundary]
    assert np.all((edge_values > low) & (edge_values < high))
    np.testing.assert_allclose(blended[20, 30], background + (object_descriptor - background) / 6.0, atol=1e-6)

    # Objects cut by the image border are not blended along the border.
    half = np.zeros((10, 10), dtype=bool)
    half[:, :5] = True
    cut = edge_blend(np.where(half[..., None], object_descriptor, background), half, background, width_px=2.0)
    np.testing.assert_allclose(cut[0, 0], object_descriptor)
    assert default_edge_width_px(640) == pytest.approx(3.0) and default_edge_width_px(320) == pytest.approx(1.5)
    with pytest.raises(DonGymError, match="width_px"):
        edge_blend(image, mask, background, width_px=0.0)


def test_view_dependent_descriptors_on_blobs_touching_the_border():
    """Both work on a crop around the mask; compare with scipy on the whole image."""
    rng = np.random.default_rng(3)
    for _ in range(5):
        noise = cv2.GaussianBlur(rng.normal(size=(40, 56)), (0, 0), 4.0)
        mask = noise > 0.02  # several blobs, some cut by the image border
        assert mask.any() and not mask.all()
        descriptors = rng.uniform(size=(40, 56, 2)).astype(np.float32)
        background = np.array([0.5, 1.0], dtype=np.float32)
        weight = np.clip((distance_transform_edt(mask) - 0.5) / 2.5, 0.0, 1.0)[..., None]
        expected = np.where(mask[..., None], background + weight * (descriptors - background), background)
        np.testing.assert_allclose(edge_blend(descriptors, mask, background, 2.5), expected, atol=1e-5)
        distance = distance_transform_edt(np.pad(mask, 1))[1:-1, 1:-1]
        np.testing.assert_allclose(mask_channel(mask), distance / distance.max(), atol=1e-5)


def test_make_target_variants(toolcap):
    descriptors, _, _ = coordinate_descriptors(toolcap)
    rendered = DescriptorRenderer(toolcap, descriptors, BACKGROUND).render(
        CameraIntrinsics.d435(160, 120), oblique_pose(0.15)
    )
    geometric = make_target("geometric", rendered.descriptor_image, rendered.object_mask, BACKGROUND)
    assert np.array_equal(geometric, rendered.descriptor_image) and geometric is not rendered.descriptor_image
    edge = make_target("edge", rendered.descriptor_image, rendered.object_mask, BACKGROUND, edge_width_px=2.0)
    # OpenCV's distance transform may differ in the last bit between calls on differently
    # aligned buffers (seen on CI), so the comparisons through it allow float32 rounding.
    np.testing.assert_allclose(
        edge, edge_blend(rendered.descriptor_image, rendered.object_mask, BACKGROUND, 2.0), rtol=0, atol=1e-6
    )
    assert not np.array_equal(edge, geometric)
    masked = make_target("mask", rendered.descriptor_image, rendered.object_mask, BACKGROUND)
    np.testing.assert_array_equal(masked[..., :2], geometric[..., :2])
    np.testing.assert_allclose(masked[..., 2], mask_channel(rendered.object_mask), rtol=0, atol=1e-6)
    masked_first = make_target("mask", rendered.descriptor_image, rendered.object_mask, BACKGROUND, mask_dim=0)
    np.testing.assert_array_equal(masked_first[..., 1:], geometric[..., 1:])
    other_background = np.array([0.25, 0.75, 0.5], dtype=np.float32)
    masked = make_target("mask", rendered.descriptor_image, rendered.object_mask, other_background)
    off = ~rendered.object_mask
    assert off.any() and rendered.object_mask.any()
    np.testing.assert_array_equal(masked[off], np.tile([0.25, 0.75, 0.0], (int(off.sum()), 1)))
    np.testing.assert_array_equal(masked[~off][:, :2], geometric[~off][:, :2])
    with pytest.raises(DonGymError, match="geometric"):
        make_target("blur", rendered.descriptor_image, rendered.object_mask, BACKGROUND)
    with pytest.raises(DonGymError, match="mask_dim"):
        make_target("mask", rendered.descriptor_image, rendered.object_mask, BACKGROUND, mask_dim=3)
    assert TARGET_VARIANTS == ("geometric", "edge", "mask")


def test_mask_background_is_furthest_from_the_dimensions_the_mask_variant_keeps():
    # Descriptors on the diagonal of the first two dimensions: the corners off it are furthest.
    t = np.linspace(0.0, 1.0, 101)
    descriptors = np.stack([t, t, 1.0 - t], axis=1)
    background = mask_background(descriptors)
    assert background.dtype == np.float32 and background[2] == 0.0
    assert cKDTree(descriptors[:, :2]).query(background[:2])[0] == pytest.approx(np.sqrt(0.5), abs=1e-3)
    first = mask_background(descriptors, mask_dim=0)
    assert first[0] == 0.0 and cKDTree(descriptors[:, 1:]).query(first[1:])[0] == pytest.approx(np.sqrt(0.5), abs=1e-3)
    with pytest.raises(DonGymError, match="mask_dim"):
        mask_background(descriptors, mask_dim=3)
    with pytest.raises(DonGymError, match="vertex_descriptors"):
        mask_background(descriptors[:, :1])


@pytest.mark.parametrize("name", ["toolcap", "shaft"])
def test_mask_background_keeps_the_outline_apart_from_the_background(name):
    """The full field's background projected onto the two geometric dimensions lies near an object
    descriptor, where the mask channel is ~0 at the outline; the mask variant's own background does not."""
    field = descriptor_field_for(load_object(name))
    geometric = cKDTree(field.vertex_descriptors[:, :2])
    projected = geometric.query(field.background[:2])[0]
    own = geometric.query(mask_background(field.vertex_descriptors)[:2])[0]
    assert projected < 0.4 and own > 0.45 and own > projected + 0.1


@pytest.mark.skipif(not embree_available(), reason="embreex does not import on this machine")
def test_embree_and_fallback_intersectors_agree(toolcap):
    descriptors, _, _ = coordinate_descriptors(toolcap)
    intrinsics = CameraIntrinsics.d435(160, 120)
    T_camera_object = oblique_pose(0.2)
    embree = DescriptorRenderer(toolcap, descriptors, BACKGROUND, intersector="embree")
    fallback = DescriptorRenderer(toolcap, descriptors, BACKGROUND, intersector="triangle")
    assert embree.intersector_name == "embree" and fallback.intersector_name == "triangle"
    a, b = embree.render(intrinsics, T_camera_object), fallback.render(intrinsics, T_camera_object)

    # Rays grazing the silhouette may fall either way in float32 vs float64.
    assert np.sum(a.object_mask != b.object_mask) <= 3
    both = a.object_mask & b.object_mask
    assert both.sum() > 400
    np.testing.assert_allclose(a.descriptor_image[both], b.descriptor_image[both], atol=1e-4)
    np.testing.assert_allclose(a.depth_m[both], b.depth_m[both], atol=1e-6)


def test_culling_loses_no_hits(toolcap):
    """Casting only the projected hull must find every pixel a full-image cast finds."""
    descriptors, _, _ = coordinate_descriptors(toolcap)
    intrinsics = CameraIntrinsics.d435(64, 48)
    renderer = DescriptorRenderer(toolcap, descriptors, BACKGROUND)
    intersector = renderer._raycaster.intersector
    rng = np.random.default_rng(0)
    nonempty = 0
    for _ in range(12):
        rotation = Rotation.random(random_state=rng).as_matrix()
        # Some poses leave the part partly off the image.
        T_camera_object = make_transform(rotation, [*rng.uniform(-0.06, 0.06, 2), rng.uniform(0.08, 0.3)])
        rendered = renderer.render(intrinsics, T_camera_object)
        T_object_camera = invert_transform(T_camera_object)
        directions = backproject_depth(intrinsics, np.ones((48, 64))).reshape(-1, 3) @ T_object_camera[:3, :3].T
        origins = np.broadcast_to(T_object_camera[:3, 3], directions.shape)
        full_hits = (intersector.intersects_first(origins, directions) >= 0).reshape(48, 64)
        assert np.array_equal(rendered.object_mask, full_hits)
        nonempty += bool(full_hits.any())
    assert nonempty >= 6


def assert_all_background(rendered: RenderedTarget, shape: tuple[int, int]) -> None:
    assert rendered.descriptor_image.shape == (*shape, 3)
    assert np.all(rendered.descriptor_image == BACKGROUND)
    assert not rendered.object_mask.any()
    assert np.all(rendered.depth_m == 0) and np.all(rendered.triangle_ids == -1)


def test_object_off_image_or_behind_camera(toolcap):
    descriptors, _, _ = coordinate_descriptors(toolcap)
    intrinsics = CameraIntrinsics.d435(80, 60)
    renderer = DescriptorRenderer(toolcap, descriptors, BACKGROUND)
    rotation = Rotation.from_euler("xyz", [0.3, 0.2, 0.1]).as_matrix()
    assert_all_background(renderer.render(intrinsics, make_transform(rotation, [1.0, 0.0, 0.3])), (60, 80))
    assert_all_background(renderer.render(intrinsics, make_transform(rotation, [0.0, 0.0, -0.3])), (60, 80))
    # Behind the camera but on the optical axis: a ray cast backwards would hit it.
    assert_all_background(renderer.render(intrinsics, make_transform(rotation, [0.0, 0.0, -0.05])), (60, 80))
    # Straddling the camera plane, beside the camera: only what lies in front may appear.
    straddling = renderer.render(intrinsics, make_transform(rotation, [0.03, 0.0, 0.0]))
    assert np.all(straddling.depth_m[straddling.object_mask] > 0)
    # The camera inside the bore looks at the bore wall: every pixel hits, none errors.
    inside = renderer.render(intrinsics, make_transform(np.eye(3), [0.0, 0.0, 0.01]))
    assert inside.object_mask.all() and np.all(inside.depth_m > 0)


def test_input_validation(toolcap):
    descriptors, _, _ = coordinate_descriptors(toolcap)
    with pytest.raises(DonGymError, match="vertex_descriptors"):
        DescriptorRenderer(toolcap, descriptors[:-1], BACKGROUND)
    with pytest.raises(DonGymError, match="background"):
        DescriptorRenderer(toolcap, descriptors, np.zeros(2))
    with pytest.raises(DonGymError, match="intersector"):
        DescriptorRenderer(toolcap, descriptors, BACKGROUND, intersector="optix")
    renderer = DescriptorRenderer(toolcap, descriptors, BACKGROUND)
    with pytest.raises(DonGymError, match="T_camera_object"):
        renderer.render(CameraIntrinsics.d435(80, 60), np.eye(3))
    # A (vertices, faces) pair works like the mesh itself.
    pair = DescriptorRenderer((toolcap.vertices, toolcap.faces), descriptors, BACKGROUND)
    a = pair.render(CameraIntrinsics.d435(80, 60), oblique_pose(0.15))
    b = renderer.render(CameraIntrinsics.d435(80, 60), oblique_pose(0.15))
    np.testing.assert_array_equal(a.descriptor_image, b.descriptor_image)
