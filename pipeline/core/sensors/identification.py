"""Crater identification, false matches and the selection of the craters used per frame.

Every function takes arrays over one frame's visible craters (in a fixed order, the caller's
crater-id order) and its own random stream, so results do not depend on processing order.
"""

from __future__ import annotations

import numpy as np


def identify(rng: np.random.Generator, n_visible: int, p_identify: float) -> np.ndarray:
    """Mask of identified craters: each visible crater independently with probability p."""
    return rng.random(n_visible) < p_identify


def false_matches(rng: np.random.Generator, unit: np.ndarray, identified: np.ndarray,
                  share: float) -> np.ndarray:
    """Index of the catalogue crater each visible crater is matched to (its own index when the
    match is right). Each identified crater is mismatched with probability `share`, to its nearest
    other visible crater (angular distance of the unit position vectors `unit`, (N, 3))."""
    matched = np.arange(unit.shape[0])
    wrong = identified & (rng.random(unit.shape[0]) < share)
    if unit.shape[0] < 2 or not wrong.any():
        return matched
    idx = np.flatnonzero(wrong)
    cos_sep = unit[idx] @ unit.T
    cos_sep[np.arange(idx.size), idx] = -np.inf
    matched[idx] = np.argmax(cos_sep, axis=1)
    return matched


def select_used(rng: np.random.Generator, identified: np.ndarray, cap: int | None, strategy: str,
                diam_km: np.ndarray, rho_m: np.ndarray, pixel_uv: np.ndarray, image_size_px: int
                ) -> np.ndarray:
    """Mask of the identified craters used for estimation, at most `cap` of them (None: all).

    Strategies: `random` (the paper's), `largest` diameter, `nearest` measured range, and `spread`:
    one crater per cell of a ceil(sqrt(cap))^2 grid over the image, cells and then the rest taken in
    random order, which spreads the craters over the image for better geometry.
    """
    cand = np.flatnonzero(identified)
    if cap is None or cand.size <= cap:
        return identified.copy()
    if strategy == "random":
        chosen = rng.permutation(cand)[:cap]
    elif strategy == "largest":
        chosen = cand[np.argsort(-diam_km[cand], kind="stable")[:cap]]
    elif strategy == "nearest":
        chosen = cand[np.argsort(rho_m[cand], kind="stable")[:cap]]
    elif strategy == "spread":
        grid = int(np.ceil(np.sqrt(cap)))
        ij = np.clip((pixel_uv[cand] / image_size_px * grid).astype(int), 0, grid - 1)
        cell = ij[:, 0] * grid + ij[:, 1]
        key = rng.random(cand.size)
        order = np.lexsort((key, cell))
        first = np.ones(cand.size, bool)
        first[1:] = cell[order[1:]] != cell[order[:-1]]
        heads, rest = order[first], order[~first]
        ranked = np.concatenate([heads[np.argsort(key[heads])], rest[np.argsort(key[rest])]])
        chosen = cand[ranked[:cap]]
    else:
        raise ValueError(f"unknown selection strategy {strategy!r}")
    used = np.zeros_like(identified)
    used[chosen] = True
    return used
