"""2DGS mask culling on CPU: dilation, pixel convention, keep rules (docs/evaluation.md §2.3)."""

import numpy as np
import pytest
from eval_fixtures import look_at
from scipy.ndimage import binary_dilation
from skimage.morphology import disk

from gsbench.data.camera import Scene
from gsbench.errors import EvaluationError
from gsbench.evaluators import culling


@pytest.mark.parametrize("radius", [0, 1, 3, 6])
def test_dilation_equals_skimage_disk(radius):
    mask = np.random.default_rng(radius).random((40, 50)) > 0.97
    np.testing.assert_array_equal(culling.dilate_mask(mask, radius), binary_dilation(mask, structure=disk(radius).astype(bool)) if radius else mask)


def test_radius_scales_with_width():
    assert culling.dilation_radius(1600, 24, 1600) == 24
    assert culling.dilation_radius(800, 24, 1600) == 12
    assert culling.dilation_radius(400, 24, 1600) == 6


def _down_camera():
    return look_at([0, 0, 3.0], [0, 0, 0], width=80, height=60, focal=70.0)


def _at_pixel(cam, u, v, depth=3.0):
    """The world point at camera depth ``depth`` that projects to continuous pixel (u, v)."""
    pc = np.array([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, 1.0]) * depth
    return cam.R.T @ (pc - cam.t)


def test_pixel_centre_convention_and_frame_border():
    cam = _down_camera()
    mask = np.zeros((60, 80), bool)
    mask[:, 0] = True  # only column 0 is object
    pts = np.array([_at_pixel(cam, u, 30.0) for u in (0.3, 0.7, 0.99, 1.6, 79.7, -5.0)])
    keep = culling.keep_in_view(pts, cam, mask)
    # u=0.3: outside (u_ref=-0.2 <= 0) -> kept; 0.7, 0.99 -> pixel 0 -> on mask; 1.6 -> pixel 1 -> culled;
    # 79.7: outside (u_ref=79.2 >= W-1) -> kept; -5: outside -> kept.
    np.testing.assert_array_equal(keep, [True, True, True, False, True, True])


def test_cull_vertices_all_views_and_faces():
    cams = [_down_camera(), look_at([3.0, 0, 0], [0, 0, 0], width=80, height=60, focal=70.0)]
    left = np.zeros((60, 80), bool)
    left[:, :40] = True
    scene = Scene(name="s", fmt="dtu", root=".", cameras=cams, images=[], masks=[left, np.ones((60, 80), bool)])
    v = np.array([_at_pixel(cams[0], 20.0, 30.0), _at_pixel(cams[0], 60.0, 30.0), _at_pixel(cams[0], 39.0, 10.0)])
    keep = culling.cull_vertices(v, scene, dilation=0)
    np.testing.assert_array_equal(keep, [True, False, True])
    # with the default 24 px at 1600 -> round(1.2) = 1 px at 80 px width, pixel 40 joins the mask
    v2 = np.array([_at_pixel(cams[0], 40.6, 30.0), _at_pixel(cams[0], 41.6, 30.0)])
    np.testing.assert_array_equal(culling.cull_vertices(v2, scene), [True, False])
    faces = np.array([[0, 1, 2], [0, 2, 0]])
    np.testing.assert_array_equal(culling.kept_faces(faces, keep), [[0, 1, 0]])


def test_cull_without_masks_is_a_clear_error():
    scene = Scene(name="nomask", fmt="dtu", root=".", cameras=[_down_camera()], images=[], masks=None)
    with pytest.raises(EvaluationError, match="eval.dtu_culling=none"):
        culling.cull_vertices(np.zeros((3, 3)), scene)
