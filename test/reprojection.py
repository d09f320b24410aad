"""Plain numpy + cv2 reprojection for tests that check depth/pose conventions (independent of geometry.py)."""
import numpy as np


def reproject(seq, j, T_i_j, min_z):
    """Where the pixels of frame j land in frame i, using the depth of j.

    Returns (map_x, map_y, z_in_i, valid): float32 remap grids for cv2.remap, the depth of each point in
    camera i, and the pixels with valid depth, in front of camera i (z > min_z) and inside frame i.
    """
    K = seq.K
    w, h = seq.size
    dj = seq.depth(j).astype(np.float64)
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    X = (np.linalg.inv(K) @ np.stack([u.ravel(), v.ravel(), np.ones(u.size)])) * dj.ravel()
    Xi = T_i_j[:3, :3] @ X + T_i_j[:3, 3:4]
    p = K @ Xi
    with np.errstate(divide='ignore', invalid='ignore'):
        mx = (p[0] / p[2]).reshape(h, w).astype(np.float32)
        my = (p[1] / p[2]).reshape(h, w).astype(np.float32)
    z_i = p[2].reshape(h, w)
    valid = (dj > 0) & (z_i > min_z) & (mx >= 0) & (mx <= w - 1) & (my >= 0) & (my <= h - 1)
    return mx, my, z_i, valid
