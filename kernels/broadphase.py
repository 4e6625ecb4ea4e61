"""The broadphase: per CSR pair, decode (i, j) and test the slightly inflated yawed boxes.

Pairs are enumerated per scene as CSR: scene s owns pair indices [pair_start[s], pair_start[s+1])
= its count*(count-1)/2 pairs (i < j) in row-major order. A pair that passes appends its two
(pair, direction) items to the narrowphase's dense work list with one ``atomic_add`` on a device
counter (zeroed by ``table_contact``, launched just before). The list's order is arbitrary on
CUDA; every item's sums land in the pair's slots (``pair_item[pair]``: the position of its
direction-0 item), so results do not depend on it.
"""

# Warp needs typed constructors (float(0.0), int(0)) for variables a loop modifies.
# ruff: noqa: UP018

from __future__ import annotations

import warp as wp

from physcene.kernels.boxes import boxes_meet

wp.set_module_options({"enable_backward": False})

__all__ = ["broadphase_items", "decode_pair", "find_scene"]


@wp.func
def find_scene(pair_start: wp.array(dtype=wp.int32), n_scene: int, k: int):
    """The scene s with pair_start[s] <= k < pair_start[s+1] (binary search over the CSR)."""
    lo = int(0)
    hi = n_scene - 1
    while lo < hi:
        mid = (lo + hi + 1) // 2
        if pair_start[mid] <= k:
            lo = mid
        else:
            hi = mid - 1
    return lo



@wp.func
def decode_pair(pair_start: wp.array(dtype=wp.int32), count: wp.array(dtype=wp.int32), n_slot: int, k: int):
    """Slots (a, b) of CSR pair k: scene by binary search, then the row-major (i < j) of its pairs."""
    s = find_scene(pair_start, count.shape[0], k)
    n = int(count[s])
    r = k - int(pair_start[s])
    # row-major (i < j): row i starts at i*n - i*(i+1)/2; float guess, then exact integer fix-up
    i = int(float(n) - 0.5 - wp.sqrt((float(n) - 0.5) * (float(n) - 0.5) - 2.0 * float(r)))
    i = wp.clamp(i, 0, n - 2)
    while i > 0 and i * n - i * (i + 1) // 2 > r:
        i -= 1
    while (i + 1) * n - (i + 1) * (i + 2) // 2 <= r:
        i += 1
    j = r - (i * n - i * (i + 1) // 2) + i + 1
    return s * n_slot + i, s * n_slot + j



@wp.kernel
def broadphase_items(
    pair_start: wp.array(dtype=wp.int32),  # (S+1,)
    count: wp.array(dtype=wp.int32),  # (S,)
    n_slot: int,
    poses: wp.array(dtype=wp.vec4),  # (S*N,) x, y, z, yaw (cm, rad)
    sizes: wp.array(dtype=wp.vec3),  # (S*N,) w, d, h (cm)
    margin: float,
    pair_a_out: wp.array(dtype=wp.int32),  # (T,) slot of the lower-index object
    pair_b_out: wp.array(dtype=wp.int32),  # (T,)
    pair_hit_out: wp.array(dtype=wp.int32),  # (T,) 1 if the inflated boxes overlap
    pair_item_out: wp.array(dtype=wp.int32),  # (T,) position of the pair's first item (hit pairs)
    n_item: wp.array(dtype=wp.int32),  # (1,) items appended so far; 0 on entry
    items_out: wp.array(dtype=wp.int32),  # (2T,) pair * 2 + direction, the first n_item[0] valid
):
    k = wp.tid()
    a, b = decode_pair(pair_start, count, n_slot, k)
    pair_a_out[k] = a
    pair_b_out[k] = b
    hit = boxes_meet(poses[a], sizes[a] * 0.5, poses[b], sizes[b] * 0.5, margin)
    pair_hit_out[k] = hit
    if hit != 0:
        first = wp.atomic_add(n_item, 0, 2)
        items_out[first] = 2 * k
        items_out[first + 1] = 2 * k + 1
        pair_item_out[k] = first
