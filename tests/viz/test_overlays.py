"""Overlay grids: one panel per view in camera order, the estimate and the truth drawn in their
colours at the projected joints, a legend naming what is drawn, typed errors, atomic files."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image

from torchmocap.cameras import make_ring_rig
from torchmocap.skeleton import human31
from torchmocap.viz.overlays import (
    ESTIMATE_COLOR,
    MASK_TINT,
    TITLE_HEIGHT,
    TRUTH_COLOR,
    frame_title,
    grid_shape,
    panel_origin,
    render_overlay_grid,
    write_overlay_grid,
)

W, H = 80, 60


@pytest.fixture(scope="module")
def skeleton():
    return human31()


@pytest.fixture(scope="module")
def rig():
    return make_ring_rig(4, image_size=(W, H))


def _pose(skeleton, shift=(0.0, 0.0, 0.0), seed=0):
    g = torch.Generator().manual_seed(seed)
    theta = skeleton.zero_pose() + 0.15 * torch.randn(skeleton.num_dofs, generator=g)
    theta[:3] = torch.tensor(shift)
    with torch.no_grad():
        return skeleton(theta).positions


def _joint_pixels(rig, positions, scale=1.0, columns=2):
    """Grid pixel (x, y) of every joint in front of each camera and inside its image."""
    pix, depth, _ = rig.project(positions.to(rig.K.dtype))
    out = []
    for c in range(rig.num_cameras):
        x0, y0 = panel_origin(c, (round(W * scale), round(H * scale)), columns)
        for j in range(positions.shape[0]):
            u, v = pix[c, j].tolist()
            if depth[c, j] > 0 and 3 <= u <= W - 4 and 3 <= v <= H - 4:
                x, y = (u + 0.5) * scale - 0.5, (v + 0.5) * scale - 0.5
                out.append((c, j, x0 + round(x), y0 + round(y)))
    return out


def _has(region, color):
    return bool((region.reshape(-1, 3) == np.array(color)).all(-1).any())


class TestGridShape:
    def test_cardinality(self):
        assert [grid_shape(c) for c in (1, 2, 3, 4, 5, 9)] == [
            (1, 1), (1, 2), (2, 2), (2, 2), (2, 3), (3, 3)]
        assert grid_shape(4, columns=1) == (4, 1) and grid_shape(3, columns=8) == (1, 3)

    def test_exception(self):
        with pytest.raises(ValueError, match="num_views"):
            grid_shape(0)
        with pytest.raises(ValueError, match="columns"):
            grid_shape(3, columns=0)

    def test_frame_title(self):
        assert frame_title(12, 25.0) == "frame 12   t = 0.480 s"


class TestRenderOverlayGrid:
    def test_smoke(self, skeleton, rig):
        grid = render_overlay_grid(None, rig, _pose(skeleton), skeleton.parents)
        assert grid.dtype == np.uint8 and grid.shape == (TITLE_HEIGHT + 2 * H, 2 * W, 3)

    def test_cardinality_one_panel_per_view(self, skeleton):
        """Every view in its own cell, row-major in camera order: a view filled with its own
        colour shows that colour in its cell and nowhere else."""
        for C in (1, 3, 4, 5):
            rig = make_ring_rig(C, image_size=(W, H))
            colors = [(10 + 40 * c, 200 - 30 * c, 7 * c) for c in range(C)]
            views = np.stack([np.broadcast_to(np.array(col, np.uint8), (H, W, 3))
                              for col in colors])
            est = _pose(skeleton, shift=(0.0, 0.0, 60.0))  # above every camera: not drawn
            grid = render_overlay_grid(views, rig, est, skeleton.parents, title="t")
            rows, cols = grid_shape(C)
            assert grid.shape[0] == TITLE_HEIGHT + rows * H and grid.shape[1] >= cols * W
            for c, col in enumerate(colors):
                x0, y0 = panel_origin(c, (W, H), cols)
                cell = grid[y0 + 18:y0 + H, x0:x0 + W]  # below the camera label
                assert (cell == np.array(col)).all(), (C, c)
                for other in set(colors) - {col}:
                    assert not _has(cell, other)
            for c in range(C, rows * cols):  # unused cells stay black
                x0, y0 = panel_origin(c, (W, H), cols)
                assert not grid[y0:y0 + H, x0:x0 + W].any()

    @pytest.mark.parametrize("scale", [1.0, 2.0])
    def test_feature_estimate_and_truth_colors_at_projected_joints(self, skeleton, rig, scale):
        est, truth = _pose(skeleton, seed=1), _pose(skeleton, shift=(0.4, 0.2, 0.0), seed=2)
        grid = render_overlay_grid(None, rig, est, skeleton.parents, truth=truth, scale=scale)
        pts = _joint_pixels(rig, est, scale)
        assert len(pts) > 40  # most joints of the four views
        for c, j, x, y in pts:  # the estimate is drawn on top
            assert tuple(grid[y, x]) == ESTIMATE_COLOR, (c, j)
        # the truth alone where it is visible: the estimate far above every camera
        far = _pose(skeleton, shift=(0.0, 0.0, 60.0), seed=1)
        grid = render_overlay_grid(None, rig, far, skeleton.parents, truth=truth, scale=scale)
        pts = _joint_pixels(rig, truth, scale)
        assert len(pts) > 40
        for c, j, x, y in pts:
            assert tuple(grid[y, x]) == TRUTH_COLOR, (c, j)
        assert not _has(grid[TITLE_HEIGHT:], ESTIMATE_COLOR)

    def test_feature_legend(self, skeleton, rig):
        est = _pose(skeleton)
        with_truth = render_overlay_grid(None, rig, est, skeleton.parents, truth=est + 0.1,
                                         title=frame_title(3, 25))
        bar = with_truth[:TITLE_HEIGHT]
        assert _has(bar, ESTIMATE_COLOR) and _has(bar, TRUTH_COLOR)
        bar = render_overlay_grid(None, rig, est, skeleton.parents)[:TITLE_HEIGHT]
        assert _has(bar, ESTIMATE_COLOR) and not _has(bar, TRUTH_COLOR)
        # one small view: the grid widens so that the title and the legend fit
        one = make_ring_rig(1, image_size=(40, 30))
        grid = render_overlay_grid(None, one, est, skeleton.parents, truth=est,
                                   title=frame_title(100, 25))
        assert grid.shape[1] > 40 and _has(grid[:TITLE_HEIGHT], TRUTH_COLOR)

    def test_feature_mask_tint(self, skeleton, rig):
        views = np.full((4, H, W, 3), 100, np.uint8)
        masks = np.zeros((4, H, W), bool)
        masks[:, :, :10] = True  # a band at the left, away from the figure
        far = _pose(skeleton, shift=(0.0, 0.0, 60.0))
        grid = render_overlay_grid(views, rig, far, skeleton.parents, masks=masks)
        x0, y0 = panel_origin(3, (W, H), 2)
        expect = np.round(0.65 * 100 + 0.35 * np.array(MASK_TINT))
        np.testing.assert_allclose(grid[y0 + H - 2, x0 + 2], expect, atol=1)
        assert (grid[y0 + H - 2, x0 + 40] == 100).all()

    def test_grey_and_float_views(self, skeleton, rig):
        est = _pose(skeleton, shift=(0.0, 0.0, 60.0))
        sil = torch.zeros(4, H, W, dtype=torch.bool)
        sil[:, 50:] = True
        grid = render_overlay_grid(sil, rig, est, skeleton.parents)
        assert (grid[TITLE_HEIGHT + 55, 5] == 255).all() and (grid[TITLE_HEIGHT + 30, 5] == 0).all()
        grid = render_overlay_grid(torch.full((4, H, W, 3), 0.5), rig, est, skeleton.parents)
        assert abs(int(grid[TITLE_HEIGHT + 30, 40, 0]) - 128) <= 1

    def test_exception(self, skeleton, rig):
        est = _pose(skeleton)
        P = skeleton.parents
        with pytest.raises(ValueError, match="views"):
            render_overlay_grid(np.zeros((3, H, W, 3), np.uint8), rig, est, P)
        with pytest.raises(ValueError, match="views"):
            render_overlay_grid(np.zeros((4, H + 1, W, 3), np.uint8), rig, est, P)
        with pytest.raises(ValueError, match="estimate"):
            render_overlay_grid(None, rig, est[None], P)
        bad = est.clone()
        bad[2, 0] = float("nan")
        with pytest.raises(ValueError, match="estimate"):
            render_overlay_grid(None, rig, bad, P)
        with pytest.raises(ValueError, match="parents"):
            render_overlay_grid(None, rig, est, P[:-1])
        with pytest.raises(ValueError, match="truth_parents"):
            render_overlay_grid(None, rig, est, P, truth=est[:5])
        with pytest.raises(ValueError, match="masks"):
            render_overlay_grid(None, rig, est, P, masks=np.zeros((2, H, W), bool))
        with pytest.raises(ValueError, match="labels"):
            render_overlay_grid(None, rig, est, P, labels=["a"])
        for scale in (0, -1.0, float("inf")):
            with pytest.raises(ValueError, match="scale"):
                render_overlay_grid(None, rig, est, P, scale=scale)


class TestWriteOverlayGrid:
    def test_round_trip(self, tmp_path, skeleton, rig):
        grid = render_overlay_grid(None, rig, _pose(skeleton), skeleton.parents)
        path = write_overlay_grid(tmp_path / "g.png", grid)
        assert np.array_equal(np.asarray(Image.open(path).convert("RGB")), grid)
        assert [p.name for p in tmp_path.iterdir()] == ["g.png"]  # no temporary file left

    def test_exception(self, tmp_path):
        with pytest.raises(ValueError, match="grid"):
            write_overlay_grid(tmp_path / "g.png", np.zeros((4, 4), np.uint8))
        with pytest.raises(ValueError, match="grid"):
            write_overlay_grid(tmp_path / "g.png", np.zeros((4, 4, 3)))
        with pytest.raises(ValueError, match="path"):
            write_overlay_grid(tmp_path / "g.unknownformat", np.zeros((4, 4, 3), np.uint8))
        assert list(tmp_path.iterdir()) == []


class TestTrackOverlayFrames:
    def _sequence(self, skeleton, rig, T=120):
        from types import SimpleNamespace

        theta = skeleton.zero_pose((T,))
        with torch.no_grad():
            pos = skeleton(theta).positions
        sil = torch.zeros(rig.num_cameras, H, W, dtype=torch.bool)
        gt = SimpleNamespace(positions=pos)
        seq = SimpleNamespace(
            rig=rig, fps=25.0, ground_truth=gt,
            frame=lambda t: SimpleNamespace(images=None, silhouettes=sil, positions=pos[t]))
        return seq, theta

    def test_cardinality_one_size_for_every_frame(self, skeleton, rig):
        from torchmocap.viz.overlays import track_overlay_frames

        seq, theta = self._sequence(skeleton, rig)
        out = list(track_overlay_frames(seq, skeleton, theta, [0, 9, 10, 111]))
        assert [t for t, _ in out] == [0, 9, 10, 111]
        assert len({g.shape for _, g in out}) == 1  # titles differ, sizes do not
        for _, g in out:
            assert _has(g[:TITLE_HEIGHT], TRUTH_COLOR) and _has(g[TITLE_HEIGHT:], ESTIMATE_COLOR)

    def test_exception(self, skeleton, rig):
        from torchmocap.viz.overlays import track_overlay_frames

        seq, theta = self._sequence(skeleton, rig, T=3)
        with pytest.raises(ValueError, match="frames"):
            list(track_overlay_frames(seq, skeleton, theta, [0, 3]))
        seq.rig = None
        with pytest.raises(ValueError, match="rig"):
            list(track_overlay_frames(seq, skeleton, theta, [0]))
