"""Row bands: render a large image band by band so memory follows a pair budget rather than the image size.

Every pixel is composited on its own, so an image can be drawn as horizontal bands of rows: shift the projected
centres up by the band's first row, composite a `height = band rows` image, and stack the bands. This is exact (the
same pairs, in the same order, with the same arithmetic) and gradients flow through the shift. A backend asks
`row_bands` for the split; it returns one band, i.e. no split, unless the screen boxes would enumerate more than
`MAX_PAIRS_PER_BAND` (Gaussian, pixel) pairs, so ordinary training renders never pay for it. A 4096 x 4096 render
of a Gaussian covering the whole image holds 16.8 M pairs; per-pair work arrays cost ~100 bytes each. (Exact up to
float rounding: the shifted centres round differently, as do the camera offsets that stack several cameras.)
"""

from __future__ import annotations

import torch
from torch import Tensor

MAX_PAIRS_PER_BAND = 1 << 23  # ~8.4 M pairs: ~1 GB of per-pair work arrays in torch_ref, far above a training step's


def row_bands(
    means2d: Tensor,  # [M, 2] projected centres (pixels) of the drawn entries, any camera
    half: Tensor,  # [M, 2] screen-box half extents in pixels
    width: int,
    height: int,
    max_pairs: int | None = None,
) -> list[tuple[int, int]]:
    """Half-open row ranges [(0, h), (h, 2h), ...] of one height h (the last band may be shorter) covering
    0..height, h as large as keeps every band's estimated pair count <= `max_pairs` (one row at the least).

    One height for every band means one compiled shape for a JIT backend (which may pad the last band to h). The
    estimate is an upper bound: every row a box touches (widened by a pixel) counts the box's full width.
    """
    budget = MAX_PAIRS_PER_BAND if max_pairs is None else int(max_pairs)
    if means2d.shape[0] == 0 or height <= 1:
        return [(0, height)]
    with torch.no_grad():
        # a box's rows x columns below are at most (2 h_x + 4)(2 h_y + 4): when even that sum fits, no need to look
        # closer (4 operations instead of ~15 on every render; NaN or inf fails the test and takes the long way)
        if float((half.detach().double() * 2.0 + 4.0).prod(-1).sum()) <= budget:
            return [(0, height)]
        m = torch.nan_to_num(means2d.detach().double(), nan=0.0, posinf=1e12, neginf=-1e12)
        h = torch.nan_to_num(half.detach().double(), nan=0.0, posinf=1e12, neginf=0.0)
        x0 = torch.floor(m[:, 0] - h[:, 0] - 1).clamp(0, width)
        x1 = torch.ceil(m[:, 0] + h[:, 0] + 1).clamp(0, width)
        y0 = torch.floor(m[:, 1] - h[:, 1] - 1).clamp(0, height).long()
        y1 = torch.ceil(m[:, 1] + h[:, 1] + 1).clamp(0, height).long()  # exclusive
        cols = (x1 - x0).clamp_min(0)
        if float((cols * (y1 - y0).clamp_min(0)).sum()) <= budget:
            return [(0, height)]
        per_row = torch.zeros(height + 1, dtype=torch.float64, device=m.device)  # on the Gaussians' device
        per_row.index_add_(0, y0, cols)
        per_row.index_add_(0, y1, -cols)
        cum = torch.cat([per_row.new_zeros(1), torch.cumsum(torch.cumsum(per_row, 0)[:height], 0)])  # [H + 1]
        rows = 1
        for k in range(2, height + 1):  # fewest bands first; ~2 sqrt(H) distinct heights to try
            rows = -(-height // k)
            starts = torch.arange(0, height, rows, device=cum.device)
            if float((cum[(starts + rows).clamp_max(height)] - cum[starts]).max()) <= budget:
                break
    return [(r0, min(r0 + rows, height)) for r0 in range(0, height, rows)]
