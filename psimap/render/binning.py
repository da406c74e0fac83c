"""Stage 2 of the renderer (SPEC.md) in torch: (tile, surfel) pairs, sorted per tile front to back."""
from __future__ import annotations

from dataclasses import dataclass

import torch

TILE = 16


@dataclass
class Bins:
    """Tile lists. Pairs are sorted by tile, then depth_key, then surfel index.

    surfel_ids: [P] int64, tile_ids: [P] int64, offsets: [tiles_x * tiles_y + 1] int64 (tile t owns
    pairs offsets[t]:offsets[t+1]); tiles are numbered row-major (t = ty * tiles_x + tx).
    """

    surfel_ids: torch.Tensor
    tile_ids: torch.Tensor
    offsets: torch.Tensor
    tiles_x: int
    tiles_y: int

    @property
    def counts(self) -> torch.Tensor:
        """[tiles] number of surfels per tile."""
        return self.offsets[1:] - self.offsets[:-1]


def bin_surfels(box: torch.Tensor, depth_key: torch.Tensor, width: int, height: int,
                tile: int = TILE) -> Bins:
    """Expand pixel boxes to (tile, surfel) pairs and sort them per tile by depth.

    box: [N, 4] int32 (x0, y0, x1, y1) half-open pixel boxes (empty box = not binned),
    depth_key: [N] sort key. Ties in depth keep the lower surfel index first.
    """
    device = box.device
    tiles_x = (width + tile - 1) // tile
    tiles_y = (height + tile - 1) // tile
    box = box.long()
    nonempty = (box[:, 2] > box[:, 0]) & (box[:, 3] > box[:, 1])
    ids = torch.nonzero(nonempty).squeeze(1)
    b = box[ids]
    tx0, ty0 = b[:, 0] // tile, b[:, 1] // tile
    tx1, ty1 = (b[:, 2] - 1) // tile, (b[:, 3] - 1) // tile     # inclusive
    nx, ny = tx1 - tx0 + 1, ty1 - ty0 + 1
    per = nx * ny
    total = int(per.sum()) if ids.numel() else 0
    if total == 0:
        empty = torch.zeros(0, dtype=torch.long, device=device)
        return Bins(empty, empty, torch.zeros(tiles_x * tiles_y + 1, dtype=torch.long, device=device),
                    tiles_x, tiles_y)
    surf = torch.repeat_interleave(ids, per)
    # Rank of each pair inside its surfel's box -> (dx, dy) offsets.
    start = torch.cumsum(per, 0) - per
    rank = torch.arange(total, device=device) - torch.repeat_interleave(start, per)
    nx_r = torch.repeat_interleave(nx, per)
    tx = torch.repeat_interleave(tx0, per) + rank % nx_r
    ty = torch.repeat_interleave(ty0, per) + rank // nx_r
    tile_id = ty * tiles_x + tx
    # Lexicographic order (tile, depth, index) as one sort of unique int64 keys tile * N + rank,
    # rank = the surfel's place in a stable depth sort (ties by index): one sort of N depths and
    # one of the pairs, instead of two stable sorts of the pairs with a gather between them.
    n = depth_key.shape[0]
    rank = torch.empty(n, dtype=torch.long, device=device)
    rank[torch.sort(depth_key.detach(), stable=True).indices] = torch.arange(n, device=device)
    order = torch.sort(tile_id * n + rank[surf]).indices
    surf, tile_id = surf[order], tile_id[order]
    counts = torch.bincount(tile_id, minlength=tiles_x * tiles_y)
    offsets = torch.zeros(tiles_x * tiles_y + 1, dtype=torch.long, device=device)
    offsets[1:] = torch.cumsum(counts, 0)
    return Bins(surf, tile_id, offsets, tiles_x, tiles_y)
