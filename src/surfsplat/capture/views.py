"""Which views go through the network together: context sets that cover a capture.

    passes = context_sets(cameras.centers, views_per_pass=2, ordered=True)   # [[0, 1], [1, 2], ...]

The network matches the views of one forward pass against each other (the multi-view transformer
and the plane-sweep cost volume), so a pass must hold views that overlap. Along an ordered capture
(a video, a walk) neighbours in time overlap most: sliding windows of `views_per_pass` consecutive
views, each sharing its first view with the previous window's last, cover every view, and the
passes overlap so fusion stitches them. An unordered set of photos is first put in order along
the camera graph: a nearest-neighbour walk over the camera centres from the first camera.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..utils.checks import SurfSplatInputError


def nearest_neighbour_order(centers: Tensor) -> list[int]:  # centers [N, 3]
    """A walk over the cameras that always steps to the nearest camera not yet visited, from camera 0."""
    n = len(centers)
    distance = torch.cdist(centers.double(), centers.double())
    order, seen = [0], torch.zeros(n, dtype=torch.bool)
    seen[0] = True
    for _ in range(n - 1):
        d = distance[order[-1]].masked_fill(seen, float("inf"))
        nxt = int(d.argmin())
        order.append(nxt)
        seen[nxt] = True
    return order


def context_sets(centers: Tensor, views_per_pass: int, ordered: bool) -> list[list[int]]:  # centers [N, 3]
    """Index lists of the views of each forward pass (each sorted), covering every view.

    N <= views_per_pass: one pass with every view (the classic reconstruction). Otherwise windows
    of views_per_pass views along the order (input order when `ordered`, else the nearest-neighbour
    walk), stepping views_per_pass - 1 views, the last window ending at the last view."""
    n = len(centers)
    if views_per_pass < 2:
        raise SurfSplatInputError(f"views_per_pass: the model matches views, expected at least 2, got {views_per_pass}")
    if n < 2:
        raise SurfSplatInputError(f"views: expected at least 2 views, got {n}")
    if n <= views_per_pass:
        return [list(range(n))]
    order = list(range(n)) if ordered else nearest_neighbour_order(centers)
    step = views_per_pass - 1
    starts = list(range(0, n - views_per_pass + 1, step))
    if starts[-1] + views_per_pass < n:
        starts.append(n - views_per_pass)
    return [sorted(order[s : s + views_per_pass]) for s in starts]
