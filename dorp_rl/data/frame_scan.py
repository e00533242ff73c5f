"""A first pass over play frames: what moves in them, how many pieces and how small.

The code trainer reads an env through its frames before it trains: the frame size,
how many separate regions of a frame differ from the static background (the objects
the codes must tell apart), how small the smallest of them is and the pixel grid they
move on (a grid world drawn ``k`` pixels a cell puts every piece of one shape at places
``k`` pixels apart). Settings that depend
on the env (the number of one-hots, the object maps' resolution) are chosen from this
scan rather than set by hand (:class:`~dorp_rl.trainers.RepresentationConfig`).

The background is the per-pixel median over the scanned frames: whatever sits in one
place in most frames (floor, walls, a door that is mostly closed). A pixel is in the
foreground where any channel differs from it by more than ``tolerance``; pieces are
8-connected foreground regions. Objects that touch in a frame are counted as one there,
so the count is a high quantile over frames, not their mean.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields

import torch
import torch.nn.functional as F

__all__ = ["FrameScan", "scan_frames"]


@dataclass(frozen=True)
class FrameScan:
    """What :func:`scan_frames` saw in the play frames.

    Attributes:
        frame_shape: ``(C, H, W)`` of the frames.
        frames: frames scanned.
        pieces: pieces in a frame, at the ``quantile`` over frames (the objects to code;
            at least 1).
        pieces_median: the median count of pieces in a frame.
        smallest_piece: the shorter bounding-box side, in pixels, of the smallest pieces
            (a low quantile over all pieces seen; 0 when nothing moved).
        foreground_share: share of pixels that differ from the background, mean over frames.
        background: the per-pixel median frame, uint8 ``[C, H, W]``.
        motion_step: the grid the pieces move on, in pixels: the largest step ``k`` such
            that the pieces of one shape lie ``k`` pixels apart in both directions (their
            places modulo ``k`` agree for 95% of the pieces); 1 where none does (pieces
            placed at any pixel, or too few seen).
        colours: the colours of the pieces in a frame, at the ``quantile`` over frames
            (a piece's colour: the mean of its pixels, to steps of 32 of 255).
    """

    frame_shape: tuple[int, int, int]
    frames: int
    pieces: int
    pieces_median: float
    smallest_piece: int
    foreground_share: float
    background: torch.Tensor = field(repr=False, compare=False)
    motion_step: int = 1
    colours: int = 1

    @property
    def pieces_share_colours(self) -> bool:
        """Whether pieces of one colour move in the frames (fewer colours than pieces): the
        codes must tell them apart by their shapes alone."""
        return self.colours < self.pieces

    @property
    def plain_background(self) -> bool:
        """Whether the background is black everywhere (nothing to subtract)."""
        return not bool(self.background.any())

    def to_dict(self) -> dict:
        """The scalar fields (not the background image)."""
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name != "background"}


def _as_bytes(frames: torch.Tensor) -> torch.Tensor:
    """Frames ``[N, C, H, W]`` as int16 values in ``[0, 255]`` (uint8 or floats in [0, 1])."""
    if frames.dtype == torch.uint8:
        return frames.to(torch.int16)
    if frames.is_floating_point():
        return (frames.clamp(0, 1) * 255).round().to(torch.int16)
    raise ValueError(f"frames must be uint8 or floats in [0, 1], got {frames.dtype}.")


def _label_pieces(foreground: torch.Tensor) -> torch.Tensor:
    """Per pixel, the largest flat index of its piece (-1 on background), ``[N, H, W]``:
    8-connected foreground pixels form a piece (whatever their colours: a renderer's
    anti-aliased edges shade one object in many). Labels spread by repeated 3 x 3 maxima
    (background is -1, below every label) until nothing changes.
    """
    n, h, w = foreground.shape
    index = torch.arange(n * h * w, dtype=torch.float32).reshape(n, 1, h, w)
    mask = foreground.unsqueeze(1)
    background = torch.full_like(index, -1.0)
    labels = torch.where(mask, index, background)
    for _ in range(h * w):
        spread = torch.where(mask, F.max_pool2d(labels, 3, stride=1, padding=1), background)
        if torch.equal(spread, labels):
            break
        labels = spread
    return labels.squeeze(1).long()


def _motion_step(
    row: torch.Tensor, col: torch.Tensor, shape: torch.Tensor, largest: int, share: float = 0.95
) -> int:
    """The largest step ``k <= largest`` (pixels) such that, in each group of pieces of one
    ``shape`` (an int64 id per piece), ``share`` of the pieces have the group's most common
    place modulo ``k`` (``row``, ``col``: their top-left corners); 1 where no ``k > 1``
    does. Only groups of at least 8 pieces count (a lone piece fits every step)."""
    shapes, counts = shape.unique(return_counts=True)
    seen = torch.isin(shape, shapes[counts >= 8])
    if int(seen.sum()) < 16:
        return 1
    row, col, shape = row[seen], col[seen], shape[seen]
    for step in range(largest, 1, -1):
        place = (shape * step + row % step) * step + col % step
        places, number = place.unique(return_counts=True)
        group = places // (step * step)
        best = torch.zeros(int(group.max()) + 1, dtype=torch.long)
        best.scatter_reduce_(0, group, number, "amax")
        if int(best.sum()) >= share * row.shape[0]:
            return step
    return 1


def _colours_per_frame(
    values: torch.Tensor,
    foreground: torch.Tensor,
    ids: torch.Tensor,
    sizes: torch.Tensor,
    kept: torch.Tensor,
    frames: int,
    level: int = 32,
) -> torch.Tensor:
    """How many colours the kept pieces of each frame have, float ``[frames]``: a piece's
    colour is the mean of its pixels, each channel rounded to steps of ``level`` (a
    renderer's shaded edges move the mean less than that)."""
    pixels = values.permute(0, 2, 3, 1)[foreground].float()  # [P, C], in the order of ids
    total = torch.zeros(sizes.shape[0], pixels.shape[1]).index_add_(0, ids, pixels)
    mean = total[kept] / sizes[kept].unsqueeze(1)
    key = (mean / level).round().long()  # at most 8 levels a channel
    key = (key * torch.tensor([1, 16, 256])[: key.shape[1]]).sum(1)
    frame = kept.nonzero().squeeze(1) // (sizes.shape[0] // frames)
    pairs = (frame * 4096 + key).unique()
    return torch.bincount(pairs // 4096, minlength=frames).float()


@torch.no_grad()
def scan_frames(
    frames: torch.Tensor,
    max_frames: int = 2048,
    tolerance: int = 24,
    quantile: float = 0.95,
    min_pixels: int = 1,
) -> FrameScan:
    """Scans play frames ``[N, C, H, W]`` (uint8 or floats in ``[0, 1]``) for moving pieces.

    Args:
        frames: play frames, at least 2.
        max_frames: evenly spaced frames scanned at most.
        tolerance: a pixel differs from the background by more than this (of 255) in
            some channel to count as foreground.
        quantile: of the per-frame piece counts, the one reported as :attr:`FrameScan.pieces`.
        min_pixels: pieces of fewer pixels are noise and not counted.

    Examples:
        >>> import torch
        >>> from dorp_rl.data import scan_frames
        >>> frames = torch.zeros(10, 3, 20, 28, dtype=torch.uint8)
        >>> for i in range(10):  # two white squares in other places in every frame
        ...     frames[i, :, 3 * (i % 5) : 3 * (i % 5) + 3, 1:4] = 255
        ...     frames[i, :, 16:19, 6 + 2 * i : 8 + 2 * i] = 255
        >>> scan = scan_frames(frames)
        >>> scan.pieces, scan.smallest_piece
        (2, 2)
        >>> grid = torch.zeros(64, 1, 24, 24, dtype=torch.uint8)
        >>> for i in range(64):  # a 3 x 3 block on a grid of 3-pixel cells
        ...     r, c = 3 * (i % 8), 3 * ((5 * i) % 8)
        ...     grid[i, :, r : r + 3, c : c + 3] = 200
        >>> scan_frames(grid).motion_step, scan.motion_step
        (3, 1)
    """
    if frames.dim() != 4 or frames.shape[0] < 2:
        raise ValueError(
            f"scan_frames needs frames [N, C, H, W] with N >= 2, got shape {tuple(frames.shape)}."
        )
    count = min(int(frames.shape[0]), int(max_frames))
    index = torch.linspace(0, frames.shape[0] - 1, count).round().long()
    values = _as_bytes(frames[index.to(frames.device)].cpu())
    background = values.median(dim=0).values
    foreground = (values - background).abs().amax(1) > tolerance
    labels = _label_pieces(foreground)
    n, h, w = labels.shape
    flat = labels.flatten(1)
    own = torch.arange(n * h * w).reshape(n, h * w)
    roots = (flat == own) & foreground.flatten(1)
    # pixels and bounding box of every piece, gathered at its root index
    ids = labels[foreground]
    sizes = torch.bincount(ids, minlength=n * h * w)
    rows = torch.arange(h).view(1, h, 1).expand(n, h, w)[foreground]
    cols = torch.arange(w).view(1, 1, w).expand(n, h, w)[foreground]
    big = torch.full((n * h * w,), h + w, dtype=torch.long)
    small = torch.full((n * h * w,), -1, dtype=torch.long)
    row_lo = big.scatter_reduce(0, ids, rows, "amin")
    row_hi = small.scatter_reduce(0, ids, rows, "amax")
    col_lo = big.scatter_reduce(0, ids, cols, "amin")
    col_hi = small.scatter_reduce(0, ids, cols, "amax")
    kept = roots.flatten() & (sizes >= min_pixels)
    per_frame = kept.reshape(n, h * w).sum(1).float()
    heights, widths = (row_hi - row_lo + 1)[kept], (col_hi - col_lo + 1)[kept]
    sides = torch.minimum(heights, widths)
    smallest = int(sides.float().quantile(0.05).floor()) if sides.numel() else 0
    shape_id = (heights * (w + 1) + widths) * (h * w + 1) + sizes[kept]
    step = _motion_step(row_lo[kept], col_lo[kept], shape_id, largest=min(h, w) // 4)
    colours = _colours_per_frame(values, foreground, ids, sizes, kept, n)
    return FrameScan(
        frame_shape=tuple(int(d) for d in frames.shape[1:]),
        frames=count,
        pieces=max(1, int(per_frame.quantile(quantile).round())),
        pieces_median=float(per_frame.median()),
        smallest_piece=smallest,
        foreground_share=float(foreground.float().mean()),
        background=background.to(torch.uint8),
        motion_step=step,
        colours=max(1, int(colours.quantile(quantile).round())),
    )
