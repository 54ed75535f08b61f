"""2D centreline graphs on synthetic masks with known skeletons (exact counts, topology, radius)."""

from __future__ import annotations

import networkx as nx
import numpy as np
import pytest

import vesselcad as vc

VIEW = vc.CArmView(primary_deg=0.0, secondary_deg=0.0, sid_mm=1100.0, sod_mm=750.0,
                   pixel_spacing_mm=(0.3, 0.3), rows=256, cols=256)


def draw_tube(mask: np.ndarray, p, q, r: float) -> np.ndarray:
    """Pixels whose centre lies within ``r`` of the segment p-q (col, row)."""
    rr, cc = np.mgrid[: mask.shape[0], : mask.shape[1]]
    P = np.stack([cc, rr], -1).astype(float)
    p, q = np.asarray(p, float), np.asarray(q, float)
    d = q - p
    t = np.clip(((P - p) @ d) / (d @ d), 0, 1)
    mask |= np.linalg.norm(P - (p + t[..., None] * d), axis=-1) <= r
    return mask


def scene(vessels, catheters) -> np.ndarray:
    """Class image (1 vessel, 2 catheter drawn over it) of ``(p, q, r)`` tubes."""
    labels = np.zeros((256, 256), np.uint8)
    for kind, tubes in ((1, vessels), (2, catheters)):
        m = np.zeros((256, 256), bool)
        for p, q, r in tubes:
            draw_tube(m, p, q, r)
        labels[m] = kind
    return labels


def interior_radius(branch: vc.Branch2D, margin: float) -> float:
    """Median radius (px) away from the branch's ends."""
    s = np.r_[0, np.cumsum(np.linalg.norm(np.diff(branch.points_px, axis=0), axis=1))]
    keep = (s > margin) & (s < s[-1] - margin)
    return float(np.median(branch.radius_px[keep]))


def near(points: np.ndarray, p, tol: float) -> bool:
    return bool(np.min(np.linalg.norm(points - np.asarray(p, float), axis=1)) <= tol)


def test_y_bifurcation_counts_topology_radius():
    m = np.zeros((256, 256), bool)
    draw_tube(m, (128, 20), (128, 128), 5.5)
    draw_tube(m, (128, 128), (50, 225), 3.5)
    draw_tube(m, (128, 128), (205, 225), 3.5)
    g = vc.centreline_graph(m, VIEW)
    assert len(g.branch_points) == 1 and len(g.end_points) == 3 and len(g.branches) == 3
    assert g.is_tree()
    assert near(g.branch_points, (128, 128), 6.0)
    for p in ((128, 20), (50, 225), (205, 225)):
        assert near(g.end_points, p, 6.0)
    # Root: the widest end (the trunk); every branch runs away from it.
    assert np.allclose(g.landmarks[g.root].point_px, (128, 20), atol=6)
    assert all(b.start != g.root or b.end != g.root for b in g.branches)
    radii = sorted(interior_radius(b, 12.0) for b in g.branches)
    assert radii[0] == pytest.approx(3.5, abs=0.5)
    assert radii[1] == pytest.approx(3.5, abs=0.5)
    assert radii[2] == pytest.approx(5.5, abs=0.5)
    # mm at the isocentre: px * spacing * SOD / SID.
    b = g.branches[0]
    assert np.allclose(b.radius_mm, b.radius_px * 0.3 * 750.0 / 1100.0)
    # The spline follows the pixels.
    u = np.linspace(b.spline.t[3], b.spline.t[-4], 50)
    d = np.min(np.linalg.norm(b.spline(u)[:, None] - b.points_px[None], axis=-1), axis=1)
    assert d.max() < 1.5


def test_t_junction():
    m = np.zeros((256, 256), bool)
    draw_tube(m, (30, 60), (220, 60), 4.5)
    draw_tube(m, (128, 60), (128, 220), 3.5)
    g = vc.centreline_graph(m, VIEW)
    assert (len(g.branch_points), len(g.end_points), len(g.branches)) == (1, 3, 3)
    assert near(g.branch_points, (128, 60), 5.0)
    degrees = dict(g.graph.degree())
    assert sorted(degrees.values()) == [1, 1, 1, 3]
    stem = [b for b in g.branches if near(b.points_px, (128, 200), 3.0)][0]
    assert interior_radius(stem, 12.0) == pytest.approx(3.5, abs=0.5)


@pytest.mark.parametrize("first,second", [
    (((30, 30), (220, 220), 4.5), ((30, 220), (220, 30), 4.5)),  # 90 degrees: one 4-way node
    (((30, 128), (220, 128), 4.5), ((60, 30), (200, 230), 3.5)),  # 55 degrees: two 3-way nodes
])
def test_x_crossing_is_resolved_into_two_vessels(first, second):
    m = np.zeros((256, 256), bool)
    draw_tube(m, *first)
    draw_tube(m, *second)
    g = vc.centreline_graph(m, VIEW)
    assert len(g.branch_points) == 0
    assert len(g.end_points) == 4
    assert len(g.branches) == 2
    assert len(g.crossings) == 1
    assert g.is_tree()
    assert sorted(g.crossings[0].branches) == [0, 1]
    assert g.crossings[0].angle_deg > 30
    for b in g.branches:  # each branch runs straight through from one side to the other
        a, e = b.points_px[0], b.points_px[-1]
        t = (e - a) / np.linalg.norm(e - a)
        off = np.abs((b.points_px - a) @ np.array([-t[1], t[0]]))
        assert off.max() < 4.5  # within a radius, also across the crossing
        assert np.linalg.norm(e - a) > 180


def _binary_tree(levels: int = 4):
    """Segments of a planar binary tree with 2**levels - 1 branches (no overlaps)."""
    segs = []

    def grow(p, angle, length, r, level):
        q = p + length * np.array([np.sin(angle), np.cos(angle)])
        segs.append((p, q, r))
        if level + 1 < levels:
            for da in (-0.45, 0.45):
                grow(q, angle + da * (1.25 ** level), length * 0.62, max(r * 0.75, 1.6), level + 1)

    grow(np.array([256.0, 20.0]), 0.0, 150.0, 6.5, 0)
    return segs


def test_tree_with_15_branches():
    view = vc.CArmView(primary_deg=0.0, secondary_deg=0.0, sid_mm=1100.0, sod_mm=750.0,
                       pixel_spacing_mm=(0.2, 0.2), rows=512, cols=512)
    segs = _binary_tree(4)
    assert len(segs) == 15
    m = np.zeros((512, 512), bool)
    for p, q, r in segs:
        draw_tube(m, p, q, r)
    g = vc.centreline_graph(m, view)
    assert len(g.branches) == 15
    assert len(g.branch_points) == 7
    assert len(g.end_points) == 8 + 1  # leaves and the root
    assert g.is_tree()
    assert all(d in (1, 3) for _, d in g.graph.degree())
    # Every drawn junction and end is found.
    for _, q, r in segs:
        assert near(g.landmark_points, q, r + 4.0)
    assert near(g.landmark_points, segs[0][0], 4.0)
    # Rooted at the trunk; a branch point's depth is one more than its parent's.
    assert np.allclose(g.landmarks[g.root].point_px, segs[0][0], atol=4)
    depth = nx.single_source_shortest_path_length(g.graph, g.root)
    assert max(depth.values()) == 4
    for b in g.branches:
        assert depth[b.end] == depth[b.start] + 1
    # Radius of the trunk and of a leaf branch.
    trunk = [b for b in g.branches if b.start == g.root][0]
    assert interior_radius(trunk, 15.0) == pytest.approx(6.5, abs=0.5)


def test_catheter_gap_is_bridged_and_catheter_tip_is_the_root():
    labels = scene([((40, 128), (220, 128), 3.5)],
                   [((120, 0), (120, 250), 3.0),  # lies across the vessel: a gap in the vessel class
                    ((40, 40), (40, 122), 3.0)])  # its tip touches the left vessel end
    g0 = vc.centreline_graph(labels == 1, VIEW)
    assert len(g0.branches) == 2  # cut in two without the device classes
    g = vc.centreline_graph(labels == 1, VIEW, labels=labels)
    assert len(g.branches) == 1
    assert np.allclose(g.landmarks[g.root].point_px, (40, 128), atol=8)


def test_spurs_from_a_rough_edge_are_pruned():
    m = np.zeros((256, 256), bool)
    draw_tube(m, (20, 128), (235, 128), 5.5)
    rng = np.random.default_rng(3)
    for c in rng.integers(40, 215, 12):  # small bumps on the wall
        draw_tube(m, (c, 122), (c + 2, 121), 2.0)
    g = vc.centreline_graph(m, VIEW)
    assert len(g.branches) == 1 and len(g.branch_points) == 0


def test_empty_mask_gives_empty_graph():
    g = vc.centreline_graph(np.zeros((256, 256), bool), VIEW)
    assert g.branches == [] and g.landmarks == [] and g.root is None


def test_bad_input_names_the_argument():
    with pytest.raises(vc.ArgumentError, match="mask"):
        vc.centreline_graph(np.zeros((100, 100), bool), VIEW)
    with pytest.raises(vc.ArgumentError, match="mask"):
        vc.centreline_graph(np.zeros((256, 256, 3), bool), VIEW)
    with pytest.raises(vc.ArgumentError, match="view"):
        vc.centreline_graph(np.zeros((256, 256), bool), "LAO 30")
    with pytest.raises(vc.ArgumentError, match="labels"):
        vc.centreline_graph(np.zeros((256, 256), bool), VIEW, labels=np.zeros((10, 10), np.uint8))
    with pytest.raises(vc.ArgumentError, match="noise_px"):
        vc.centreline_graph(np.zeros((256, 256), bool), VIEW, noise_px=-1.0)


def test_root_at_a_catheter_tip_on_the_vessel_is_split_into_the_branch():
    # The catheter ends on a vessel that runs on past the ostium (a side branch leaving it the
    # other way, or the left main's two daughters in projection): no vessel end lies at the tip,
    # so the root is a node put into the branch at the tip, with the two vessels as its branches.
    labels = scene([((40, 150), (220, 150), 4.5)],
                   [((100, 0), (100, 144), 2.5)])  # comes from above, tip at the vessel's wall
    g = vc.centreline_graph(labels == 1, VIEW, labels=labels)
    root = g.landmarks[g.root]
    assert np.allclose(root.point_px, (100, 150), atol=3.0)
    assert root.degree == 2 and len(g.branches) == 2
    assert all(g.root == b.start for b in g.branches)  # both run from the ostium outward
    ends = sorted(float(g.landmarks[b.end].point_px[0]) for b in g.branches)
    assert ends[0] < 50 and ends[1] > 210


@pytest.mark.parametrize("catheter_end_row", [139, 125])
def test_root_ignores_a_piece_of_vessel_labelled_catheter(catheter_end_row):
    # A segmentation model labels 24 px of the vessel far from the ostium as catheter (120 px
    # from the ostium: nearer the vessel than the catheter's real end). The catheter itself comes
    # down from the image's top edge and ends 4 px above the vessel's left end (row 139), or
    # stops 20 px short of it (row 125, a model's labels leaving background between): its end is
    # the tip, and the root is the vessel's left end below it, not the piece on the vessel.
    labels = scene([((60, 150), (220, 150), 4.5)],
                   [((60, 0), (60, catheter_end_row), 2.5), ((176, 150), (200, 150), 3.5)])
    g = vc.centreline_graph(labels == 1, VIEW, labels=labels)
    assert np.allclose(g.landmarks[g.root].point_px, (62, 150), atol=6.0)


def test_root_of_a_cannulated_vessel_is_where_the_catheter_enters():
    # A coronary sinus catheter runs 60 px inside the vessel: its tip is on the skeleton, but the
    # ostium is the vessel end where it enters (the vessel mask holds most of the catheter there).
    labels = scene([((40, 128), (220, 128), 6.0)],
                   [((0, 60), (40, 128), 2.0), ((40, 128), (100, 128), 2.0)])
    g = vc.centreline_graph(labels == 1, VIEW, labels=labels)
    assert len(g.branches) == 1
    assert np.allclose(g.landmarks[g.root].point_px, (40, 128), atol=8)


def test_root_is_the_end_nearest_a_catheter_that_the_contrast_has_not_reached():
    # The proximal vessel next to the catheter tip is not (yet) filled: the vessel starts 80 px
    # from the tip. Its end there is the root, although the far end is wider.
    labels = scene([((100, 128), (200, 128), 3.0), ((200, 128), (230, 128), 6.0)],
                   [((20, 0), (20, 128), 2.5)])
    g = vc.centreline_graph(labels == 1, VIEW, labels=labels)
    assert np.allclose(g.landmarks[g.root].point_px, (100, 128), atol=6)


def test_root_at_the_balloon_when_the_catheter_before_it_is_labelled_vessel():
    # A coronary sinus (r 6 px) with an occlusion balloon (ellipse 40 x 24 px = 31 mm² at the
    # isocentre, centred at (150, 150)) on the catheter that carries it. The model labels the
    # catheter's last 130 px vessel (a thin vessel from (20, 60) joining the sinus at its start):
    # the catheter labelled as such ends 140 px from the balloon. The root is where the balloon begins, on the
    # sinus's centreline, not the end of the catheter-coloured "vessel".
    labels = scene([((100, 150), (240, 150), 6.0), ((20, 60), (100, 150), 2.5)],
                   [((0, 0), (20, 60), 2.5)])
    rr, cc = np.mgrid[:256, :256]
    labels[((cc - 150) / 20.0) ** 2 + ((rr - 150) / 12.0) ** 2 <= 1.0] = 3
    g = vc.centreline_graph(labels == 1, VIEW, labels=labels)
    assert np.allclose(g.landmarks[g.root].point_px, (130, 150), atol=8.0)
    # A small balloon-coloured speck (a model's false positive, 1.2 mm² here) is no balloon: the
    # root stays at the catheter's end.
    labels[labels == 3] = 1
    labels[((cc - 150) / 4.5) ** 2 + ((rr - 150) / 4.5) ** 2 <= 1.0] = 3
    g = vc.centreline_graph(labels == 1, VIEW, labels=labels)
    assert np.linalg.norm(g.landmarks[g.root].point_px - (20, 60)) < 12.0


def test_a_given_catheter_tip_roots_the_tree():
    # Two catheters enter from the top edge; the labels alone make the one ending on the vessel's
    # right end the tip. A tip passed in (the phase matching's key point, confirmed by the other
    # view) at the other catheter's end roots the tree at the vessel's left end instead.
    labels = scene([((60, 150), (220, 150), 4.5)],
                   [((60, 0), (60, 139), 2.5), ((220, 0), (220, 139), 2.5)])
    g = vc.centreline_graph(labels == 1, VIEW, labels=labels, tip=(60.0, 139.0))
    assert np.allclose(g.landmarks[g.root].point_px, (62, 150), atol=6.0)
    g = vc.centreline_graph(labels == 1, VIEW, labels=labels, tip=(220.0, 139.0))
    assert np.allclose(g.landmarks[g.root].point_px, (218, 150), atol=6.0)
    with pytest.raises(vc.ArgumentError, match="tip"):
        vc.centreline_graph(labels == 1, VIEW, labels=labels, tip=(np.nan, 3.0))
    with pytest.raises(vc.ArgumentError, match="tip"):
        vc.centreline_graph(labels == 1, VIEW, labels=labels, tip="ostium")
    with pytest.raises(vc.ArgumentError, match="tip"):
        vc.centreline_graph(labels == 1, VIEW, tip=(60.0, 139.0))


def test_root_at_a_catheter_tip_a_catheter_width_off_the_vessel():
    # The catheter's last pixels cover the vessel's first ones (its label wins): the tip ends 5 px
    # above the vessel's wall, 10 px from the centreline (more than a radius plus TIP_MARGIN_PX
    # from it). The vessel pixel nearest the tip stands for it: the root is put into the branch
    # below the tip, not at a vessel end 55 px away.
    labels = scene([((40, 150), (220, 150), 4.5)],
                   [((100, 0), (100, 138), 2.5)])
    assert (labels[141:145, 100] == 0).all()  # background between the catheter and the vessel
    g = vc.centreline_graph(labels == 1, VIEW, labels=labels, tip=(100.0, 140.0))
    root = g.landmarks[g.root]
    assert np.allclose(root.point_px, (100, 150), atol=3.0)
    assert root.degree == 2


def test_root_at_the_tip_ignores_the_end_of_another_skeleton_piece():
    # A separate piece of vessel (a stub the segmentation cut off) ends 12 px from the catheter tip;
    # the tree's own skeleton runs past the tip. The stub's end says nothing about the tree's root:
    # the tree is rooted at the tip, not at its own end nearest the tip (55 px away).
    labels = scene([((40, 150), (220, 150), 4.5), ((90, 139), (40, 100), 2.5)],
                   [((100, 0), (100, 144), 2.5)])
    g = vc.centreline_graph(labels == 1, VIEW, labels=labels, tip=(100.0, 144.0))
    assert nx.number_connected_components(g.graph) == 2  # the stub is a piece of its own
    assert np.allclose(g.landmarks[g.root].point_px, (100, 150), atol=3.0)
