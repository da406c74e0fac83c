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
    n = box.shape[0]
    b = box.long()
    # Per surfel its tile range (an empty box touches none). Written without boolean indexing and
    # with known output sizes, so on a GPU the only host sync is reading the number of pairs.
    tx0, ty0 = b[:, 0] // tile, b[:, 1] // tile
    nx = torch.where(b[:, 2] > b[:, 0], (b[:, 2] - 1) // tile - tx0 + 1, 0)
    ny = torch.where(b[:, 3] > b[:, 1], (b[:, 3] - 1) // tile - ty0 + 1, 0)
    per = nx * ny
    end = torch.cumsum(per, 0)
    total = int(end[-1]) if n else 0
    if total == 0:
        empty = torch.zeros(0, dtype=torch.long, device=device)
        return Bins(empty, empty, torch.zeros(tiles_x * tiles_y + 1, dtype=torch.long, device=device),
                    tiles_x, tiles_y)
    surf = torch.repeat_interleave(torch.arange(n, device=device), per, output_size=total)
    # Rank of each pair inside its surfel's box -> (dx, dy) offsets.
    rank = torch.arange(total, device=device) - (end - per)[surf]
    nx_r = nx[surf]
    tile_id = (ty0[surf] + rank // nx_r) * tiles_x + tx0[surf] + rank % nx_r
    # Lexicographic order (tile, depth, index) as one sort of unique int64 keys tile * N + rank,
    # rank = the surfel's place in a stable depth sort (ties by index): one sort of N depths and
    # one of the pairs, instead of two stable sorts of the pairs with a gather between them.
    depth_rank = torch.empty(n, dtype=torch.long, device=device)
    depth_rank[torch.sort(depth_key.detach(), stable=True).indices] = torch.arange(n, device=device)
    order = torch.sort(tile_id * n + depth_rank[surf]).indices
    surf, tile_id = surf[order], tile_id[order]
    # Tile t's pairs start at the first sorted tile id >= t.
    offsets = torch.searchsorted(tile_id, torch.arange(tiles_x * tiles_y + 1, device=device))
    return Bins(surf, tile_id, offsets, tiles_x, tiles_y)
