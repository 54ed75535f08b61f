"""The analytic 3D vessel tree shared by the matching and end-to-end tests (LPS mm).

name -> (parent, Bezier control points); children start on their parent's end.
"""

TREE = {
    "trunk": (None, [(-30, 0, 45), (-18, 4, 30), (0, 5, 12)]),
    "left": ("trunk", [(0, 5, 12), (-15, 8, -8), (-28, 12, -32)]),
    "right": ("trunk", [(0, 5, 12), (12, 2, -2), (22, 0, -16)]),
    "right_a": ("right", [(22, 0, -16), (36, -4, -18), (50, -6, -26)]),
    "right_b": ("right", [(22, 0, -16), (20, 6, -34), (14, 10, -52)]),
}
RADIUS_MM = {"trunk": 2.0, "left": 1.4, "right": 1.6, "right_a": 1.2, "right_b": 1.2}
