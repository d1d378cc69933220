"""2D worlds for the neural memory (thesis section 4.4.2): agents walking on images.

An *environment* is an S x S RGB image (values in [-1, 1]): a crop of a natural image shipped with
scikit-image (``skimage.data``; only the images bundled with the package, never a download), a
face of its LFW subset, or a procedural top-down floor plan (rooms, walls, doors, textured floors -
planks, tiles, carpet -, rugs and furniture, generated from a seed; the thesis' HoME-2D floor plans
are rendered furnished rooms, which a flat-coloured plan is not). Test environments come from images and seeds that training
never sees (:data:`TRAIN_IMAGES` / :data:`TEST_IMAGES`, floor-plan seeds offset by 10^6).

An *agent* walks ``steps`` steps: at each it observes the q x q patch centred on its position,
turned to its heading (``torch.rot90``: headings are multiples of 90 deg, so the rotation is
exact on the pixel grid - a deviation from the thesis' +-45 deg agent, whose rotations need
interpolation), masked by its view field (``square``: the whole patch, 360 deg, translation
only - thesis agent A^s; ``front``: the front half of the patch, 180 deg, the agent turns by
+-90 deg - thesis agent A^c), then moves forward 1/4..3/4 of its view field's depth (thesis 4.4.2: 2..6 px for the 8 px deep
front view, 3..11 px for the 15 px square view) (turning agents) or
in one of four directions (square agents), staying inside the image.

Poses are (row, col, k): the patch centre in image pixels and the heading k (k x 90 deg, counter-
clockwise). The allocentric frame is the first observation's: pose t in it is the offset of
the centre rotated by -k_0, and the heading k_t - k_0 (:func:`allocentric`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Agent2D", "AGENTS", "TRAIN_IMAGES", "TEST_IMAGES", "environment", "walk", "allocentric", "make_batch",
           "floor_plan", "view_mask", "KINDS"]

TRAIN_IMAGES = ("astronaut", "coffee", "chelsea", "rocket", "hubble_deep_field", "immunohistochemistry", "retina",
                "colorwheel", "camera", "coins", "clock", "grass", "brick", "page")
TEST_IMAGES = ("cat", "moon", "horse", "gravel", "text", "cell", "logo")
"""Bundled scikit-image pictures used for training / testing (disjoint)."""

_CACHE: dict = {}


def _image(name: str) -> np.ndarray:
    """(H, W, 3) float32 in [0, 1] of a bundled scikit-image picture."""
    if name not in _CACHE:
        import skimage.data as d
        im = np.asarray(getattr(d, name)(), dtype=np.float32)
        if im.ndim == 2:
            im = np.repeat(im[..., None], 3, axis=2)
        im = im[..., :3]
        _CACHE[name] = im / max(float(im.max()), 1e-6)
    return _CACHE[name]


def _faces() -> np.ndarray:
    if "lfw" not in _CACHE:
        import skimage.data as d
        f = np.asarray(d.lfw_subset(), np.float32)       # (200, 25, 25) grey faces in [0, 1]
        _CACHE["lfw"] = f / max(float(f.max()), 1e-6)
    return _CACHE["lfw"]


def _floor_texture(h: int, w: int, base: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(h, w, 3) float32 floor of one room around the colour ``base``: wooden planks (boards of 2-4 px with
    their own shade, staggered joints, grain), tiles (3-6 px, grout lines, a shade per tile) or carpet
    (smoothed noise). Per-plank / per-tile shades make the pattern aperiodic: a view can be placed on it by
    its content, as on the thesis' rendered HoME floors (flat-coloured floors cannot be: a raw-pixel search
    at the true memory placed 12 % of the steps within 1 px on them, against 81-87 % on faces and pictures)."""
    import cv2
    kind = int(rng.integers(3))
    shade = np.ones((h, w), np.float32)
    if kind == 0:                      # planks, along rows or columns
        along_rows = bool(rng.integers(2))
        H, W = (h, w) if along_rows else (w, h)
        t = int(rng.integers(2, 5))
        plank = np.arange(H) // t
        length = int(rng.integers(6, 14))
        offs = rng.integers(0, length, plank.max() + 1)
        seg = (np.arange(W)[None, :] + offs[plank][:, None]) // length            # board index along the plank
        ids = plank[:, None] * 1000 + seg
        _, inv = np.unique(ids, return_inverse=True)
        shade = rng.uniform(0.75, 1.2, inv.max() + 1)[inv.reshape(H, W)].astype(np.float32)
        shade *= 1.0 + 0.06 * rng.standard_normal(W).astype(np.float32)[None, :]  # grain
        shade[(np.arange(H) % t) == t - 1] *= 0.8                                 # gaps between planks
        shade = shade if along_rows else shade.T
    elif kind == 1:                    # tiles with grout
        t = int(rng.integers(3, 7))
        tr, tc = np.arange(h) // t, np.arange(w) // t
        shade = rng.uniform(0.8, 1.15, (tr.max() + 1, tc.max() + 1))[tr[:, None], tc[None, :]].astype(np.float32)
        grout = ((np.arange(h) % t) == 0)[:, None] | ((np.arange(w) % t) == 0)[None, :]
        shade[grout] = float(rng.uniform(0.45, 0.7))
    else:                              # carpet: smoothed noise
        n = rng.standard_normal((h, w)).astype(np.float32)
        n = cv2.GaussianBlur(n, (0, 0), float(rng.uniform(0.8, 1.6)))
        shade = 1.0 + 0.5 * n / max(float(n.std()), 1e-6) * 0.3
    return np.clip(base[None, None, :] * shade[..., None], 0.0, 1.0).astype(np.float32)


def floor_plan(size: int, rng: np.random.Generator) -> np.ndarray:
    """(size, size, 3) float32 in [0, 1]: a top-down floor plan - rooms split by walls with doors, textured
    floors (:func:`_floor_texture`), rugs and furniture blocks with dark outlines."""
    img = np.zeros((size, size, 3), np.float32)
    rooms = [(0, 0, size, size)]
    for _ in range(int(rng.integers(2, 5))):
        k = int(rng.integers(len(rooms)))
        r0, c0, r1, c1 = rooms.pop(k)
        if (r1 - r0) >= (c1 - c0) and r1 - r0 > 12:
            cut = int(rng.integers(r0 + 6, r1 - 6))
            rooms += [(r0, c0, cut, c1), (cut, c0, r1, c1)]
        elif c1 - c0 > 12:
            cut = int(rng.integers(c0 + 6, c1 - 6))
            rooms += [(r0, c0, r1, cut), (r0, cut, r1, c1)]
        else:
            rooms.append((r0, c0, r1, c1))
    for r0, c0, r1, c1 in rooms:
        img[r0:r1, c0:c1] = _floor_texture(r1 - r0, c1 - c0, rng.uniform(0.3, 0.95, 3), rng)
        if r1 - r0 > 9 and c1 - c0 > 9 and rng.random() < 0.5:          # a rug
            h, w = int(rng.integers(4, r1 - r0 - 3)), int(rng.integers(4, c1 - c0 - 3))
            a, b = int(rng.integers(r0 + 1, r1 - h)), int(rng.integers(c0 + 1, c1 - w))
            img[a:a + h, b:b + w] = _floor_texture(h, w, rng.uniform(0.2, 0.9, 3), rng)
            img[a, b:b + w] = img[a + h - 1, b:b + w] = img[a:a + h, b] = img[a:a + h, b + w - 1] = rng.uniform(0.1, 0.5, 3)
        for _ in range(int(rng.integers(1, 4))):
            h, w = int(rng.integers(2, 7)), int(rng.integers(2, 7))
            if r1 - r0 > h + 2 and c1 - c0 > w + 2:
                a, b = int(rng.integers(r0 + 1, r1 - h)), int(rng.integers(c0 + 1, c1 - w))
                img[a:a + h, b:b + w] = rng.uniform(0.0, 0.6, 3)
                if h > 2 and w > 2:                                          # outline + a lighter top
                    img[a + 1:a + h - 1, b + 1:b + w - 1] = np.clip(img[a, b] + rng.uniform(0.1, 0.3), 0, 1)
        wall = (0.08, 0.08, 0.1)
        img[r0, c0:c1] = img[r1 - 1, c0:c1] = wall
        img[r0:r1, c0] = img[r0:r1, c1 - 1] = wall
        for side in range(2):       # doors
            if side == 0 and c1 - c0 > 6:
                d = int(rng.integers(c0 + 2, c1 - 3))
                img[r1 - 1, d:d + 3] = img[min(r1, size - 1) - 2, d:d + 3]
            elif r1 - r0 > 6:
                d = int(rng.integers(r0 + 2, r1 - 3))
                img[d:d + 3, c1 - 1] = img[d:d + 3, max(c1 - 2, 0)]
    return img


KINDS = ("picture", "face", "floor plan")
"""The kinds of 2D environments, in the order :func:`environment` draws them (40 %, 30 %, 30 %)."""


def environment(rng: np.random.Generator, size: int, split: str = "train", with_kind: bool = False):
    """(3, size, size) float32 in [-1, 1]: a random environment of ``split`` (see the module docstring);
    ``with_kind``: (image, index of its kind in :data:`KINDS`)."""
    import cv2
    u = rng.random()
    kind = 0 if u < 0.4 else (1 if u < 0.7 else 2)
    if kind == 0:
        names = TRAIN_IMAGES if split == "train" else TEST_IMAGES
        im = _image(names[int(rng.integers(len(names)))])
        h, w = im.shape[:2]
        s = int(rng.integers(max(size, min(h, w) // 6), max(size + 1, min(h, w) // 2)))
        r, c = int(rng.integers(0, h - s + 1)), int(rng.integers(0, w - s + 1))
        img = cv2.resize(im[r:r + s, c:c + s], (size, size), interpolation=cv2.INTER_AREA)
    elif kind == 1:
        faces = _faces()
        idx = rng.integers(0, 150) if split == "train" else rng.integers(150, 200)
        g = cv2.resize(faces[int(idx)], (size, size), interpolation=cv2.INTER_CUBIC)
        tint = rng.uniform(0.7, 1.0, 3).astype(np.float32)
        img = np.clip(g[..., None] * tint, 0, 1)
    else:
        seed = int(rng.integers(0, 10**6)) + (0 if split == "train" else 10**6)
        img = floor_plan(size, np.random.default_rng(seed))
    out = np.ascontiguousarray(np.transpose(img * 2.0 - 1.0, (2, 0, 1))).astype(np.float32)
    return (out, kind) if with_kind else out


@dataclass(frozen=True)
class Agent2D:
    """An agent's view and motion (see the module docstring)."""

    name: str
    view: int
    """Side q of the observed patch, pixels (odd)."""
    field: str
    """``square`` (360 deg) or ``front`` (the front half)."""
    turns: bool
    """Turns by +-90 deg (and moves forward) instead of translating in four directions."""


AGENTS = {"square": Agent2D("square", 15, "square", False), "front": Agent2D("front", 15, "front", True)}


def view_mask(agent: Agent2D) -> np.ndarray:
    """(q, q) bool: the patch pixels the agent sees (heading up = row 0 side)."""
    q = agent.view
    m = np.ones((q, q), bool)
    if agent.field == "front":
        m[q // 2 + 1:] = False
    return m


def _patch(img: np.ndarray, r: int, c: int, k: int, q: int) -> np.ndarray:
    h = q // 2
    p = img[:, r - h:r + h + 1, c - h:c + h + 1]
    return np.rot90(p, -k, axes=(1, 2))   # turn the world so the agent's heading points up


def walk(img: np.ndarray, agent: Agent2D, steps: int, rng: np.random.Generator):
    """(observations (T, 3, q, q) with unseen pixels 0, poses (T, 3) int: row, col, heading k)."""
    S = img.shape[1]
    q, h = agent.view, agent.view // 2
    r, c = int(rng.integers(h, S - h)), int(rng.integers(h, S - h))
    k = int(rng.integers(4)) if agent.turns else 0
    mask = view_mask(agent).astype(np.float32)
    obs, poses = [], []
    dirs = [(-1, 0), (0, -1), (1, 0), (0, 1)]       # heading k: up, left, down, right (k x 90 deg CCW)
    reach = q // 2 + 1 if agent.field == "front" else q      # depth of the view field, pixels
    for t in range(steps):
        obs.append(_patch(img, r, c, k, q) * mask)
        poses.append((r, c, k))
        for _ in range(20):
            d = int(rng.integers(max(1, reach // 4), 3 * reach // 4 + 1))
            if agent.turns:
                k2 = (k + int(rng.choice([-1, 0, 0, 1]))) % 4
                dr, dc = dirs[k2]
            else:
                k2 = 0
                dr, dc = dirs[int(rng.integers(4))]
            r2, c2 = r + dr * d, c + dc * d
            if h <= r2 < S - h and h <= c2 < S - h:
                r, c, k = r2, c2, k2
                break
        else:
            if agent.turns:
                k = (k + 2) % 4
    return np.stack(obs).astype(np.float32), np.asarray(poses, np.int64)


def allocentric(poses: np.ndarray) -> np.ndarray:
    """(T, 3) poses in the first observation's frame: offset (row, col) rotated by -k_0, heading k - k_0."""
    r0, c0, k0 = poses[0]
    d = poses[:, :2] - poses[0, :2]
    out = np.zeros_like(poses)
    for t, (dr, dc) in enumerate(d):
        for _ in range(int(k0) % 4):                # rotate the offset by -90 deg per step of k0
            dr, dc = dc, -dr
        out[t, :2] = (dr, dc)
    out[:, 2] = (poses[:, 2] - k0) % 4
    return out


def make_batch(rng: np.random.Generator, batch: int, agent: Agent2D, steps: int, size: int, split: str = "train",
               with_kinds: bool = False):
    """(images (B, 3, S, S), observations (B, T, 3, q, q), poses (B, T, 3) image frame, allocentric poses);
    ``with_kinds``: and (B,) the environments' kinds (indices into :data:`KINDS`)."""
    imgs, obs, poses, allo, kinds = [], [], [], [], []
    for _ in range(batch):
        img, kind = environment(rng, size, split, with_kind=True)
        kinds.append(kind)
        o, p = walk(img, agent, steps, rng)
        imgs.append(img)
        obs.append(o)
        poses.append(p)
        allo.append(allocentric(p))
    out = (np.stack(imgs), np.stack(obs), np.stack(poses), np.stack(allo))
    return (*out, np.asarray(kinds, np.int64)) if with_kinds else out
