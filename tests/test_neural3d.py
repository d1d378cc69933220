"""The neural memory's 3D geometry: ground projection, level frame, planar poses, grid rotations."""
from __future__ import annotations

import math

import numpy as np
import pytest

from data_tools.camera import Intrinsics
from data_tools.geometry import look_at
from slam.neural.geometry3d import (allocentric_to_world, egocentric_cells, level_rotation, planar_relative,
                                    planar_state, project_max, view_wedge)


def _cam(x, y, yaw, z=1.0, pitch_deg=-10.0):
    p = math.radians(pitch_deg)
    e = np.array([x, y, z])
    return look_at(e, e + np.array([math.cos(yaw) * math.cos(p), math.sin(yaw) * math.cos(p), math.sin(p)]))


def _ego_offset(T_w_c, X, cell):
    """(forward, right) of world point X in the level frame of camera T_w_c, metres."""
    x, y, yaw = planar_state(T_w_c)
    d = X[:2] - np.array([x, y])
    return d @ np.array([math.cos(yaw), math.sin(yaw)]), -(d @ np.array([-math.sin(yaw), math.cos(yaw)]))


def test_plane_fills_expected_cells():
    """A fronto-parallel wall 2 m ahead of a level camera lands in the grid row 2 m / cell ahead,
    across the columns of the camera's horizontal field of view."""
    intr = Intrinsics(40, 30, 36.25, 36.25, 19.5, 14.5)
    T = _cam(0, 0, 0.0, pitch_deg=0.0)
    R = level_rotation(T)
    np.testing.assert_allclose(R, np.eye(3), atol=1e-12)
    depth = np.full((30, 40), 2.0)
    q, cell = 51, 0.1
    cells = egocentric_cells(depth, intr, R, cell, q)
    rows, cols = cells // q, cells % q
    assert np.all(cells >= 0)
    assert set(rows.tolist()) == {q // 2 - 20}
    half = 2.0 * 19.5 / 36.25        # lateral half-width of the wall seen (pixel centres 0 and 39), metres
    assert cols.min() == q // 2 - round(half / cell) and cols.max() == q // 2 + round(half / cell)
    assert len(set(cols.tolist())) == 2 * round(half / cell) + 1
    # holes and points behind or beyond the range are dropped
    depth[0, 0] = 0
    assert egocentric_cells(depth, intr, R, cell, q)[0] == -1
    assert np.all(egocentric_cells(depth, intr, R, cell, q, max_range_m=1.5) == -1)


def test_allocentric_round_trip_and_consistency():
    """A world point seen from camera t, placed by t's allocentric pose, lands where camera 0 sees it;
    allocentric_to_world inverts planar_relative."""
    rng = np.random.default_rng(0)
    cell = 0.1
    T0 = _cam(0.3, -0.2, 0.7)
    for _ in range(20):
        Tt = _cam(0.3 + rng.uniform(-1, 1), -0.2 + rng.uniform(-1, 1), rng.uniform(-3, 3))
        row, col, yaw = planar_relative(T0, Tt, cell)
        np.testing.assert_allclose(allocentric_to_world(T0, row, col, yaw, cell), Tt, atol=1e-9)
        X = np.append(rng.uniform(-3, 3, 2), 0.5)
        f0, r0 = _ego_offset(T0, X, cell)
        ft, rt = _ego_offset(Tt, X, cell)
        # egocentric offset of t in grid units (up = forward), rotated counter-clockwise by yaw (seen from above)
        x, y = rt / cell, ft / cell                      # math axes: x right, y up
        c, s = math.cos(yaw), math.sin(yaw)
        xa, ya = x * c - y * s, x * s + y * c
        assert abs((col + xa) - r0 / cell) < 1e-9 and abs((row - ya) - (-f0 / cell)) < 1e-9


def test_rotation_bank_matches_quarter_turns_and_turns_left():
    import torch

    from slam.neural.model import rotate_grid, rotation_bank
    x = torch.zeros(1, 1, 9, 9)
    x[0, 0, 0, 4] = 1.0              # a point straight ahead (up)
    b = rotation_bank(x, 12)
    np.testing.assert_allclose(b[0, 3, 0].numpy(), torch.rot90(x, 1, (2, 3))[0, 0].numpy(), atol=1e-6)
    # 30 deg counter-clockwise: the point moves left of straight ahead
    r30 = rotate_grid(x, 1, 12)[0, 0]
    rr, cc = np.unravel_index(int(r30.argmax()), r30.shape)
    assert cc < 4 and rr <= 1


def test_project_max_and_its_gradient():
    import torch
    f = torch.tensor([[[[1.0, 3.0], [-2.0, 5.0]]]], requires_grad=True)     # (1, 1, 2, 2)
    cells = torch.tensor([[0, 0, 4, -1]])                                    # q = 3
    g = project_max(f, cells, 3)
    assert g.shape == (1, 1, 3, 3)
    assert g[0, 0, 0, 0] == 3.0 and g[0, 0, 1, 1] == -2.0 and g[0, 0].abs().sum() == 5.0
    g.sum().backward()
    np.testing.assert_allclose(f.grad.numpy().ravel(), [0, 1, 1, 0])


def test_view_wedge_is_the_horizontal_field_of_view():
    intr = Intrinsics(40, 30, 36.25, 36.25, 19.5, 14.5)
    m = view_wedge(intr, np.eye(3), 0.1, 51, 2.5)
    c = 25
    assert m[c, c] and m[c - 10, c] and not m[c + 1, c] and not m[c - 1, 0]
    half = math.degrees(math.atan(19.5 / 36.25))
    # a cell 2 m ahead at a bearing just inside / outside the half field of view
    for ang, want in ((half - 3, True), (half + 3, False)):
        r = c - int(round(2.0 * math.cos(math.radians(ang)) / 0.1))
        cc = c + int(round(2.0 * math.sin(math.radians(ang)) / 0.1))
        assert m[r, cc] == want


@pytest.mark.parametrize("pitch", [-10.0, -25.0])
def test_level_rotation_drops_pitch(pitch):
    T = _cam(1, 2, 0.4, pitch_deg=pitch)
    R = level_rotation(T)
    # the level frame's y is gravity (world -z) and its z is the horizontal heading
    R_w_L = T[:3, :3] @ R
    np.testing.assert_allclose(R_w_L[:, 1], [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(R_w_L[:, 2], [math.cos(0.4), math.sin(0.4), 0], atol=1e-12)
